"""Run identity: a run's folder is its configuration, later stages find their inputs by the same rule,
and one root seed drives every stochastic part."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from hydra import compose
from omegaconf import OmegaConf

from tracegs.config.identity import derive_seed, scoped_values
from tracegs.config.tree import ConfigTree
from tracegs.config.validate import ConfigError, validate
from tracegs.location import CONF_DIR
from tracegs.pipeline.records import RUN_RECORD, check_run_record, migrate_older_folders, write_run_record
from tracegs.pipeline.report import ablation_inputs, swept_method_evaluations
from tracegs.pipeline.upstream import locate_artifacts
from tracegs.pipeline.variants import table3_variants

# Every part that draws random numbers, by its seed field.
SEED_FIELDS = ("stage.seed", "data.prepare.seed", "data.prepare.fit.seed", "data.datamodule.seed", "deploy.seed",
               "backbone.sampler.seed")


pytestmark = pytest.mark.usefixtures("hydra_context")  # tests/conftest.py


def run_dir(overrides: list[str], config_name: str = "train") -> str:
    return str(compose(config_name=config_name, overrides=overrides).run_dir)


def trained(entry_config, root: Path, overrides: list[str], product: str) -> Path:
    """The product a ``tracegs-train`` command line writes, made on disk under ``root`` (its own job), with the run
    record a finished run keeps beside it."""
    cfg = entry_config("train", [f"paths.root_dir={root}", *overrides])
    folder = Path(str(cfg.run_dir)) / product
    folder.mkdir(parents=True)
    write_run_record(cfg, cfg.stage.name, cfg.run_dir)
    return folder


@pytest.mark.parametrize("changed", [
    ["loss.lambda_ret=0.3"], ["optimizer.lr=3e-4"], ["teacher=v12"], ["policy=off"], ["seed=1"],
    ["stage.rollout_steps=3"], ["debug=fdr"], ["debug=limit"], ["data.prepare.clips_per_scene=4"],
    ["backbone.lora.rank=2"], ["experiment.stage1_steps=10"],
])
def test_a_changed_setting_gets_its_own_stage2_folder(changed):
    assert run_dir(["stage=stage2", *changed]) != run_dir(["stage=stage2"])


@pytest.mark.parametrize("unchanged", [
    ["trainer.log_every_n_steps=1"], ["trainer.enable_progress_bar=false"], ["data.prepare.workers=1"],
    ["stage.checkpoint_every_n_steps=5"], ["paths.weights_dir=/elsewhere"], ["evaluation.progress=false"],
])
def test_execution_settings_keep_the_folder(unchanged):
    assert run_dir(["stage=stage2", *unchanged]) == run_dir(["stage=stage2"])


def test_inputs_handed_in_by_path_are_known_by_their_content(tmp_path):
    """Two Stage-2 runs handed different Stage-1 adapters (or caches) are two runs; the same bytes at another
    path are the same run; a cache is known by its manifest."""
    first, second, copy = (tmp_path / name for name in ("a.safetensors", "b.safetensors", "c.safetensors"))
    first.write_bytes(b"adapter one")
    second.write_bytes(b"adapter two")
    copy.write_bytes(b"adapter one")
    named = {path: run_dir(["stage=stage2", f"stage.init_adapter={path}"]) for path in (first, second, copy)}
    assert named[first] != named[second] and named[first] == named[copy] != run_dir(["stage=stage2"])
    caches = []
    for name, manifest in (("x", "{}"), ("y", '{"clips": 1}')):
        (tmp_path / name).mkdir()
        (tmp_path / name / "manifest.json").write_text(manifest)
        (tmp_path / name / "shard.bin").write_bytes(name.encode())  # not hashed: the manifest stands for it
        caches.append(run_dir(["stage=stage2", f"data.datamodule.cache_dir={tmp_path / name}"]))
    assert caches[0] != caches[1]


def test_settings_a_stage_does_not_read_keep_its_folder():
    # Stage 1 reads neither lambda_ret nor the on/off-policy switch: every Table 3 variant shares it.
    assert run_dir(["stage=stage1", "loss.lambda_ret=0"]) == run_dir(["stage=stage1"])
    assert run_dir(["stage=stage1", "policy=off"]) == run_dir(["stage=stage1"])
    assert run_dir(["stage=stage1", "loss.lambda_align=2"]) != run_dir(["stage=stage1"])


def test_sweep_points_never_share_a_folder():
    points = [[f"seed={s}", f"loss.lambda_ret={r}", f"ablation={v}"]
              for s in (0, 1, 2) for r in (0.0, 0.15) for v in ("E", "F")]
    folders = [run_dir(["stage=stage2", *p]) for p in points]
    assert len(set(folders)) == len(points)


def test_a_folder_is_named_by_the_seed_and_the_digest_of_the_typed_values(entry_config):
    cfg = entry_config("train", ["stage=stage2", "seed=2", "loss.lambda_ret=0.3", "trainer.log_every_n_steps=1"])
    folder = Path(str(cfg.run_dir))
    assert re.fullmatch(r"seed2-[0-9a-f]{8}", folder.name) and folder.parent.name == "F"
    logged_less = entry_config("train", ["stage=stage2", "seed=2", "loss.lambda_ret=0.3"])
    assert str(logged_less.run_dir) == str(cfg.run_dir)  # how often it logs changes no product


def test_stage2_finds_the_stage1_and_baseline_runs_it_builds_on(entry_config, tmp_path):
    # The earlier stages were run with the experiment's shared settings and their own stage defaults, each by its
    # own command line (holding no Stage-2 override).
    shared = [f"paths.root_dir={tmp_path}", "seed=3", "data.prepare.clips_per_scene=4"]
    stage1 = trained(entry_config, tmp_path, [*shared, "stage=stage1", "loss.lambda_ret=0.3"], "stage1_adapter")
    baseline = trained(entry_config, tmp_path, [*shared, "stage=baseline"], "baseline_transformer")
    own = [*shared, "stage=stage2", "ablation=C", "optimizer.lr=1e-4", "loss.lambda_ret=0.3"]
    cfg = entry_config("train", own)
    locate_artifacts(cfg, ["baseline_weights", "stage1_adapter"])
    assert (Path(cfg.artifacts.stage1_adapter), Path(cfg.artifacts.baseline_weights)) == (stage1, baseline)
    assert cfg.stage.init_adapter == cfg.artifacts.stage1_adapter
    # The run's own folder keeps the name it had before its inputs were located.
    assert cfg.run_dir == run_dir(own)


@pytest.mark.parametrize("stage2_only", [
    "experiment.stage2_lr=3e-4", "experiment.stage2_steps=40", "stage.rollout_steps=3",
    "backbone.schedule.deploy_time_power=6", "backbone.schedule.deploy_steps=20", "backbone.sampler.guidance_scale=2",
])
def test_a_stage2_only_setting_reuses_the_baseline_and_stage1_runs(entry_config, stage2_only):
    # The Stage-2 sweep a researcher runs after `train stage=baseline` and `train stage=stage1` with no overrides:
    # it must find those runs, not ask for an A and a Stage 1 retrained under a setting they never read.
    cfg = entry_config("train", ["stage=stage2", stage2_only])
    locate_artifacts(cfg, ["baseline_weights", "stage1_adapter"])
    assert cfg.artifacts.baseline_weights == str(Path(run_dir(["stage=baseline"])) / "baseline_transformer")
    assert cfg.artifacts.stage1_adapter == str(Path(run_dir(["stage=stage1"])) / "stage1_adapter")
    assert cfg.run_dir != run_dir(["stage=stage2"])


def test_settings_a_stage_reads_still_rename_it():
    assert run_dir(["stage=baseline", "experiment.baseline_lr=1e-4"]) != run_dir(["stage=baseline"])
    assert run_dir(["stage=stage1", "experiment.baseline_lr=1e-4"]) != run_dir(["stage=stage1"])
    assert run_dir(["stage=stage1", "backbone.lora.rank=2"]) != run_dir(["stage=stage1"])
    assert run_dir(["stage=baseline", "backbone.lora.rank=2"]) == run_dir(["stage=baseline"])
    assert run_dir(["stage=stage1", "experiment.stage1_lr=3e-4"]) != run_dir(["stage=stage1"])
    assert run_dir(["stage=baseline", "experiment.stage1_lr=3e-4"]) == run_dir(["stage=baseline"])


def test_evaluation_finds_the_student_its_variant_trained(entry_config):
    cfg = entry_config("evaluate", ["ablation=E", "seed=1", "loss.lambda_ret=0.3"])
    locate_artifacts(cfg, ["student_adapter"])
    student = run_dir(["stage=stage2", "ablation=E", "seed=1", "loss.lambda_ret=0.3"])
    assert cfg.artifacts.student_adapter == str(Path(student) / "student_adapter")


TEST_ONLY = ["data.synthetic.test_seeds=[9001,9002]"]


@pytest.mark.parametrize("kind", ["baseline", "stage1", "stage2"])
def test_a_test_scene_list_never_renames_a_trained_product(kind):
    """A, Stage 1 and Stage 2 never see a test scene: another test list keeps their folders (and the train
    split's cache they read), and a validation list too."""
    stage = [f"stage={kind}"]
    assert run_dir([*stage, *TEST_ONLY]) == run_dir(stage)
    assert run_dir([*stage, "data.synthetic.val_seeds=[60]"]) == run_dir(stage)
    assert run_dir([*stage, "data.synthetic.train_seeds=[0,2,3]"]) != run_dir(stage)
    # Training reads latents: frames kept in its cache for inspection leave the trained product as it is.
    assert run_dir([*stage, "data.prepare.store_frames=true"]) == run_dir(stage)


def test_each_cache_is_named_by_the_scenes_of_its_split():
    def cache(split: str, *overrides: str) -> str:
        return str(compose(config_name="prepare", overrides=[f"data.prepare.split={split}", *overrides])
                   .data.prepare.cache_dir)

    for split, own, other in (("train", "data.synthetic.train_seeds=[0,2]", "data.synthetic.test_seeds=[9001]"),
                              ("test", "data.synthetic.test_seeds=[9001]", "data.synthetic.train_seeds=[0,2]"),
                              ("val", "data.synthetic.val_seeds=[60]", "data.synthetic.test_seeds=[9001]")):
        assert cache(split, own) != cache(split), split
        assert cache(split, other) == cache(split), split
    train = compose(config_name="evaluate", overrides=TEST_ONLY).data.datamodule.cache_dir
    assert train == compose(config_name="train").data.datamodule.cache_dir


def test_evaluation_on_other_test_scenes_finds_the_same_restorers(entry_config, tmp_path):
    """The embedded demo's models, evaluated on other test scenes: the same A and student, another evaluation."""
    baseline = trained(entry_config, tmp_path, ["stage=baseline"], "baseline_transformer")
    student = trained(entry_config, tmp_path, ["stage=stage2", "ablation=F"], "student_adapter")
    in_domain = entry_config("evaluate", [f"paths.root_dir={tmp_path}", "ablation=F"]).evaluation.out_dir
    cfg = entry_config("evaluate", [f"paths.root_dir={tmp_path}", "ablation=F", *TEST_ONLY])
    locate_artifacts(cfg, ["baseline_weights", "student_adapter"])
    assert (Path(cfg.artifacts.student_adapter), Path(cfg.artifacts.baseline_weights)) == (student, baseline)
    assert cfg.evaluation.out_dir != in_domain


@pytest.mark.parametrize("experiment", ["paper", "rehearsal"])
def test_evaluation_of_another_dataset_finds_the_students_of_the_training_data(entry_config, tmp_path, experiment):
    """Table 2: ``tracegs-evaluate experiment=paper data=mipnerf360`` loads the Stage-1 adapter and the student
    trained on DL3DV (the experiment's training_data) by the training command lines as typed, whatever the
    evaluated dataset's own settings; its folder is its own."""
    common = [f"paths.root_dir={tmp_path}", f"experiment={experiment}", "seed=1"]
    stage1 = trained(entry_config, tmp_path, [*common, "stage=stage1"], "stage1_adapter")
    student = trained(entry_config, tmp_path, [*common, "stage=stage2", "ablation=E"], "student_adapter")
    assert compose(config_name="train", overrides=[*common, "stage=stage2"]).data.name == "dl3dv"
    in_domain = entry_config("evaluate", [*common, "ablation=E"]).evaluation.out_dir
    cfg = entry_config("evaluate", [*common, "data=mipnerf360", "ablation=E", "data.source.root=/elsewhere/mip",
                                    "data.prepare.clips_per_scene=3"])
    locate_artifacts(cfg, ["stage1_adapter", "student_adapter"])
    assert (Path(cfg.artifacts.stage1_adapter), Path(cfg.artifacts.student_adapter)) == (stage1, student)
    assert cfg.evaluation.out_dir != in_domain and Path(str(cfg.evaluation.out_dir)).name.startswith("mipnerf360-")


def test_a_capture_is_restored_by_the_restorers_of_the_training_data(entry_config, tmp_path):
    """``tracegs-restore capture.path=...``: its data section describes the capture, yet it loads the A and student
    trained on the training data, and one line names the choice when two such students match."""
    common = [f"paths.root_dir={tmp_path}", "seed=2"]
    baseline = trained(entry_config, tmp_path, [*common, "stage=baseline"], "baseline_transformer")
    student = trained(entry_config, tmp_path, [*common, "stage=stage2"], "student_adapter")
    damaged = student.parent.with_name("seed2-00000000")  # a record cut short: its folder is passed over
    damaged.mkdir()
    (damaged / RUN_RECORD).write_text('{"data.name": "synth')
    cfg = entry_config("restore", common)
    locate_artifacts(cfg, ["baseline_weights", "student_adapter"])
    assert (Path(cfg.artifacts.baseline_weights), Path(cfg.artifacts.student_adapter)) == (baseline, student)
    trained(entry_config, tmp_path, [*common, "stage=stage2", "data.synthetic.train_seeds=[0,2]"], "student_adapter")
    with pytest.raises(ConfigError, match=r"'artifacts.student_adapter': 2 stage2 runs on synthetic match"):
        locate_artifacts(entry_config("restore", common), ["student_adapter"])


def test_training_data_names_where_the_students_are_looked_up(entry_config, tmp_path):
    """Restorers trained on a dataset of one's own are found by naming it as the training data."""
    common = [f"paths.root_dir={tmp_path}", "experiment=paper", "training_data=custom"]
    student = trained(entry_config, tmp_path, [*common, "data=custom", "stage=stage2"], "student_adapter")
    cfg = entry_config("evaluate", [*common, "data=mipnerf360"])
    locate_artifacts(cfg, ["student_adapter"])
    assert Path(cfg.artifacts.student_adapter) == student


def test_training_reads_the_cache_that_prepare_writes():
    prepared = compose(config_name="prepare", overrides=["seed=4", "data.prepare.clips_per_scene=4"])
    trained = compose(config_name="train", overrides=["seed=4", "data.prepare.clips_per_scene=4"])
    assert trained.data.datamodule.cache_dir == prepared.data.prepare.cache_dir
    held_out = compose(config_name="prepare", overrides=["seed=4", "data.prepare.clips_per_scene=4",
                                                         "data.prepare.split=test"])
    assert held_out.data.prepare.cache_dir != prepared.data.prepare.cache_dir
    other_seed = compose(config_name="train", overrides=["seed=5"])
    assert other_seed.data.datamodule.cache_dir != trained.data.datamodule.cache_dir


@pytest.mark.parametrize("overrides", [
    ["data.synthetic.train_seeds=[0,2]", "loss.lambda_ret=0.3"],
    ["artifacts.stage1_adapter=/some/where/adapter", "data.prepare.student_views=[3,6]"],
])
def test_folder_names_paste_safely_and_name_no_path(entry_config, overrides):
    """No '=' or ',' (override syntax) and no path: a name pastes into any command line."""
    name = Path(str(entry_config("train", ["stage=stage2", *overrides]).run_dir)).name
    assert re.fullmatch(r"seed0-[0-9a-f]{8}", name)


def test_one_root_spelled_two_ways_or_copied_is_one_run(tmp_path, monkeypatch):
    """Paths inside the root are identified relative to it: a relative spelling, a copy elsewhere."""
    def values(root: str) -> dict:
        cfg = compose(config_name="train", overrides=["stage=stage2", f"paths.root_dir={root}",
                                                      f"artifacts.stage1_adapter={root}/outputs/stage1/a"])
        return scoped_values(cfg, "stage2")

    monkeypatch.chdir(tmp_path)
    assert values(".") == values(str(tmp_path)) == values(str(tmp_path / "copy"))
    assert values(".")["artifacts.stage1_adapter"] == "<root>/outputs/stage1/a"


def test_a_capture_is_known_by_its_images_and_reconstruction(tmp_path):
    def identity(capture: Path) -> str:
        cfg = compose(config_name="restore", overrides=[f"capture.path={capture}"])
        return scoped_values(cfg, "restore")["capture.path"]

    capture = tmp_path / "mine"
    for name, data in (("images/0.png", b"a"), ("sparse/0/cameras.txt", b"b")):
        (capture / name).parent.mkdir(parents=True, exist_ok=True)
        (capture / name).write_bytes(data)
    moved = tmp_path / "elsewhere" / "mine"
    moved.parent.mkdir()
    import shutil

    shutil.copytree(capture, moved)
    assert identity(capture) == identity(moved) == identity(tmp_path / "elsewhere" / ".." / "mine")
    (capture / "images" / "0.png").write_bytes(b"edited")
    assert identity(capture) != identity(moved)
    before = identity(moved)
    (moved / "sparse" / "0" / "cameras.txt").write_bytes(b"edited")
    assert identity(moved) != before


def test_photos_are_known_by_their_bytes_and_a_video_by_its_own(tmp_path):
    """A folder of photos (no reconstruction yet) is known by its photos alone; a video by its bytes."""
    def identity(key: str, value: Path) -> str:
        return scoped_values(compose(config_name="restore", overrides=[f"{key}={value}"]), "restore")[key]

    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "a.jpg").write_bytes(b"a")
    (photos / "b.png").write_bytes(b"b")
    before = identity("capture.path", photos)
    (photos / "notes.txt").write_text("not a photo, never read")
    assert identity("capture.path", photos) == before
    (photos / "b.png").write_bytes(b"edited")
    assert identity("capture.path", photos) != before
    video = tmp_path / "walk.mp4"
    video.write_bytes(b"frames")
    first = identity("capture.video", video)
    video.write_bytes(b"other frames")
    assert first.startswith("content:") and identity("capture.video", video) != first


def test_a_folder_recorded_under_other_settings_is_refused_naming_the_keys(tmp_path):
    folder = tmp_path / "run"
    write_run_record(compose(config_name="train", overrides=["stage=stage2"]), "stage2", folder)
    check_run_record(compose(config_name="train", overrides=["stage=stage2", "trainer.log_every_n_steps=1"]),
                           "stage2", folder)
    assert OmegaConf.load(folder / "config.yaml").stage.name == "stage2"
    with pytest.raises(ConfigError, match=r"loss\.lambda_ret"):
        check_run_record(compose(config_name="train", overrides=["stage=stage2", "loss.lambda_ret=0.5"]),
                               "stage2", folder)


def test_a_product_finished_again_keeps_the_record_of_the_run_that_made_it(tmp_path):
    """A rerun or a later shard of a finished product writes no record: the resolved config kept beside it stays
    the first run's, even where the schema gained fields since (so a root an older version made reruns read-only)."""
    folder = tmp_path / "run"
    cfg = compose(config_name="train", overrides=["stage=stage2"])
    write_run_record(cfg, "stage2", folder)
    (folder / "config.yaml").write_text("written by an older version\n")
    write_run_record(cfg, "stage2", folder)
    assert (folder / "config.yaml").read_text() == "written by an older version\n"


def test_one_root_seed_derives_a_distinct_stream_for_every_part():
    per_seed = []
    for seed in (0, 1):
        cfg = compose(config_name="train", overrides=[f"seed={seed}"])
        seeds = [OmegaConf.select(cfg, key) for key in SEED_FIELDS]
        assert len(set(seeds)) == len(seeds), "two parts share a random stream"
        per_seed.append(seeds)
    assert all(a != b for a, b in zip(*per_seed)), "a part ignores the root seed"
    assert derive_seed(0, "training") == per_seed[0][0]


def test_scoped_values_resolve_without_the_run_folder():
    cfg = compose(config_name="evaluate", overrides=["seed=1"])
    values = scoped_values(cfg, "evaluate")
    assert values["seed"] == 1 and "evaluation.out_dir" not in values and "data.prepare.cache_dir" not in values


def test_the_cache_is_named_by_what_it_is_made_with():
    """A training or sampling setting keeps the paired-clip cache (a sweep over it re-prepares nothing); the
    codec and the frozen encoders name it, and so does the whole backbone when it makes the pseudo-targets."""
    def cache(*overrides: str) -> str:
        # A cache of ground-truth targets (A trained by this framework makes the embedded default's: its training
        # settings name that cache, tests/config/test_data_protocol.py).
        overrides = ["experiment=embedded_gt_targets", *overrides]
        return str(compose(config_name="train", overrides=overrides).data.datamodule.cache_dir)

    for training_setting in ("backbone.schedule.train_time_power=0", "backbone.transformer.prediction=velocity",
                             "backbone.lora.rank=2", "backbone.sampler.guidance_scale=2"):
        assert cache(training_setting) == cache(), training_setting
    assert cache("backbone.codec.latent_channels=16") != cache()
    assert cache("backbone.reference_encoder.patch_size=4") != cache()
    restorer = "data.prepare.pseudo_target=restorer"
    assert cache(restorer, "backbone.schedule.deploy_steps=7") != cache(restorer)
    assert cache(restorer, "data.prepare.pseudo_target_guidance=2") != cache(restorer)
    assert cache(restorer, "data.prepare.pseudo_target_strength=0.5") != cache(restorer)
    assert cache(restorer, "backbone.transformer.num_layers=3") != cache(restorer)


@pytest.mark.parametrize("experiment", ["embedded_gt_targets", "rehearsal"])
def test_settings_that_do_not_change_a_restoration_keep_a_restorer_made_cache(experiment):
    """Pseudo-targets from a frozen restorer loaded from its weights: its adapters, memory settings, where the encoders live, the
    training-time density and the deployment guidance never touch the cached bytes, so they keep the cache."""
    base = [f"experiment={experiment}", "data.prepare.pseudo_target=restorer"]

    def cache(*overrides: str) -> str:
        return str(compose(config_name="train", overrides=[*base, *overrides]).data.datamodule.cache_dir)

    for setting in ("backbone.lora.rank=4", "backbone.transformer.activation_checkpointing=0.5",
                    "backbone.offload_encoders=true", "backbone.sampler.guidance_scale=3",
                    "backbone.schedule.train_time_power=2", "backbone.sampler.seed=5"):
        assert cache(setting) == cache(), setting


def test_a_product_made_from_other_inputs_is_made_again(tmp_path):
    """Reuse is decided by the record and the content of the inputs, never by a checkpoint being there."""
    adapter = tmp_path / "stage1_adapter"
    adapter.mkdir()
    (adapter / "adapter_model.safetensors").write_bytes(b"1")
    cfg = compose(config_name="train", overrides=["stage=stage2", f"artifacts.stage1_adapter={adapter}",
                                                  "artifacts.baseline_weights=null"])
    folder = tmp_path / "run"
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "checkpoints" / "last.ckpt").write_bytes(b"a checkpoint")
    assert not check_run_record(cfg, "stage2", folder)  # no record: not finished, whatever it holds
    write_run_record(cfg, "stage2", folder)
    assert check_run_record(cfg, "stage2", folder)
    (adapter / "adapter_model.safetensors").write_bytes(b"retrained")
    assert not check_run_record(cfg, "stage2", folder)
    assert not (folder / "checkpoints").exists() and not (folder / RUN_RECORD).exists()


def test_a_record_read_back_compares_equal_to_its_run(tmp_path, monkeypatch):
    """The record holds root-relative paths; reading it back under the same root (as a relative spelling, the
    launch folder being the root) finds the same run, and so does a record holding the absolute path."""
    monkeypatch.chdir(tmp_path)
    cfg = compose(config_name="train", overrides=["stage=stage1", "paths.root_dir=.",
                                                  f"artifacts.baseline_weights={tmp_path}/outputs/baseline/a"])
    folder = tmp_path / "run"
    write_run_record(cfg, "stage1", folder)
    assert check_run_record(cfg, "stage1", folder)
    record = folder / RUN_RECORD
    values = json.loads(record.read_text())
    record.write_text(json.dumps({**values, "artifacts.baseline_weights": f"{tmp_path}/outputs/baseline/a"}))
    assert check_run_record(cfg, "stage1", folder)


def test_table_3_reads_the_evaluation_of_every_variant_on_each_dataset(entry_config, tmp_path):
    """``tracegs-report report.kind=ablation experiment=paper`` finds what ``tracegs-evaluate ablation=<v>`` and
    ``tracegs-evaluate ablation=<v> data=mipnerf360`` wrote, and names the first evaluation missing."""
    common = [f"paths.root_dir={tmp_path}", "experiment=paper"]
    report = [*common, "report.kind=ablation"]
    with pytest.raises(FileNotFoundError, match="no evaluation of variant A on dl3dv"):
        ablation_inputs(entry_config("report", report))
    written = {}
    for dataset in ("dl3dv", "mipnerf360"):
        for variant in table3_variants(ConfigTree.at(CONF_DIR)):
            chosen = [] if dataset == "dl3dv" else [f"data={dataset}"]
            evaluation = entry_config("evaluate", [*common, f"ablation={variant.name}", *chosen])
            folder = Path(str(evaluation.evaluation.out_dir))
            folder.mkdir(parents=True)
            (folder / "results.json").write_text("{}")
            write_run_record(evaluation, "evaluate", folder)
            written.setdefault(dataset, []).append(folder)
    assert ablation_inputs(entry_config("report", report)) == written


def test_tables_1_2_take_a_and_f_from_the_sweeps_evaluations(entry_config, tmp_path):
    """``tracegs-report report.kind=main report.main_from_sweep=true`` reads A's scores from what
    ``tracegs-evaluate ablation=A`` wrote and F's from ``ablation=F``'s (this command's variant), and names the
    first evaluation missing in one line."""
    common = [f"paths.root_dir={tmp_path}", "experiment=paper", "data=mipnerf360"]
    report = entry_config("report", [*common, "report.kind=main", "report.main_from_sweep=true"])
    with pytest.raises(FileNotFoundError, match="report.main_from_sweep: no evaluation of variant A on mipnerf360"):
        swept_method_evaluations(report)
    written = {}
    for variant, method in (("A", "baseline"), ("F", "tracegs")):
        folder = Path(str(entry_config("evaluate", [*common, f"ablation={variant}"]).evaluation.out_dir))
        (folder / "units").mkdir(parents=True)
        written[method] = folder
    assert swept_method_evaluations(entry_config("report", [*common, "report.kind=main",
                                                            "report.main_from_sweep=true"])) == written


def test_one_product_spelled_two_ways_is_one_folder(entry_config, tmp_path):
    """A folder's name follows from the typed values, so a command that types a default out names the folder its
    plain spelling names, before either exists: the same product is never made twice, beside itself."""
    root = f"paths.root_dir={tmp_path}"
    plain = entry_config("prepare", [root, "data.prepare.split=test"])
    views = ",".join(str(v) for v in plain.data.prepare.student_views)
    spelled = [root, "data.prepare.split=test", f"data.prepare.student_views=[{views}]"]
    assert entry_config("prepare", spelled).data.prepare.cache_dir == plain.data.prepare.cache_dir
    stage1 = entry_config("train", [root, "stage=stage1"])
    assert entry_config("train", [root, "stage=stage1", f"optimizer.lr={stage1.optimizer.lr}"]).run_dir \
        == stage1.run_dir
    assert not Path(stage1.run_dir).exists()


def older_root(entry_config, root: Path, overrides: list[str]) -> tuple[Path, Path]:
    """(today's folder, the older version's folder) of a ``tracegs-train`` command line under ``root``: a root
    made when names repeated the typed overrides (``seed0_<overrides>-<digest>``), holding a product."""
    expected = Path(str(entry_config("train", [f"paths.root_dir={root}", *overrides]).run_dir))
    older = expected.with_name(f"seed0_typed-{expected.name.rsplit('-', 1)[1]}")
    (older / "stage1_adapter").mkdir(parents=True)
    (older / "stage1_adapter" / "weights").write_bytes(b"trained")
    return expected, older


def test_a_folder_named_by_an_older_version_is_found_then_renamed_and_kept(entry_config, tmp_path):
    """A root made by an older version keeps its products: resolving a config finds the older folder where it
    lies and renames nothing; the command's migration step renames it to the name the typed values give,
    contents and all, and a twin of another spelling is left alone (and named in the log)."""
    overrides = [f"paths.root_dir={tmp_path}", "stage=stage1", "loss.lambda_ret=0.3"]
    expected, older = older_root(entry_config, tmp_path, overrides)
    twin = older.with_name(f"seed0_typed_again-{expected.name.rsplit('-', 1)[1]}")
    twin.mkdir()
    cfg = entry_config("train", overrides)
    assert Path(str(cfg.run_dir)) == older and older.is_dir() and not expected.exists()
    migrate_older_folders(cfg)
    assert Path(str(cfg.run_dir)) == expected and not older.exists() and twin.is_dir()
    assert (expected / "stage1_adapter" / "weights").read_bytes() == b"trained"


def test_printing_the_resolved_config_writes_nothing(entry_config, entry_point, tmp_path):
    overrides = [f"paths.root_dir={tmp_path}", "stage=stage1", "loss.lambda_ret=0.3"]
    _, older = older_root(entry_config, tmp_path, overrides)
    before = sorted(tmp_path.rglob("*"))
    run = entry_point("train", [*overrides, "--cfg", "job", "--resolve"], tmp_path)
    assert run.returncode == 0, run.stderr
    assert OmegaConf.create(run.stdout).run_dir == str(older)  # found where it lies
    assert sorted(tmp_path.rglob("*")) == before


def test_a_command_on_an_older_root_renames_the_folder_and_reuses_its_product(entry_config, entry_point, tmp_path):
    """The rerun promise on a root an older version made: the same command renames the product's folder and
    finds the product finished."""
    overrides = [f"paths.root_dir={tmp_path}", "stage=baseline"]
    cfg = entry_config("train", overrides)
    expected = Path(str(cfg.run_dir))
    older = expected.with_name(f"seed0_typed-{expected.name.rsplit('-', 1)[1]}")
    (older / "baseline_transformer").mkdir(parents=True)
    write_run_record(cfg, "baseline", older)
    run = entry_point("train", overrides, tmp_path)
    assert run.returncode == 0, run.stderr
    assert not older.exists() and (expected / "baseline_transformer").is_dir()
    assert "renamed to" in run.stdout and "nothing to do" in run.stdout


@pytest.mark.parametrize(("variant", "dense_views", "final_fits"), [("C", [12, None], False), ("B", [None], True)])
def test_a_variant_brings_its_teacher_and_keeps_a_and_stage1(entry_config, tmp_path, variant, dense_views, final_fits):
    """``tracegs-prepare ablation=C`` then ``tracegs-train stage=stage2 ablation=C``, as typed: the cache the
    variant trains on holds its teacher condition (C: 12 views; B: the sparse fits' final snapshot), and A and
    Stage 1 are the default's, found in the same folders."""
    root = f"paths.root_dir={tmp_path}"
    prepared = entry_config("prepare", [root, f"ablation={variant}"])
    assert list(prepared.data.prepare.dense_views) == dense_views
    assert prepared.data.prepare.student_final_fits is final_fits
    student = entry_config("train", [root, "stage=stage2", f"ablation={variant}"])
    validate(student)  # the teacher is prepared: not refused
    default = entry_config("train", [root, "stage=stage2"])
    assert student.data.datamodule.cache_dir == prepared.data.prepare.cache_dir != default.data.datamodule.cache_dir
    for cfg in (student, default):
        locate_artifacts(cfg, ["baseline_weights", "stage1_adapter"])
    assert (student.artifacts.baseline_weights, student.artifacts.stage1_adapter) == \
        (default.artifacts.baseline_weights, default.artifacts.stage1_adapter)
    assert student.run_dir != default.run_dir
