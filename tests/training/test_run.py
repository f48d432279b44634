"""``train_stage`` end to end: baseline -> Stage 1 -> Stage 2 through the real DataModule and Trainer."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import pytest
import torch
from support.training import (
    CHANNELS,
    TINY_LORA,
)
from support.training_runs import BACKBONE, config, train_baseline_and_stage1

from tracegs.errors import ConfigMismatchError
from tracegs.restorer.adapters import read_adapter
from tracegs.restorer.config import CodecConfig, ReferenceEncoderConfig
from tracegs.training.config import OptimizerConfig, StageConfig, TrainConfig
from tracegs.training.run import train_stage


@pytest.fixture(scope="module")
def stages(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("run")
    return tmp, *train_baseline_and_stage1(tmp)


def logged_columns(run_dir: Path) -> set[str]:
    columns = set()
    for metrics in (run_dir / "csv").glob("version_*/metrics.csv"):
        with open(metrics) as handle:
            columns |= set(next(csv.reader(handle)))
    return columns


def test_stages_chain_and_log_every_term(stages):
    tmp, _, baseline, stage1 = stages
    assert (baseline / "config.json").is_file() and (stage1 / "adapter_config.json").is_file()
    assert {"train/fm_student", "train/grad_norm", "train/lr", "train/samples_per_sec"} <= logged_columns(
        tmp / "baseline"
    )
    assert {"train/fm_student", "train/fm_teacher", "train/align", "train/loss"} <= logged_columns(tmp / "stage1")
    assert any((tmp / "stage1" / "tensorboard").glob("events.out.tfevents.*"))
    assert (tmp / "stage1" / "checkpoints" / "last.ckpt").is_file()


@pytest.mark.parametrize("interrupt_at", [2, 3], ids=["epoch-boundary", "mid-epoch"])
def test_stage2_resumed_at_a_checkpoint_matches_uninterrupted(stages, interrupt_at):
    tmp, cache, baseline, stage1 = stages
    extra = dict(base_weights=str(baseline), init_adapter=str(stage1))
    full_dir = tmp / "full"
    full = full_dir / "student_adapter"
    if not full.exists():
        train_stage(config(tmp, cache, "stage2", 4, "full", **extra))
    assert {"train/traj", "train/ret", "train/loss"} <= logged_columns(full_dir)
    # 4 clips in batches of 2 make 2 steps an epoch: stopping after step 2 ends an epoch, after step 3 it
    # leaves epoch 1 half done, and the rerun to 4 steps resumes from last.ckpt at the next unseen batch.
    out = f"interrupted_{interrupt_at}"
    train_stage(config(tmp, cache, "stage2", interrupt_at, out, **extra))
    resumed = train_stage(config(tmp, cache, "stage2", 4, out, **extra))
    a, b = read_adapter(full)[0], read_adapter(resumed)[0]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    # Bitwise: the saved adapter files are identical, byte for byte.
    assert (full / "adapter_model.safetensors").read_bytes() == (resumed / "adapter_model.safetensors").read_bytes()


def logged_values(run_dir: Path, column: str) -> list[float]:
    (metrics,) = (run_dir / "csv").glob("version_*/metrics.csv")
    with open(metrics) as handle:
        return [float(row[column]) for row in csv.DictReader(handle) if row.get(column)]


def test_learning_rate_warms_up_then_follows_the_configured_decay(stages):
    tmp, cache, _, _ = stages
    train_stage(config(tmp, cache, "baseline", 5, "cosine", decay="cosine"))
    # warm-up over 2 steps, then a cosine from 3e-3 at step 2 to zero at step 5
    assert logged_values(tmp / "cosine", "train/lr") == pytest.approx([1.5e-3, 3e-3, 3e-3, 2.25e-3, 0.75e-3])
    assert logged_values(tmp / "baseline", "train/lr") == pytest.approx([1.5e-3, 3e-3])
    with pytest.raises(ValueError, match="optimizer.decay"):
        OptimizerConfig(decay="linear")


def test_stage2_without_stage1_adapter_fails_clearly(stages):
    tmp, cache, baseline, _ = stages
    with pytest.raises(FileNotFoundError, match="stage.init_adapter"):
        train_stage(config(tmp, cache, "stage2", 1, "missing", base_weights=str(baseline),
                           init_adapter=str(tmp / "nope.safetensors")))


def test_config_accepts_a_matching_dictconfig_and_rejects_bad_fields():
    from omegaconf import OmegaConf

    from tracegs.training.run import as_train_config

    node = OmegaConf.create({"stage": {"name": "stage1", "max_steps": 7}, "loss": {"lambda_align": 0.5}})
    cfg = as_train_config(node)
    assert isinstance(cfg, TrainConfig) and cfg.stage.max_steps == 7 and cfg.loss.lambda_align == 0.5
    with pytest.raises(ValueError, match="stage.memory_mode"):
        as_train_config(OmegaConf.create({"stage": {"memory_mode": "fast"}}))


def test_resuming_under_another_restorer_configuration_fails_naming_the_field(stages):
    tmp, cache, _, _ = stages
    first = config(tmp, cache, "baseline", 1, "reconfigured")
    train_stage(first)
    changed = config(tmp, cache, "baseline", 2, "reconfigured")
    changed.backbone = dataclasses.replace(
        BACKBONE, transformer=dataclasses.replace(BACKBONE.transformer, prediction="residual"))
    with pytest.raises(ValueError, match="'prediction': \\('velocity', 'residual'\\)"):
        train_stage(changed)


def test_checkpoints_carry_their_hyperparameters_for_load_from_checkpoint(stages):
    from tracegs.restorer.adapters import adapter_parameters
    from tracegs.restorer.build import build_backbone
    from tracegs.training.stage2 import Stage2DistillationModule

    tmp, cache, baseline, stage1 = stages
    cfg = config(tmp, cache, "stage2", 2, "reloaded", base_weights=str(baseline), init_adapter=str(stage1))
    cfg.loss = dataclasses.replace(cfg.loss, lambda_ret=0.25)
    student = train_stage(cfg)
    checkpoint = tmp / "reloaded" / "checkpoints" / "last.ckpt"
    backbone = build_backbone(dataclasses.replace(
        BACKBONE, transformer=dataclasses.replace(BACKBONE.transformer, pretrained_path=str(baseline))))
    module = Stage2DistillationModule.load_from_checkpoint(
        checkpoint, transformer=backbone.transformer, schedule=backbone.schedule, weights_only=True)
    assert module.lambda_ret == 0.25 and module.rollout_steps == 3
    assert module.optimizer_cfg == cfg.optimizer
    saved = read_adapter(student)[0]
    reloaded = adapter_parameters(module.transformer, "student")
    assert len(reloaded) == len(saved)
    assert sum(float(p.detach().abs().sum()) for p in reloaded) == pytest.approx(
        sum(float(t.float().abs().sum()) for t in saved.values()), rel=1e-6)


def test_a_saved_student_adapter_loads_with_peft_directly(stages):
    from peft import PeftModel, get_peft_model_state_dict

    from tracegs.restorer.transformer import ReferenceGuidedTransformer

    tmp, cache, baseline, stage1 = stages
    student = train_stage(config(tmp, cache, "stage2", 1, "for_peft", base_weights=str(baseline),
                                 init_adapter=str(stage1)))
    # As the README shows: diffusers loads the baseline transformer, peft the student adapter.
    base = ReferenceGuidedTransformer.from_pretrained(str(baseline))
    model = PeftModel.from_pretrained(base, str(student))
    loaded = {k.removeprefix("base_model.model."): v for k, v in get_peft_model_state_dict(model).items()}
    saved = read_adapter(student)[0]
    assert loaded.keys() == saved.keys() and all(torch.equal(loaded[k], saved[k]) for k in saved)
    assert any(float(v.abs().sum()) > 0 for k, v in saved.items() if "lora_B" in k)


def test_resuming_with_another_lora_rank_names_both_shapes(stages):
    tmp, cache, baseline, _ = stages
    train_stage(config(tmp, cache, "stage1", 1, "rerank", base_weights=str(baseline)))
    changed = config(tmp, cache, "stage1", 2, "rerank", base_weights=str(baseline))
    changed.backbone = dataclasses.replace(BACKBONE, lora=dataclasses.replace(TINY_LORA, rank=4, alpha=4))
    with pytest.raises(ConfigMismatchError, match=r"stage.resume_from: .*lora_A.* \(2, 16\) in the checkpoint, "
                                                  r"\(4, 16\) now; was backbone.lora.rank changed"):
        train_stage(changed)


def test_training_builds_no_encoder(stages):
    """The cache holds latents, reference tokens and text embeddings: a training run neither loads the VAE,
    DINOv2, VGGT or T5 nor needs their folders (here configured at paper kinds, pointing nowhere)."""
    tmp, cache, baseline, stage1 = stages
    cfg = config(tmp, cache, "stage2", 1, "no_encoders", base_weights=str(baseline), init_adapter=str(stage1))
    absent = str(tmp / "absent")
    cfg.backbone = dataclasses.replace(
        BACKBONE,
        codec=CodecConfig(kind="cogvideox", latent_channels=CHANNELS, pretrained_path=absent),
        reference_encoder=ReferenceEncoderConfig(kind="dinov2_vggt", dino_path=absent, vggt_path=absent),
        text_encoder=dataclasses.replace(BACKBONE.text_encoder, kind="t5", pretrained_path=absent),
    )
    assert (train_stage(cfg) / "adapter_model.safetensors").is_file()


def transformer_weights(state: dict) -> dict[str, torch.Tensor]:
    return {k.removeprefix("transformer."): v for k, v in state.items() if k.startswith("transformer.")}


def checkpointed_weights_and_their_average(run: Path, steps: int, decay: float
                                           ) -> tuple[list[dict[str, torch.Tensor]], dict[str, torch.Tensor]]:
    """The current weights w_1 ... w_steps of a run's step checkpoints and their moving average
    e_k = d e_(k-1) + (1 - d) w_k (e_1 = w_1), computed here from the checkpoints, independently of the module."""
    current = [transformer_weights(torch.load(run / "checkpoints" / f"step{k:06d}.ckpt",
                                              weights_only=True)["current_model_state"]) for k in range(1, steps + 1)]
    average = dict(current[0])
    for weights in current[1:]:
        average = {k: decay * average[k] + (1 - decay) * weights[k] for k in average}
    return current, average


def test_stage1_exports_the_moving_average_of_its_adapter(stages):
    """``stage.ema_decay`` at Stage 1: the exported adapter is e_k = d e_(k-1) + (1 - d) w_k over the adapter
    weights w_k after each step (e_1 = w_1), not the last step's weights."""
    from safetensors.torch import load_file

    tmp, cache, baseline, _ = stages
    decay = 0.5
    product = train_stage(config(tmp, cache, "stage1", 3, "ema_stage1", ema_decay=decay, keep_checkpoints=-1,
                                 base_weights=str(baseline)))
    current, expected = checkpointed_weights_and_their_average(tmp / "ema_stage1", 3, decay)
    exported = load_file(str(product / "adapter_model.safetensors"))
    # peft writes "base_model.model.<module>.lora_A.weight" for the module's "<module>.lora_A.aligned.weight".
    averaged = {k.replace(".aligned.", "."): v for k, v in expected.items() if ".aligned." in k}
    exported = {k.removeprefix("base_model.model."): v for k, v in exported.items()}
    assert exported.keys() == averaged.keys()
    assert all(torch.allclose(exported[k], averaged[k], atol=1e-6) for k in averaged)
    last = {k.replace(".aligned.", "."): v for k, v in current[-1].items() if ".aligned." in k}
    assert not all(torch.equal(exported[k], last[k]) for k in averaged)


def test_the_baseline_exports_the_moving_average_of_its_weights(stages):
    """``stage.ema_decay``: the product is e_k = d e_(k-1) + (1 - d) w_k over the weights w_k after each step
    (e_1 = w_1), not the last step's weights."""
    from diffusers.models.modeling_utils import load_state_dict

    tmp, cache, _, _ = stages
    decay = 0.5
    product = train_stage(config(tmp, cache, "baseline", 3, "ema", ema_decay=decay, keep_checkpoints=-1))
    current, expected = checkpointed_weights_and_their_average(tmp / "ema", 3, decay)
    exported = load_state_dict(str(product / "diffusion_pytorch_model.safetensors"))
    assert exported.keys() == expected.keys()
    assert all(torch.allclose(exported[k], expected[k], atol=1e-6) for k in expected)
    assert not all(torch.equal(exported[k], current[-1][k]) for k in expected)


def test_a_resumed_moving_average_matches_the_uninterrupted_one(stages):
    tmp, cache, _, _ = stages
    full = train_stage(config(tmp, cache, "baseline", 4, "ema_full", ema_decay=0.9))
    train_stage(config(tmp, cache, "baseline", 3, "ema_resumed", ema_decay=0.9))  # stops mid-epoch
    resumed = train_stage(config(tmp, cache, "baseline", 4, "ema_resumed", ema_decay=0.9))
    name = "diffusion_pytorch_model.safetensors"
    assert (full / name).read_bytes() == (resumed / name).read_bytes()


def test_a_moving_average_needs_a_decay_below_one():
    with pytest.raises(ValueError, match="stage.ema_decay"):
        StageConfig(name="baseline", ema_decay=1.0)


def test_a_stage_with_deployment_eval_logs_its_scores_and_trains_the_same_weights(stages):
    """``stage.deployment_eval``: the stage deploys its own restorer (Stage 1: base + aligned adapter) on a
    validation scene every step and at its end, the scores land in the CSV log at their steps, and the trained
    adapter is bitwise the one trained without it (deployment runs on its own random streams)."""
    from tracegs.data.config import SceneSourceConfig, SyntheticConfig
    from tracegs.data.synthetic import generate_scene, scene_name
    from tracegs.deploy.config import RefinementConfig
    from tracegs.splat.config import DensificationConfig, GaussianFitConfig, TrajectoryConfig
    from tracegs.training.config import DeploymentEvalConfig

    tmp, cache, baseline, stage1 = stages
    scenes = tmp / "scenes"
    generate_scene(50, SyntheticConfig(root=str(scenes), num_views=16, height=24, width=32, num_objects=1,
                                       gaussians_per_unit_area=150, init_points=400), scenes)
    cfg = config(tmp, cache, "stage1", 2, "deploying", base_weights=str(baseline),
                 deployment_eval=DeploymentEvalConfig(scenes=[scene_name(50)], views=[3], every_n_steps=1))
    cfg.source = SceneSourceConfig(root=str(scenes))
    cfg.fit = GaussianFitConfig(iterations=30, snapshot_iters=[], densification=DensificationConfig(enabled=False))
    cfg.deploy = RefinementConfig(total_iters=30, repair_iters=[10, 20], max_clips_per_round=1, steps=2,
                                  trajectory=TrajectoryConfig(frames_per_clip=9, ellipse_frames=24))
    product = train_stage(cfg)

    (metrics,) = (tmp / "deploying" / "csv").glob("version_*/metrics.csv")
    with open(metrics) as handle:
        rows = [row for row in csv.DictReader(handle) if row.get("deploy/psnr_k3")]
    assert [int(row["step"]) for row in rows] == [1, 2]
    assert all(5.0 < float(row["deploy/psnr_k3"]) < 60.0 and 0.0 < float(row["deploy/ssim_k3"]) <= 1.0
               for row in rows)
    assert (product / "adapter_model.safetensors").read_bytes() == (stage1 / "adapter_model.safetensors").read_bytes()
