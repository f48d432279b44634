"""How the restorer's transformer executes: the switches that trade Stage 2's memory and time at the paper's scale.

The supplement's computational cost (about five days on four A100s for preprocessing and the 2,000 Stage-2
iterations) leaves Stage 2 little room: each iteration runs N student forwards with gradient and N teacher
forwards (supplement A.4). Each switch below computes the same function, so none changes a product
(``tracegs.restorer.config.TransformerConfig``); each is tested for equal outputs on the CPU:

- activation checkpointing on a share of the blocks (``checkpoint_blocks``): the activations of the blocks it
  wraps are recomputed in backward instead of kept. Every block (share 1) is what fits a 5B student on any card;
  a card with memory to spare keeps more and recomputes less;
- ``torch.compile`` of each block (``compile_blocks``): PyTorch's regional compilation, one graph that every block
  of the same structure shares, instead of the whole model's;
- the SDPA kernel each attention call runs on (``AttentionKernels``): the fused kernels (flash, cuDNN, memory-
  efficient) never materialise the attention matrix; PyTorch's math fallback does, silently.

LoRA computed in bfloat16 with float32 master factors is the adapters' own setting
(``tracegs.restorer.adapters.set_lora_compute``): it changes the rounding of every adapted projection.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend
from torch.overrides import TorchFunctionMode
from torch.utils.checkpoint import checkpoint

from tracegs.errors import ConfigError

if TYPE_CHECKING:
    from tracegs.restorer.config import BackboneConfig
    from tracegs.restorer.transformer import ReferenceGuidedTransformer

log = logging.getLogger(__name__)

FUSED_FIELD = "backbone.transformer.require_fused_attention"
BACKEND_FIELD = "backbone.transformer.compile_backend"
# The names a log line and the GPU check give PyTorch's SDPA backends (torch.nn.attention.SDPBackend).
KERNEL_NAMES = {SDPBackend.FLASH_ATTENTION: "flash", SDPBackend.EFFICIENT_ATTENTION: "efficient",
                SDPBackend.CUDNN_ATTENTION: "cudnn", SDPBackend.MATH: "math",
                SDPBackend.OVERRIDEABLE: "overrideable", SDPBackend.ERROR: "none"}
UNFUSED = ("math", "none")


def checkpoint_blocks(transformer: ReferenceGuidedTransformer, share: float) -> int:
    """Recompute in backward the activations of the first ``round(share x blocks)`` blocks (non-reentrant
    ``torch.utils.checkpoint``, as diffusers' own gradient checkpointing); the others keep theirs. Returns how
    many blocks are wrapped. Which blocks does not matter for memory: every block's activations live until its
    backward, and every block is the same size."""
    blocks = list(transformer.transformer_blocks)
    count = round(share * len(blocks))
    if count == 0:
        transformer.disable_gradient_checkpointing()
        return 0
    wrapped = {id(block) for block in blocks[:count]}

    def run_block(block: torch.nn.Module, *args):
        if id(block) in wrapped:
            return checkpoint(block.__call__, *args, use_reentrant=False)
        return block(*args)

    # diffusers' block loop calls this for every block whenever gradients are enabled.
    transformer.enable_gradient_checkpointing(run_block)
    return count


def compile_blocks(transformer: ReferenceGuidedTransformer, backend: str) -> None:
    """``torch.compile`` each block in place (``nn.Module.compile``: parameter names, state dicts and the adapters
    peft injects later stay as they are; compilation happens at the first call). Dynamo guards on parameters
    rather than on the module, so the blocks share their graphs (PyTorch's "regional compilation" recipe); whether
    gradients are on, and whether the retrieval response is read, are guarded: Stage 2's student and teacher calls
    get a few graphs, all traced in the first iteration (measured on the rehearsal: no recompilation after it)."""
    if isinstance(backend, str) and backend not in torch.compiler.list_backends(exclude_tags=()):
        raise ConfigError(BACKEND_FIELD, f"{backend!r} is not a torch.compile backend here (have "
                                         f"{', '.join(torch.compiler.list_backends())})")
    for block in transformer.transformer_blocks:
        block.compile(backend=backend)


@torch.compiler.disable  # asked outside a compiled block's graph: dynamo cannot build guards around the call
def sdpa_kernel(query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, attn_mask=None, dropout_p: float = 0.0,
                is_causal: bool = False, scale: float | None = None, enable_gqa: bool = False) -> str:
    """The kernel ``F.scaled_dot_product_attention`` picks for these arguments (PyTorch's own choice function).
    Under autocast the call runs in the autocast dtype (SDPA is on its lower-precision list), so it is asked
    about that dtype."""
    device = query.device.type
    if torch.is_autocast_enabled(device) and query.is_floating_point():
        dtype = torch.get_autocast_dtype(device)
        query, key, value = (tensor.to(dtype) for tensor in (query, key, value))
    choice = torch._fused_sdp_choice(query, key, value, attn_mask, dropout_p, is_causal, scale=scale,
                                     enable_gqa=enable_gqa)
    return KERNEL_NAMES[SDPBackend(choice)]


class AttentionKernels(TorchFunctionMode):
    """Within ``with``: count the kernel of every SDPA call (``counts``); with ``require_fused``, refuse the first
    call that would run on the math fallback, in one line naming ``require_fused_attention``, before it runs.
    A checkpointed block's recomputation in backward (inside the autograd engine) is not seen: it repeats a forward
    call that was."""

    def __init__(self, require_fused: bool = False):
        super().__init__()
        self.require_fused = require_fused
        self.counts: Counter[str] = Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is F.scaled_dot_product_attention:
            kernel = sdpa_kernel(*args, **kwargs)
            self.counts[kernel] += 1
            if self.require_fused and kernel in UNFUSED:
                query = args[0] if args else kwargs["query"]
                raise ConfigError(FUSED_FIELD, f"attention would run on PyTorch's {kernel} kernel on "
                                  f"{query.device} ({str(query.dtype).removeprefix('torch.')}, head dim "
                                  f"{query.shape[-1]}), no fused SDPA kernel (flash, cuDNN, efficient) takes these "
                                  "inputs; set it to false to run unfused")
        return func(*args, **kwargs)

    def summary(self) -> str:
        """One line: the kernels the recorded calls ran on."""
        calls = ", ".join(f"{kernel} x{count}" for kernel, count in self.counts.most_common())
        fused = "fused" if self.counts and not set(self.counts) & set(UNFUSED) else "NOT all fused"
        return f"attention (SDPA) kernels: {calls or 'no calls'} ({fused})"


def apply_switches(transformer: ReferenceGuidedTransformer, cfg: BackboneConfig) -> None:
    """The switches of ``cfg.transformer`` and ``cfg.lora`` on a built transformer: checkpointing, compilation and
    the adapters' compute dtype (the attention check runs in a fit's first step: tracegs.training.attention)."""
    from tracegs.restorer.adapters import set_lora_compute

    t = cfg.transformer
    if t.activation_checkpointing:
        count = checkpoint_blocks(transformer, t.activation_checkpointing)
        log.info("activation checkpointing: %d of %d blocks", count, len(transformer.transformer_blocks))
    if t.compile_blocks:
        compile_blocks(transformer, t.compile_backend)
    set_lora_compute(transformer, cfg.lora.compute_bf16)
