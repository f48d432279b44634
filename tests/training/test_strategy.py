"""The FSDP strategy shards each transformer block and each LoRA factor (fully_shard) and checkpoints the blocks;
sharded adapters are exported whole."""

from __future__ import annotations

import pytest
import torch
import torch.distributed as dist
from support.training import TINY_LORA, make_transformer
from torch.distributed.device_mesh import init_device_mesh
from torch.distributed.fsdp import FSDPModule

from tracegs.restorer.adapters import add_adapter
from tracegs.restorer.transformer import ReferenceGuidedBlock
from tracegs.training.config import FsdpConfig, TrainerConfig
from tracegs.training.strategy import (
    ShardedRestorerStrategy,
    build_strategy,
    full_lora_state,
    one_job_of_processes,
    shard_restorer,
)


@pytest.fixture
def cpu_mesh(tmp_path):
    """A one-rank gloo process group on this process's CPU (what each rank of a two-process run holds)."""
    with one_job_of_processes():  # releases the group and what init_process_group changed in this process
        dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'rendezvous'}", rank=0, world_size=1)
        yield init_device_mesh("cpu", (1,))


def test_fsdp_shards_blocks_and_factors_and_exports_whole_adapters(cpu_mesh):
    model = make_transformer()
    add_adapter(model, "student", TINY_LORA)
    with torch.no_grad():
        for name, param in model.named_parameters():
            if "lora_B" in name:
                param.normal_()  # peft starts B at zero: make the factors matter
    before = {k: v.clone() for k, v in model.state_dict().items() if "lora_" in k}
    assert full_lora_state(model) is None  # unsharded: nothing to gather
    shard_restorer(model, FsdpConfig(), cpu_mesh)
    blocks = [m for m in model.modules() if isinstance(m, ReferenceGuidedBlock)]
    factors = [m for name, m in model.named_modules() if ".lora_A.student" in name or ".lora_B.student" in name]
    assert len(blocks) == 2 and len(factors) == 2 * 2 * 4 * 2
    assert all(isinstance(m, FSDPModule) for m in [model, *blocks, *factors])
    units = {m for m in model.modules() if isinstance(m, FSDPModule)}
    assert units == {model, *blocks, *factors}  # nothing else is a unit
    gathered = full_lora_state(model)
    assert gathered.keys() == before.keys()
    for key, value in before.items():
        assert type(gathered[key]) is torch.Tensor
        torch.testing.assert_close(gathered[key], value, rtol=0, atol=0)


def test_fsdp_config_builds_the_sharded_strategy_and_unknown_wrap_classes_fail():
    strategy = build_strategy(TrainerConfig(strategy="fsdp"))
    assert isinstance(strategy, ShardedRestorerStrategy) and strategy.fsdp.activation_checkpointing
    assert build_strategy(TrainerConfig(strategy="ddp")) == "ddp"
    with pytest.raises(ValueError, match="trainer.fsdp.wrap_modules"):
        build_strategy(TrainerConfig(strategy="fsdp", fsdp=FsdpConfig(wrap_modules=["Block"])))
