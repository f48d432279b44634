"""The FSDP strategy wraps the transformer blocks (and the LoRA factors) and checkpoints the blocks."""

from __future__ import annotations

import pytest
from lightning.pytorch.strategies import FSDPStrategy
from torch.distributed.fsdp.wrap import CustomPolicy
from training_support import TINY_LORA, make_transformer

from tracegs.restorer.adapters import add_adapter
from tracegs.restorer.transformer import ReferenceGuidedBlock
from tracegs.training.config import FsdpConfig, TrainerConfig
from tracegs.training.strategy import build_strategy


def test_fsdp_wraps_and_checkpoints_the_transformer_blocks():
    model = make_transformer()
    add_adapter(model, "student", TINY_LORA)
    strategy = build_strategy(TrainerConfig(strategy="fsdp"), model)
    assert isinstance(strategy, FSDPStrategy)
    # activation checkpointing: a ModuleWrapPolicy naming the block class
    assert strategy._activation_checkpointing_kwargs["auto_wrap_policy"]._module_classes == {ReferenceGuidedBlock}
    blocks = [m for m in model.modules() if isinstance(m, ReferenceGuidedBlock)]
    policy = strategy.kwargs["auto_wrap_policy"]
    assert isinstance(policy, CustomPolicy)
    wrapped = policy._run_policy(model, set(), {})
    assert all(block in wrapped for block in blocks) and len(blocks) == 2
    # every LoRA factor is its own unit (one dtype, one requires_grad); nothing else is
    factors = [m for name, m in model.named_modules() if ".lora_A.student" in name or ".lora_B.student" in name]
    assert all(factor in wrapped for factor in factors) and len(factors) == 2 * 2 * 4 * 2
    assert set(wrapped) == {*blocks, *factors}


def test_other_strategies_pass_through_and_unknown_wrap_classes_fail():
    assert build_strategy(TrainerConfig(strategy="ddp"), make_transformer()) == "ddp"
    with pytest.raises(ValueError, match="trainer.fsdp.wrap_modules"):
        build_strategy(TrainerConfig(strategy="fsdp", fsdp=FsdpConfig(wrap_modules=["Block"])), make_transformer())
