"""The rehearsal (``experiment=rehearsal``) as the tests compose and run it, the keys it may shrink and the default
suite's budget on top of it."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from hydra import initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from tracegs.cli.app import CONF_DIR, run_task
from tracegs.config.schema import register_configs
from tracegs.pipeline.runner import composed

# Dotted key -> why it is a size (or the run's name) and not science.
SIZE_KEYS = {
    "experiment.name": "the run's name: rehearsal outputs never land in a paper run's folder",
    "experiment.description": "the run's one-line description",
    "experiment.stage1_steps": "iteration budget (paper / 100)",
    "experiment.stage2_steps": "iteration budget (paper / 100)",
    "experiment.stage2_warmup_steps": "iteration budget (paper / 100)",
    "experiment.frame_height": "clip resolution (the datasets, clips and trajectories follow it)",
    "experiment.frame_width": "clip resolution (the datasets, clips and trajectories follow it)",
    "experiment.frames_per_clip": "clip frames (prepare and deployment follow it)",
    "experiment.clips_per_scene": "number of clips",
    "backbone.transformer.num_layers": "model depth",
    "backbone.transformer.num_attention_heads": "model width",
    "backbone.transformer.attention_head_dim": "model width",
    "backbone.transformer.text_embed_dim": "model width (equals the T5 width)",
    "backbone.transformer.max_text_seq_length": "text tokens (equals the T5 length)",
    "backbone.transformer.time_embed_dim": "model width",
    "backbone.transformer.sample_frames": "clip frames",
    "backbone.transformer.sample_height": "latent resolution (clip height / VAE factor 8)",
    "backbone.transformer.sample_width": "latent resolution (clip width / VAE factor 8)",
    "backbone.transformer.ref_2d_dim": "model width (equals the DINOv2 width)",
    "backbone.transformer.ref_3d_dim": "model width (equals the VGGT token width, twice DINOv2's as at paper scale)",
    "backbone.lora.rank": "adapter width",
    "backbone.lora.alpha": "kept equal to the rank, so the LoRA scale alpha / r stays 1 as in the paper",
    "backbone.reference_encoder.image_size": "reference resolution (a multiple of the patch 14)",
    "backbone.text_encoder.dim": "T5 width",
    "backbone.text_encoder.max_length": "text tokens",
    "data.prepare.fit.backend": "the rasterizer's device: pure-PyTorch on CPU instead of gsplat on CUDA",
    "data.prepare.fit.iterations": "iteration budget (paper / 100)",
    "data.prepare.fit.snapshot_iters": "iteration schedule (paper / 100)",
    "data.prepare.fit.sh_degree_interval": "iteration schedule (paper / 100)",
    "data.prepare.fit.densification.refine_start_iter": "iteration schedule (paper / 100)",
    "data.prepare.fit.densification.refine_stop_iter": "iteration schedule (paper / 100)",
    "data.prepare.fit.densification.refine_every": "iteration schedule (paper / 100)",
    "data.prepare.fit.densification.reset_every": "iteration schedule (paper / 100)",
    "data.prepare.fit.densification.max_gaussians": "number of Gaussians",
    "data.prepare.fit.init_num_points": "number of Gaussians (paper / 100)",
    "deploy.total_iters": "iteration budget (paper / 100)",
    "deploy.captions.blip2_path": "no BLIP-2 in the rehearsal's weights tree: captions from caption.txt",
    "deploy.repair_iters": "iteration schedule (paper / 100)",
    "deploy.trajectory.ellipse_frames": "clips per round (poses per round, cut into windows of the clip's size)",
    "trainer.accelerator": "the device: CPU instead of GPU",
    "trainer.devices": "number of devices",
}

# The default suite's overrides on top of experiment=rehearsal: each makes a count smaller, none touches a
# mode, rate, weight, schedule or sampler (test_budget_overrides_are_sizes checks the keys).
BUDGET = (
    "experiment.stage1_steps=1",  # Stage 1: one optimiser step
    "experiment.stage2_steps=2",  # Stage 2: two optimiser steps, each a full N = 10 rollout of the M = 50 grid
    "deploy.max_clips_per_round=1",  # restored clips per repair round (rehearsal: one per reference pair)
    "evaluation.views=[3]",  # evaluated view counts (rehearsal: 3, 6, 9); the K = 3 unit runs unchanged
)


def rehearsal_config(root: Path, config_name: str = "train", overrides: tuple[str, ...] = ()):
    """``conf/<config_name>.yaml`` under ``experiment=rehearsal`` with every path below ``root``."""
    with rehearsal_job(root, config_name, overrides) as cfg:
        return cfg


@contextlib.contextmanager
def rehearsal_job(root: Path, config_name: str, overrides: tuple[str, ...] = ()) -> Iterator[DictConfig]:
    """``rehearsal_config`` composed as the console script composes it, keeping the job's overrides as its
    ``command_line`` and Hydra initialised while the job runs: its steps compose the configs of the steps before
    them from those overrides, so the run folders they name are the ones that command line writes and reads."""
    register_configs()
    with initialize_config_dir(config_dir=str(Path(CONF_DIR)), version_base="1.3"):
        yield composed(config_name, ["experiment=rehearsal", f"paths.root_dir={root}", *overrides])


def run_rehearsal_task(task, root: Path, config_name: str, overrides: tuple[str, ...] = ()):
    """Run ``task`` as its console script does (tracegs.cli.app.run_task: validation, seeding, the task), so
    each stage finds the products of the stages before it."""
    with rehearsal_job(root, config_name, overrides) as cfg:
        return run_task(task, cfg)


def rehearsal_run_dir(root: Path, config_name: str, overrides: tuple[str, ...] = (), key: str = "run_dir") -> Path:
    """The folder a rehearsal command line writes (``key``: ``run_dir`` or ``evaluation.out_dir``)."""
    with rehearsal_job(root, config_name, overrides) as cfg:
        return Path(str(OmegaConf.select(cfg, key)))


def fresh_root(tmp_path: Path, rehearsal_root: Path, paper_data: dict[str, Path]) -> Path:
    """A launch directory sharing the weights and the DL3DV scenes, with its own caches and outputs."""
    root = tmp_path / "launch"
    (root / "data").mkdir(parents=True)
    (root / "weights").symlink_to(rehearsal_root / "weights")
    (root / "data" / paper_data["dl3dv"].name).symlink_to(paper_data["dl3dv"])
    return root
