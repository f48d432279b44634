"""Trainable LoRA factors and their AdamW state stay fp32 on a bf16 base, whatever Lightning's precision plugin.

At lr 1e-5 an AdamW step moves a weight by about 1e-5, far below bf16's resolution (~4e-3 relative): bf16
factors would round most updates away. The updates of a bf16-base run must match those of an fp32-base run
to the precision of the bf16 forward pass.
"""

from __future__ import annotations

import pytest
import torch
from support.training import fit_steps, make_batch, make_schedule, make_transformer

from tracegs.training.config import OptimizerConfig
from tracegs.training.stage2 import STUDENT, Stage2DistillationModule

LR, STEPS = 1e-5, 4


def student_weights(module) -> dict[str, torch.Tensor]:
    return {n: p.detach().float().clone() for n, p in module.transformer.named_parameters() if f".{STUDENT}." in n}


def stage2_updates(adapter, base_dtype: torch.dtype, precision: str) -> tuple[dict, Stage2DistillationModule]:
    """Per-tensor change of the student factors after STEPS Stage-2 steps at lr 1e-5."""
    optimizer = OptimizerConfig(lr=LR, warmup_steps=0, grad_clip=None)
    module = Stage2DistillationModule(make_transformer().to(base_dtype), make_schedule(), adapter, optimizer,
                                      rollout_steps=3, deploy_steps=8, seed=3)
    before = student_weights(module)
    fit_steps(module, make_batch(), steps=STEPS, precision=precision)
    after = student_weights(module)
    return {n: after[n] - before[n] for n in before}, module


def relative_error(updates: dict, reference: dict) -> float:
    diff = torch.cat([(updates[n] - reference[n]).flatten() for n in reference])
    return float(diff.norm() / torch.cat([r.flatten() for r in reference.values()]).norm())


@pytest.mark.parametrize("precision", ["bf16-mixed", "bf16-true"])
def test_bf16_base_updates_match_fp32_base(stage1_adapter, precision):
    fp32_reference, _ = stage2_updates(stage1_adapter, torch.float32, "32-true")
    updates, module = stage2_updates(stage1_adapter, torch.bfloat16, precision)
    base = {p.dtype for n, p in module.transformer.named_parameters() if "lora_" not in n}
    assert base == {torch.bfloat16}
    assert {p.dtype for p in module.trainable_parameters()} == {torch.float32}
    state = module.optimizers().optimizer.state
    assert {v.dtype for p in module.trainable_parameters() for k, v in state[p].items() if k != "step"} == {
        torch.float32}
    moved = torch.cat([(u != 0).flatten() for u in updates.values()]).float().mean()
    assert moved == 1.0  # every entry moved, as in the fp32 run
    # Measured: 4-5 % (the bf16 forward's rounding, amplified by Adam's normalisation in the first steps).
    # With bf16 factors the updates are 99.5 % off and only 1.4 % of the entries move at all.
    assert relative_error(updates, fp32_reference) < 0.1
