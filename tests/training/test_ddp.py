"""Stepwise back-propagation under DDP (2 CPU processes, gloo): same update as retain (slow, opt-in)."""

from __future__ import annotations

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader
from training_support import make_batch, make_schedule, make_transformer

from tracegs.training.config import OptimizerConfig
from tracegs.training.stage2 import STUDENT, Stage2DistillationModule


def train_ddp(adapter, mode: str) -> dict[str, torch.Tensor]:
    module = Stage2DistillationModule(make_transformer(), make_schedule(), adapter,
                                      OptimizerConfig(lr=1e-2, grad_clip=None), rollout_steps=3, deploy_steps=8,
                                      memory_mode=mode)
    trainer = L.Trainer(accelerator="cpu", devices=2, strategy="ddp_spawn", max_steps=2, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)
    # two different batches: one per rank
    trainer.fit(module, train_dataloaders=DataLoader([make_batch(seed=0), make_batch(seed=1)], batch_size=None))
    return {n: p.detach().clone() for n, p in module.transformer.named_parameters() if f".{STUDENT}." in n}


@pytest.mark.slow
def test_stepwise_defers_sync_and_matches_retain_under_ddp(stage1_adapter):
    retain, stepwise = train_ddp(stage1_adapter, "retain"), train_ddp(stage1_adapter, "stepwise")
    initial = {n: p.detach() for n, p in Stage2DistillationModule(
        make_transformer(), make_schedule(), stage1_adapter, OptimizerConfig()).transformer.named_parameters()
        if f".{STUDENT}." in n}
    assert any(not torch.allclose(retain[n], initial[n]) for n in retain)
    for name in retain:
        torch.testing.assert_close(stepwise[name], retain[name], rtol=1e-5, atol=1e-6)
