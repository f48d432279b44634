"""Lightning strategy of a training run: the configured name, or a fully sharded strategy built for the restorer.

``trainer.strategy: fsdp`` (``conf/trainer/fsdp.yaml``) is torch's per-parameter FSDP (``fully_shard``) through
Lightning's ``ModelParallelStrategy``, one data-parallel mesh dimension over every rank. Each transformer block
is its own unit, so only one block's full weights are gathered at a time, and its activations are recomputed
in backward. Each LoRA factor is a unit of its own: one unit all-gathers its parameters as one buffer of one
dtype, while a block holds the frozen bf16 base next to the float32 factors (see ``tracegs.restorer.adapters``).
The same code runs on GPUs (NCCL) and on CPU processes (gloo): torch's FSDP1 and Lightning's ``FSDPStrategy``
refuse a CPU accelerator, ``fully_shard`` does not.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

import torch
import torch.distributed as dist
from lightning.pytorch.strategies import ModelParallelStrategy
from torch import Tensor, nn
from torch.distributed._composable import checkpoint
from torch.distributed.fsdp import FSDPModule, fully_shard
from torch.distributed.tensor import DTensor

from tracegs.restorer.transformer import ReferenceGuidedBlock
from tracegs.training.config import FsdpConfig, TrainerConfig

# Module classes ``trainer.fsdp.wrap_modules`` may name.
WRAPPABLE = {cls.__name__: cls for cls in (ReferenceGuidedBlock,)}


def block_classes(cfg: FsdpConfig) -> set[type[nn.Module]]:
    unknown = sorted(set(cfg.wrap_modules) - set(WRAPPABLE))
    if unknown:
        raise ValueError(f"trainer.fsdp.wrap_modules: unknown module classes {unknown} (known: {sorted(WRAPPABLE)})")
    return {WRAPPABLE[name] for name in cfg.wrap_modules}


def lora_factors(model: nn.Module, adapter: str | None = None) -> list[nn.Module]:
    """Every LoRA factor module (of ``adapter``, or of all): peft keeps them in ``lora_A`` / ``lora_B``
    ModuleDicts keyed by adapter name."""
    return [factor for module in model.modules() for name in ("lora_A", "lora_B")
            if isinstance(getattr(module, name, None), nn.ModuleDict)
            for key, factor in getattr(module, name).items() if adapter in (None, key)]


def shard_restorer(model: nn.Module, cfg: FsdpConfig, mesh) -> None:
    """Shard ``model`` in place over ``mesh``: LoRA factors first, then the blocks (with activation
    checkpointing), then the root, which takes every parameter not in a unit below it."""
    blocks = tuple(block_classes(cfg))
    for factor in lora_factors(model):
        fully_shard(factor, mesh=mesh, reshard_after_forward=cfg.reshard_after_forward)
    for module in [m for m in model.modules() if isinstance(m, blocks)]:
        if cfg.activation_checkpointing:
            checkpoint(module)
        fully_shard(module, mesh=mesh, reshard_after_forward=cfg.reshard_after_forward)
    fully_shard(model, mesh=mesh, reshard_after_forward=cfg.reshard_after_forward)


def full_lora_state(model: nn.Module) -> dict[str, Tensor] | None:
    """The LoRA factors of a sharded ``model`` as whole tensors, keyed as ``model.state_dict()`` (which under
    FSDP holds each rank's shards); None for an unsharded model. A collective: every rank must call it."""
    if not isinstance(model, FSDPModule):
        return None
    return {key: value.full_tensor() if isinstance(value, DTensor) else value
            for key, value in model.state_dict().items() if "lora_" in key}


# What Lightning's launchers set in the launching process (lightning/pytorch/strategies/launchers/
# subprocess_script.py, _call_children_scripts); with LOCAL_RANK set it takes the ranks as started by someone else.
# They also set OMP_NUM_THREADS and torch's intra-op threads to cores / processes when OMP_NUM_THREADS is unset
# (lightning/fabric/utilities/distributed.py, _set_num_threads_if_needed).
LAUNCH_ENV = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE", "OMP_NUM_THREADS")


@contextlib.contextmanager
def one_job_of_processes() -> Iterator[None]:
    """One training job's ranks: in the process that launches them (no LOCAL_RANK before), the process group is
    closed and the launcher's variables and thread count restored afterwards, so the next job of a multirun in
    this process launches its own ranks and computes with the threads it was given (a different count changes
    the float results). ``init_process_group`` also wraps ``sys.excepthook`` to prefix every line with the rank
    and ``destroy_process_group`` leaves the wrapper: it is restored too, else each job would add one more prefix.
    Ranks started by Lightning, torchrun or SLURM are left alone (they end with the job)."""
    before = {key: os.environ.get(key) for key in LAUNCH_ENV}
    threads, excepthook = torch.get_num_threads(), sys.excepthook
    try:
        yield
    finally:
        if before["LOCAL_RANK"] is None:
            torch.set_num_threads(threads)
            sys.excepthook = excepthook
            if dist.is_available() and dist.is_initialized():
                dist.destroy_process_group()
            for key, value in before.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


class ShardedRestorerStrategy(ModelParallelStrategy):
    """``ModelParallelStrategy`` with every rank on the data-parallel dimension (no tensor parallelism) and the
    restorer sharded by ``shard_restorer`` from the module's ``configure_model`` hook. Checkpoints are single
    files (full trainable state on rank 0), like the other strategies'."""

    def __init__(self, cfg: FsdpConfig) -> None:
        super().__init__(save_distributed_checkpoint=False)
        self.fsdp = cfg

    def setup_environment(self) -> None:
        self._data_parallel_size, self._tensor_parallel_size = self.num_nodes * self.num_processes, 1
        super().setup_environment()

    def shard(self, model: nn.Module) -> None:
        if not isinstance(model, FSDPModule):  # configure_model runs again on a second fit
            shard_restorer(model, self.fsdp, self.device_mesh["data_parallel"])


def build_strategy(cfg: TrainerConfig):
    """``cfg.strategy`` as Lightning reads it, except "fsdp": a ``ShardedRestorerStrategy``."""
    if cfg.strategy != "fsdp":
        return cfg.strategy
    block_classes(cfg.fsdp)  # an unknown class fails here, before any process starts
    return ShardedRestorerStrategy(cfg.fsdp)
