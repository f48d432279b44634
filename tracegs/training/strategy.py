"""Lightning strategy of a training run: the configured name, or an FSDP strategy built for the restorer.

FSDP (``conf/trainer/fsdp.yaml``) shards each transformer block as its own unit, so only one block's full
weights are gathered at a time, and checkpoints the blocks' activations (recomputed in backward). The LoRA
factors get units of their own: an FSDP unit flattens its parameters into one tensor of one dtype and one
``requires_grad``, while a block holds the frozen bf16 base, the frozen teacher factors and the trainable
float32 student factors (see ``tracegs.restorer.adapters``).
"""

from __future__ import annotations

from torch import nn

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


def build_strategy(cfg: TrainerConfig, model: nn.Module):
    """``cfg.strategy`` as Lightning reads it, except "fsdp": an ``FSDPStrategy`` wrapping ``model``'s blocks
    (and LoRA factors) and checkpointing the blocks' activations."""
    if cfg.strategy != "fsdp":
        return cfg.strategy
    from lightning.pytorch.strategies import FSDPStrategy
    from torch.distributed.fsdp.wrap import CustomPolicy

    blocks = tuple(block_classes(cfg.fsdp))
    factors = {id(factor) for factor in lora_factors(model)}
    return FSDPStrategy(
        auto_wrap_policy=CustomPolicy(lambda module: isinstance(module, blocks) or id(module) in factors),
        activation_checkpointing_policy=set(blocks) if cfg.fsdp.activation_checkpointing else None,
        sharding_strategy=cfg.fsdp.sharding_strategy,
    )
