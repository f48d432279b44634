"""benchmarks/gpu_check.py at the rehearsal's shapes on the CPU: every section of the one GPU check (its own
functions, the JSON it writes) and benchmarks/paper_gpu_hours.py reading that JSON."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import gpu_check  # noqa: E402  (a script directory, not a package)
import paper_gpu_hours  # noqa: E402


@pytest.fixture(scope="module")
def checked(tmp_path_factory, rehearsal_root) -> tuple[dict, Path]:
    """One check at rehearsal shapes on the rehearsal's weights tree (tiny random models in the paper's layouts)."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        from paper_weights import install_vggt_double

        install_vggt_double(monkeypatch)
        out = tmp_path_factory.mktemp("gpu_check")
        # the speed section has its own fixture; the demo section runs the whole demo (tens of minutes here)
        others = [name for name in gpu_check.SECTIONS if name not in ("speed", "demo")]
        record = gpu_check.main(["--scale", "rehearsal", "--fit-iterations", "20", "--out", str(out),
                                 "--sections", ",".join(others), f"paths.root_dir={rehearsal_root}"])
    return record, out


@pytest.fixture(scope="module")
def sped(tmp_path_factory) -> tuple[dict, Path]:
    """The restorer and speed sections at rehearsal shapes; compiled blocks on torch.compile's "eager" backend (the
    CPU's inductor builds C++ for minutes; it runs here, 72 s for the embedded forward alone)."""
    out = tmp_path_factory.mktemp("speed")
    record = gpu_check.main(["--scale", "rehearsal", "--sections", "restorer,speed", "--out", str(out),
                             f"paths.root_dir={tmp_path_factory.mktemp('root')}",
                             "backbone.transformer.compile_backend=eager"])
    return record, out


def test_every_section_measures_and_the_json_is_what_it_printed(checked):
    record, out = checked
    assert json.loads((out / "gpu_check.json").read_text()) == json.loads(json.dumps(record, default=str))
    assert "rasterizer ..." in (out / "gpu_check.log").read_text()
    assert not [name for name, figures in record.items() if isinstance(figures, dict) and "error" in figures]
    assert record["device"]["name"] == "cpu" and record["device"]["torch"] == torch.__version__
    fits = record["rasterizer"]["fits"]
    assert [fit["backend"] for fit in fits] == ["torch", "compiled"]  # on a GPU: gsplat, then compiled
    assert all(fit["iterations"] == 20 and fit["iterations_per_s"] > 0 and math.isfinite(fit["psnr_held_out"])
               for fit in fits)
    restorer = record["restorer"]
    assert all(restorer[unit]["seconds"] > 0 for unit in ("deploy_step", "rollout_step"))
    stage2 = record["stage2"]
    assert stage2["batch_size"] == 2 and stage2["rollout_steps"] == 10  # the paper's batch and N
    assert len(stage2["iterations"]) == 2 and stage2["iteration"] == stage2["iterations"][1]
    assert all(iteration["seconds"] > 0 for iteration in stage2["iterations"])
    assert record["vae"]["vae_clip"] == [9, 32, 48] and record["vae"]["vae_decode"]["seconds"] > 0


def test_present_weights_are_loaded_and_restore_a_clip_missing_ones_are_named(checked):
    weights = checked[0]["weights"]
    assert set(weights["paths"]) == {"gsfixer_transformer", "cogvideox_vae", "t5_text_encoder", "t5_tokenizer",
                                     "dinov2", "vggt", "blip2_captioner", "vgg16_lpips"}
    assert weights["paths"]["blip2_captioner"] is None  # the rehearsal captions from caption.txt
    assert weights["missing"] == []
    assert weights["load_seconds"] > 0 and weights["restore_clip"]["seconds"] > 0


def test_missing_weights_are_named_and_nothing_is_loaded(tmp_path):
    cfg = gpu_check.compose("rehearsal", (f"paths.root_dir={tmp_path}",))
    weights = gpu_check.weights_section(cfg, torch.device("cpu"), gpu_check.Clock(torch.device("cpu")))
    assert weights["missing"] == ["cogvideox_vae", "dinov2", "gsfixer_transformer", "t5_text_encoder",
                                  "t5_tokenizer", "vgg16_lpips", "vggt"]
    assert "load_seconds" not in weights


def test_a_rerun_of_one_section_replaces_its_figures_alone(checked, rehearsal_root, tmp_path):
    record, out = checked
    (tmp_path / "gpu_check.json").write_text((out / "gpu_check.json").read_text())
    rerun = gpu_check.main(["--scale", "rehearsal", "--sections", "vae", "--out", str(tmp_path),
                            f"paths.root_dir={rehearsal_root}"])
    assert rerun["restorer"] == json.loads(json.dumps(record["restorer"]))  # kept from the first run
    assert json.loads((tmp_path / "gpu_check.json").read_text()) == json.loads(json.dumps(rerun, default=str))
    assert "vae ..." in (tmp_path / "gpu_check.log").read_text()
    assert "restorer ..." not in (tmp_path / "gpu_check.log").read_text()  # not run again


def test_an_unknown_section_is_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit):
        gpu_check.main(["--scale", "rehearsal", "--sections", "vae,raster", "--out", str(tmp_path)])
    assert "--sections: unknown raster" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_a_failing_section_is_recorded_and_the_others_still_run(tmp_path):
    record = {}

    def broken(publish) -> dict:
        raise RuntimeError("CUDA out of memory\nsecond line")

    def measured_then_broken(publish):
        yield "deploy_step", {"seconds": 1.5}
        raise RuntimeError("CUDA out of memory\nsecond line")

    def published_then_broken(publish) -> dict:
        publish("iterations", [{"seconds": 140.0}])
        raise RuntimeError("killed")

    saved = []
    gpu_check.section("restorer", measured_then_broken, record, lambda: saved.append(dict(record["restorer"])))
    gpu_check.section("vae", broken, record)
    gpu_check.section("stage2", published_then_broken, record, lambda: saved.append(dict(record["stage2"])))
    gpu_check.section("device", lambda publish: {"name": "cpu"}, record)
    assert saved == [{"deploy_step": {"seconds": 1.5}}, {"iterations": [{"seconds": 140.0}]}]  # before the failure
    assert record["restorer"]["deploy_step"] == {"seconds": 1.5}  # what was measured before the failure stays
    assert record["stage2"]["iterations"] == [{"seconds": 140.0}]
    assert record["restorer"]["error"] == record["vae"]["error"] == "RuntimeError: CUDA out of memory"
    assert record["device"]["name"] == "cpu"


def test_without_a_gpu_nothing_is_measured(capsys, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    assert gpu_check.main(["--out", str(tmp_path)]) is None
    assert capsys.readouterr().out.strip() == "no GPU: nothing measured"
    assert not list(tmp_path.iterdir())


def test_the_estimate_reads_the_measured_seconds(checked, capsys):
    record, out = checked
    assumed = paper_gpu_hours.main([])
    measured = paper_gpu_hours.main(["--measured", str(out / "gpu_check.json")])
    unit, sources = measured["unit_seconds"], measured["unit_sources"]
    assert unit["transformer_forward"] == record["restorer"]["rollout_step"]["seconds"]
    assert unit["vae_encode"] == record["vae"]["vae_encode"]["seconds"]
    assert sources["transformer_forward"] == "measured on cpu"
    assert sources["fit_iteration"] == sources["caption"] == "assumed (one A100)"
    assert assumed["unit_sources"]["transformer_forward"] == "assumed (one A100)"
    assert measured["gpu_hours_total"] != assumed["gpu_hours_total"]
    assert "transformer_forward: measured on cpu" in capsys.readouterr().out


def test_an_unreadable_measurement_is_refused_in_one_line(tmp_path):
    broken = tmp_path / "gpu_check.json"
    broken.write_text("{not json")
    with pytest.raises(SystemExit, match="--measured .*gpu_check.json: not a readable gpu_check.json"):
        paper_gpu_hours.main(["--measured", str(broken)])


def test_the_speed_section_times_a_stage2_iteration_under_each_switch(sped):
    record, out = sped
    assert json.loads((out / "gpu_check.json").read_text()) == json.loads(json.dumps(record, default=str))
    speed = record["speed"]
    assert "error" not in speed and speed["batch_size"] == 2 and speed["rollout_steps"] == 2
    for name in gpu_check.SPEED_SETTINGS:
        assert set(speed[name]) == {"seconds", "peak_mib", "first_seconds"}, name
        assert speed[name]["seconds"] > 0 and speed[name]["peak_mib"] is None  # no allocator statistics on a CPU
    # two attentions in each of the rehearsal's two blocks per forward; a student and a teacher forward per visited
    # state (the batch in one call); a checkpointed block's recomputation in backward runs outside the recording
    assert speed["attention_kernels"] == {"flash": 2 * 2 * 2 * speed["rollout_steps"]}
    assert speed["best"] == min(gpu_check.SPEED_SETTINGS, key=lambda name: speed[name]["seconds"])


def test_a_failing_setting_records_its_error_and_the_others_are_timed(tmp_path, monkeypatch):
    monkeypatch.setattr(gpu_check, "SPEED_SETTINGS", {
        "as_configured": (),
        "compile_blocks": ("backbone.transformer.compile_blocks=true", "backbone.transformer.compile_backend=nonesuch")})
    figures = {}
    best = gpu_check.speed_section("rehearsal", (f"paths.root_dir={tmp_path}",), torch.device("cpu"), tmp_path, 1,
                                   figures.__setitem__)
    assert figures["compile_blocks"]["error"].startswith(
        "ConfigError: config field 'backbone.transformer.compile_backend': 'nonesuch' is not a torch.compile backend")
    assert "\n" not in figures["compile_blocks"]["error"]
    assert figures["as_configured"]["seconds"] > 0 and best == {"best": "as_configured"}


def test_the_estimate_takes_the_fastest_measured_stage2_setting(sped, tmp_path, capsys):
    record, out = sped
    measured = paper_gpu_hours.main(["--measured", str(out / "gpu_check.json")])
    speed, forward = record["speed"], record["restorer"]["rollout_step"]["seconds"]
    per_state = speed[speed["best"]]["seconds"] / (speed["batch_size"] * speed["rollout_steps"])
    assert measured["unit_seconds"]["training_forward_factor"] == max(per_state - forward, forward) / forward
    assert measured["unit_sources"]["training_forward_factor"] == (
        f"measured on cpu (Stage 2 with speed setting {speed['best']})")
    assert measured["paper_gpu_hours"] == 480
    printed = capsys.readouterr().out
    scope = f"{measured['gpu_hours_paper_scope']:10.1f}  that preparation + Stage 1 + one student, against the paper's 480"
    assert scope in printed and f"Stage 2 with speed setting {speed['best']}" in printed
    # a faster setting is the one taken; a stage2 section's iteration at the paper's N competes as configured
    slow = {**record, "speed": {**speed, "compile_blocks": {"seconds": 1e-3, "peak_mib": None, "first_seconds": 1.0}},
            "stage2": {"batch_size": 2, "rollout_steps": 10, "iteration": {"seconds": 1e-6, "peak_mib": None},
                       "iterations": [{"seconds": 1.0}, {"seconds": 1e-6}]}}
    (tmp_path / "gpu_check.json").write_text(json.dumps(slow))
    fastest = paper_gpu_hours.main(["--measured", str(tmp_path / "gpu_check.json")])
    assert fastest["unit_sources"]["training_forward_factor"] == "measured on cpu (Stage 2 as configured)"
    del slow["stage2"]
    (tmp_path / "gpu_check.json").write_text(json.dumps(slow))
    faster = paper_gpu_hours.main(["--measured", str(tmp_path / "gpu_check.json")])
    assert faster["unit_sources"]["training_forward_factor"].endswith("with speed setting compile_blocks)")
    # a student state costs at least one forward: the factor's floor
    assert faster["unit_seconds"]["training_forward_factor"] == 1.0 <= measured["unit_seconds"]["training_forward_factor"]


@pytest.mark.parametrize("device", ["cuda", "cpu"])
def test_the_demo_sections_command_composes_and_validates_on_any_machine(device, tmp_path):
    """The demo section's ``tracegs-demo`` command line is a valid configuration here, without a GPU: it is refused
    only by the device check when it runs (below)."""
    from hydra import compose, initialize_config_dir

    from tracegs.config.schema import register_configs
    from tracegs.config.validate import validate
    from tracegs.location import CONF_DIR

    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="demo", overrides=gpu_check.demo_overrides(torch.device(device), tmp_path))
    validate(cfg)
    on_gpu = device == "cuda"
    assert cfg.trainer.accelerator == ("gpu" if on_gpu else "cpu") and int(cfg.trainer.devices) == 1
    assert cfg.data.prepare.fit.backend == ("gsplat" if on_gpu else "auto")
    assert cfg.trainer.precision == ("bf16-mixed" if on_gpu else "32-true")


def test_the_demo_on_a_gpu_is_refused_in_one_line_where_there_is_none(entry_point, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    root = tmp_path / "root"
    run = entry_point("demo", gpu_check.demo_overrides(torch.device("cuda"), root), tmp_path)
    assert run.returncode == 2
    (line,) = run.stderr_lines()
    assert line.startswith("tracegs-demo: error: config field 'trainer.accelerator': 'gpu' needs a CUDA device and "
                           f"this machine has none (torch {torch.__version__}, ")
    assert line.endswith("; run with trainer=cpu here")
    assert not root.exists() or not list(root.rglob("*.safetensors"))  # refused before any work


def test_a_required_fused_kernel_stops_the_first_training_step_and_leaves_no_recording(tmp_path):
    """The training callback (tracegs.training.attention) in the Stage-2 step the check times, on a machine whose
    only attention kernel is the math fallback."""
    from torch.nn.attention import SDPBackend, sdpa_kernel

    from tracegs.errors import ConfigError
    from tracegs.training.attention import AttentionKernelCheck

    cfg = gpu_check.compose("rehearsal", (f"paths.root_dir={tmp_path}",))
    backbone = gpu_check.random_backbone(cfg)
    gpu_check.make_random_adapter(backbone, tmp_path / "adapter", "cpu")
    module = gpu_check.stage2_module(backbone, cfg.stage.memory_mode, 1, tmp_path / "adapter", "cpu",
                                     cfg.stage.guidance_scale)
    check, finished = AttentionKernelCheck(require_fused=True), []
    with sdpa_kernel(SDPBackend.MATH), pytest.raises(ConfigError, match="require_fused_attention': attention would "
                                                                         "run on PyTorch's math kernel on cpu"):
        gpu_check.train_two_iterations(module, gpu_check.stage2_batch(cfg, backbone, torch.device("cpu")),
                                       cfg.trainer.precision, torch.device("cpu"), finished.append, [check])
    assert finished == [] and check.kernels == {"math": 1}  # stopped in the first step, at its first call
    assert torch._C._len_torch_function_stack() == 0  # the recording ended with the step
