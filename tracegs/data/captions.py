"""Clip captions (supplement A.2, "Text tokens"): one rule for the training clips and the deployed clips.

Paper scale: a frozen BLIP-2 captioner (transformers, local weights) describes the first frame of the sparse
rendering R_s; the text encoder appends the fixed quality suffix (``TextEncoder.prompt``). Embedded scale
(``blip2_path`` unset): a deterministic source, the scene's ``caption.txt`` (the synthetic benchmark writes
one describing its objects), else ``fallback``. Prepare and deployment both call ``clip_caption`` with the
same ``CaptionConfig`` (``data.prepare.captions`` is ``deploy.captions``), so a restorer deploys on the
captions it was trained on.
"""

from __future__ import annotations

from pathlib import Path

import torch
from PIL import Image
from torch import Tensor

from tracegs.data.config import CaptionConfig
from tracegs.devices import accelerator


def require_captioner(cfg: CaptionConfig, field: str) -> None:
    """Fail before any work when the configured BLIP-2 weights are missing."""
    if cfg.blip2_path is not None and not Path(cfg.blip2_path).is_dir():
        raise FileNotFoundError(f"{field}.blip2_path={cfg.blip2_path!r}: no BLIP-2 weights there")


def captioner_dtype(device: str) -> torch.dtype:
    """BLIP-2 runs in bf16 when the run has a GPU (inference only), in float32 on a CPU-only machine."""
    return torch.bfloat16 if torch.device(device).type == "cuda" else torch.float32


# path -> (processor, model): each BLIP-2 is loaded once per process; its home is the CPU (release_captioner).
_CAPTIONERS: dict[str, tuple] = {}


def _blip2(path: str, device: str):
    """The frozen BLIP-2 captioner on ``device`` (bf16 when a GPU is present)."""
    if path not in _CAPTIONERS:
        from transformers import Blip2ForConditionalGeneration, Blip2Processor

        dtype = captioner_dtype(accelerator())
        processor = Blip2Processor.from_pretrained(path, local_files_only=True)
        model = Blip2ForConditionalGeneration.from_pretrained(path, local_files_only=True, torch_dtype=dtype)
        _CAPTIONERS[path] = (processor, model.eval())
    processor, model = _CAPTIONERS[path]
    return processor, model.to(device)


def release_captioner() -> None:
    """Move every loaded BLIP-2 off the accelerator. Deployment calls this after captioning a round's clips,
    before the restorer denoises them; the next ``clip_caption`` brings the captioner back. No GPU: no-op."""
    if _CAPTIONERS and torch.cuda.is_available():
        for _, model in _CAPTIONERS.values():
            model.to("cpu")
        torch.cuda.empty_cache()


@torch.no_grad()
def clip_caption(cfg: CaptionConfig, first_frame: Tensor, scene_caption: str | None) -> str:
    """The caption of one clip from the first frame [3,H,W] in [0,1] of its R_s (see the module docstring)."""
    if cfg.blip2_path is None:
        return scene_caption or cfg.fallback
    device = accelerator()
    processor, model = _blip2(cfg.blip2_path, device)
    pixels = (first_frame.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    inputs = processor(images=Image.fromarray(pixels), return_tensors="pt").to(device, model.dtype)
    tokens = model.generate(**inputs, max_new_tokens=cfg.max_new_tokens)
    return processor.batch_decode(tokens, skip_special_tokens=True)[0].strip() or cfg.fallback
