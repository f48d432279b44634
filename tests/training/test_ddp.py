"""Stepwise back-propagation under DDP (2 CPU processes, gloo): same update as retain (slow, opt-in)."""

from __future__ import annotations

import lightning as L
import pytest
import torch
from support.training import make_batch, make_schedule, make_transformer
from torch.utils.data import DataLoader

from tracegs.training.config import OptimizerConfig
from tracegs.training.stage2 import STUDENT, Stage2DistillationModule
from tracegs.training.strategy import one_job_of_processes


def train_ddp(adapter, mode: str) -> dict[str, torch.Tensor]:
    module = Stage2DistillationModule(make_transformer(), make_schedule(), adapter,
                                      OptimizerConfig(lr=1e-2, grad_clip=None), rollout_steps=3, deploy_steps=8,
                                      memory_mode=mode)
    trainer = L.Trainer(accelerator="cpu", devices=2, strategy="ddp_spawn", max_steps=2, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)
    with one_job_of_processes():  # the spawn launcher's port and process state, released afterwards
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


@pytest.mark.slow
def test_ddp_trains_fp32_adapters_on_a_bf16_base_with_guidance(stage1_adapter):
    """The paper's combination under DDP (2 gloo ranks): bf16 base, bf16-mixed, guided rollout, fp32 factors."""
    module = Stage2DistillationModule(make_transformer().to(torch.bfloat16), make_schedule(), stage1_adapter,
                                      OptimizerConfig(lr=1e-5, grad_clip=1.0), rollout_steps=3, deploy_steps=8,
                                      guidance_scale=6.0)
    before = {n: p.detach().clone() for n, p in module.transformer.named_parameters() if f".{STUDENT}." in n}
    trainer = L.Trainer(accelerator="cpu", devices=2, strategy="ddp_spawn", precision="bf16-mixed", max_steps=2,
                        logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False)
    with one_job_of_processes():
        trainer.fit(module, train_dataloaders=DataLoader([make_batch(seed=0), make_batch(seed=1)], batch_size=None))
    after = {n: p.detach() for n, p in module.transformer.named_parameters() if f".{STUDENT}." in n}
    assert all(p.dtype == torch.float32 for p in after.values())
    moved = torch.cat([(after[n] != before[n]).flatten() for n in before]).float().mean()
    assert moved > 0.99  # lr 1e-5 updates survive: the factors are float32
