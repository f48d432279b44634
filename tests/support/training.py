"""Tiny restorer, random sample-dict batches shaped like the data module's output, and a short fit loop."""

from __future__ import annotations

import lightning as L
import torch
from torch.utils.data import DataLoader

from tracegs.restorer.build import create_transformer
from tracegs.restorer.config import LoraConfig, ScheduleConfig, TransformerConfig
from tracegs.restorer.schedules import build_schedule

FRAMES, CHANNELS, HEIGHT, WIDTH = 2, 4, 4, 4
REF_TOKENS, TEXT_LEN = 3, 4

TINY_TRANSFORMER = TransformerConfig(
    num_layers=2,
    num_attention_heads=2,
    attention_head_dim=8,
    latent_channels=CHANNELS,
    text_embed_dim=8,
    max_text_seq_length=TEXT_LEN,
    time_embed_dim=16,
    patch_size=2,
    sample_frames=FRAMES,
    sample_height=HEIGHT,
    sample_width=WIDTH,
    ref_2d_dim=6,
    ref_3d_dim=5,
)
TINY_LORA = LoraConfig(rank=2, alpha=2)
TINY_SCHEDULE = ScheduleConfig(kind="rectified_flow", deploy_steps=8)


def make_transformer(seed: int = 0):
    torch.manual_seed(seed)
    return create_transformer(TINY_TRANSFORMER).requires_grad_(False)


def make_schedule():
    return build_schedule(TINY_SCHEDULE)


def make_batch(batch_size: int = 2, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    latent = (batch_size, FRAMES, CHANNELS, HEIGHT, WIDTH)
    target = torch.randn(latent, generator=g)
    return {
        "student_cond": target + 0.8 * torch.randn(latent, generator=g),
        "teacher_cond": target + 0.1 * torch.randn(latent, generator=g),
        "target": target,
        "ref_2d": torch.randn(batch_size, REF_TOKENS, 6, generator=g),
        "ref_3d": torch.randn(batch_size, REF_TOKENS, 5, generator=g),
        "text": torch.randn(batch_size, TEXT_LEN, 8, generator=g),
        "text_dropped": torch.zeros(batch_size, dtype=torch.bool),
        "scene": ["s"] * batch_size,
        "clip": torch.arange(batch_size),
        "student_views": torch.full((batch_size,), 3),
        "teacher_views": torch.full((batch_size,), -1),
        "snapshot": torch.full((batch_size,), 140),
    }

def fixed_batch_loader(batch: dict) -> DataLoader:
    # batch_size=None: the single dataset item already is a collated batch (one batch per epoch).
    return DataLoader([batch], batch_size=None)


def fit_steps(module: L.LightningModule, batch: dict, steps: int, ckpt_path=None, root=None,
              precision: str = "32-true") -> L.Trainer:
    trainer = L.Trainer(
        accelerator="cpu",
        devices=1,
        precision=precision,
        max_steps=steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        default_root_dir=root,
    )
    trainer.fit(module, train_dataloaders=fixed_batch_loader(batch), ckpt_path=ckpt_path)
    return trainer
