"""``train_stage`` on a random cache in the prepared layout: the cache, the stage configs, a baseline and Stage 1
trained on it, and the bytes a run's product is compared by."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import torch

from support.training import (
    CHANNELS,
    FRAMES,
    HEIGHT,
    TEXT_LEN,
    TINY_LORA,
    TINY_SCHEDULE,
    TINY_TRANSFORMER,
    WIDTH,
)
from tracegs.data.cache_keys import CACHE_VERSION, MANIFEST, condition_key
from tracegs.data.config import DataModuleConfig
from tracegs.data.preparation.shards import EncodedClip, write_clip
from tracegs.data.splits import view_set_key
from tracegs.restorer.config import BackboneConfig, CodecConfig, ReferenceEncoderConfig, TextEncoderConfig
from tracegs.training.config import OptimizerConfig, StageConfig, TrainConfig, TrainerConfig
from tracegs.training.run import train_stage

REF_TOKENS = 6  # two reference views of three tokens
# The embedded reference encoder with 2x2 patches gives 12 (2D) and 12 + 8 (3D) features per token.
BACKBONE = BackboneConfig(
    transformer=dataclasses.replace(TINY_TRANSFORMER, ref_2d_dim=12, ref_3d_dim=20),
    lora=TINY_LORA,
    codec=CodecConfig(latent_channels=CHANNELS),
    reference_encoder=ReferenceEncoderConfig(patch_size=2),
    text_encoder=TextEncoderConfig(dim=TINY_TRANSFORMER.text_embed_dim, max_length=TEXT_LEN),
    schedule=TINY_SCHEDULE,
)


def write_cache(root: Path, clips: int = 4) -> Path:
    """A cache in the prepared layout (manifest, one shard per clip and the scene files it indexes, written by
    prepare's ``write_clip``) with random latents."""
    g = torch.Generator().manual_seed(0)
    latent = (FRAMES, CHANNELS, HEIGHT, WIDTH)
    paths = []
    for clip in range(clips):
        target = torch.randn(latent, generator=g)
        tensors = {
            "latent/target": target,
            f"latent/{condition_key(3, 140)}": target + 0.7 * torch.randn(latent, generator=g),
            f"latent/{condition_key(None)}": target + 0.1 * torch.randn(latent, generator=g),
        }
        ref_2d = torch.randn(REF_TOKENS, 12, generator=g).half()
        encoded = EncodedClip({k: v.half() for k, v in tensors.items()}, 3, (clip, clip + 1), f"clip {clip}",
                              tuple(ref_2d.chunk(2)), torch.randn(REF_TOKENS, 20, generator=g).half(),
                              torch.randn(TEXT_LEN, TINY_TRANSFORMER.text_embed_dim, generator=g).half())
        paths.append(str(write_clip(root / "scene_a", clip, encoded, {}, "random").relative_to(root)))
    manifest = {"version": CACHE_VERSION, "teacher_views": [view_set_key(3), view_set_key(None)],
                "scenes": {"scene_a": {"clips": paths}}}
    (root / MANIFEST).write_text(json.dumps(manifest))
    return root


def config(tmp_path: Path, cache: Path, name: str, steps: int, out: str, decay: str = "constant",
           **stage) -> TrainConfig:
    return TrainConfig(
        stage=StageConfig(name=name, max_steps=steps, batch_size=2, rollout_steps=3, checkpoint_every_n_steps=1,
                          **stage),
        optimizer=OptimizerConfig(lr=3e-3, warmup_steps=2, decay=decay),
        trainer=TrainerConfig(enable_progress_bar=False, log_every_n_steps=1),
        backbone=BACKBONE,
        data=DataModuleConfig(cache_dir=str(cache), student_views=[3], student_snapshots=[140], caption_dropout=0.0),
        output_dir=str(tmp_path / out),
    )


def train_baseline_and_stage1(tmp: Path) -> tuple[Path, Path, Path]:
    """(cache, baseline transformer, Stage-1 adapter): two steps of each stage on a random cache under ``tmp``."""
    cache = write_cache(tmp / "cache")
    baseline = train_stage(config(tmp, cache, "baseline", 2, "baseline"))
    stage1 = train_stage(config(tmp, cache, "stage1", 2, "stage1", base_weights=str(baseline)))
    return cache, baseline, stage1


def product_bytes(product: Path) -> bytes:
    """Every byte of a product: a file, or each file of a folder (the peft adapter folder) in name order."""
    files = sorted(p for p in product.rglob("*") if p.is_file()) if product.is_dir() else [product]
    return b"".join(f.name.encode() + f.read_bytes() for f in files)
