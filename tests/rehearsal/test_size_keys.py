"""`experiment=rehearsal` is `experiment=paper` with only sizes shrunk (the CPU rehearsal of the paper scale).

Both configurations are composed, flattened to dotted keys (interpolations unresolved, so a changed
interpolation counts as a difference) and compared: every differing key must be declared below with the
reason it is a size, and every iteration-based schedule must be the paper's divided by one factor.
"""

from __future__ import annotations

from fractions import Fraction

import pytest
from hydra import compose
from omegaconf import OmegaConf

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
ITERATION_FACTOR = Fraction(1, 100)


def flatten(node, prefix: str = "") -> dict[str, object]:
    """Dotted key -> leaf value; lists are leaves (a schedule is compared as a whole)."""
    out: dict[str, object] = {}
    for key, value in node.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{dotted}."))
        else:
            out[dotted] = value
    return out


def composed(config_name: str, experiment: str) -> dict[str, object]:
    cfg = compose(config_name=config_name, overrides=[f"experiment={experiment}"])
    return flatten(OmegaConf.to_container(cfg, resolve=False))


def differing_keys(config_name: str) -> dict[str, tuple[object, object]]:
    paper, rehearsal = composed(config_name, "paper"), composed(config_name, "rehearsal")
    assert paper.keys() == rehearsal.keys()
    return {k: (paper[k], rehearsal[k]) for k in paper if paper[k] != rehearsal[k]}


@pytest.mark.parametrize("config_name", ["prepare", "train", "evaluate"])
def test_rehearsal_differs_from_paper_only_in_sizes(hydra_context, config_name):
    differing = differing_keys(config_name)
    undeclared = {k: v for k, v in differing.items() if k not in SIZE_KEYS}
    assert not undeclared, f"experiment=rehearsal differs from experiment=paper outside the size keys: {undeclared}"


def test_every_declared_size_key_is_shrunk(hydra_context):
    stale = sorted(set(SIZE_KEYS) - set(differing_keys("train")))
    assert not stale, f"declared size keys that do not differ (remove them): {stale}"


def test_iteration_schedules_are_scaled_by_one_factor(hydra_context):
    differing = differing_keys("train")
    for key, reason in SIZE_KEYS.items():
        if not reason.startswith("iteration"):
            continue
        paper, rehearsal = differing[key]
        pairs = zip(paper, rehearsal) if isinstance(paper, list) else [(paper, rehearsal)]
        for full, small in pairs:
            assert Fraction(small, full) == ITERATION_FACTOR, f"{key}: {small} is not {full} x {ITERATION_FACTOR}"
