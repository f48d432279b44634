"""Bytes each restorer component holds, counted on the meta device (no memory used, no weights read).

Training: the frozen base, the float32 LoRA adapters, the student's gradients and AdamW state of one Stage-2
rank (benchmarks/stage2_memory.py). Deployment / evaluation (Algorithm 1, bottom): one frozen backbone shared by
variant A and TRACE-GS (deploy/assembly.py), the VAE, and the frozen encoders, which with
``backbone.offload_encoders`` live on the CPU and visit the accelerator only while they encode (encoders.py),
like the BLIP-2 captioner (data/captions.py). Encoder shapes come from the ``config.json`` of each weights
folder, so the figure is that of the weights the run will load.
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from tracegs.restorer.adapters import adapter_parameters, add_adapter, clone_adapter
from tracegs.restorer.build import create_transformer
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.encoders import VGGT_INSTALL_HINT, encoder_placement
from tracegs.restorer.loading import MissingPackageError, require_local_dir, torch_dtype

GIB = 2**30


def _tensor_bytes(tensors: Sequence[torch.Tensor]) -> int:
    return sum(t.numel() * t.element_size() for t in tensors)


def module_bytes(module: torch.nn.Module) -> int:
    """Bytes of a module's parameters and buffers (exact on the meta device: numel x element size)."""
    return _tensor_bytes([*module.parameters(), *module.buffers()])


def base_transformer(cfg: BackboneConfig) -> torch.nn.Module:
    """The frozen transformer theta at ``cfg``'s shapes and dtype, on the meta device."""
    return create_transformer(cfg.transformer, "meta").to(torch_dtype(cfg.transformer.dtype, "transformer.dtype"))


def training_component_bytes(cfg: BackboneConfig) -> dict[str, int]:
    """Bytes per Stage-2 training-rank component at ``cfg``'s shapes: the frozen base, the student and teacher
    adapters (float32 factors), the student's gradients and AdamW's two moments; plus the adapter's parameters."""
    model = base_transformer(cfg)
    base = module_bytes(model)
    add_adapter(model, "student", cfg.lora)
    clone_adapter(model, "student", "teacher", trainable=False)
    student = _tensor_bytes(adapter_parameters(model, "student"))
    return {
        "transformer_base": base,
        "student_adapter": student,
        "teacher_adapter": _tensor_bytes(adapter_parameters(model, "teacher")),
        "student_grads": student,
        "adamw_state": 2 * student,
        "adapter_params": sum(p.numel() for p in adapter_parameters(model, "student")),
    }


@dataclass
class Holding:
    """One component of a deployment run: where its weights live between uses, and while it runs."""

    component: str
    dtype: str
    bytes: int
    home: str  # where the weights stay for the run
    visits: str | None = None  # the device it moves to only while it runs (offloaded encoders, the captioner)


def _meta(build) -> torch.nn.Module:
    with torch.device("meta"):
        return build()


def _vae(path: Path) -> torch.nn.Module:
    from diffusers import AutoencoderKLCogVideoX

    return _meta(lambda: AutoencoderKLCogVideoX.from_config(AutoencoderKLCogVideoX.load_config(path)))


def _t5(path: Path) -> torch.nn.Module:
    from transformers import T5Config, T5EncoderModel

    return _meta(lambda: T5EncoderModel(T5Config.from_pretrained(path)))


def _dinov2(path: Path) -> torch.nn.Module:
    from transformers import AutoConfig, AutoModel

    return _meta(lambda: AutoModel.from_config(AutoConfig.from_pretrained(path)))


def _vggt(path: Path) -> torch.nn.Module:
    """VGGT from its folder's ``config.json`` (the keyword arguments its hub mixin stores)."""
    try:
        from vggt.models.vggt import VGGT
    except ImportError as err:
        raise MissingPackageError(VGGT_INSTALL_HINT) from err
    config = path / "config.json"
    stored = json.loads(config.read_text()) if config.is_file() else {}
    accepted = inspect.signature(VGGT).parameters
    return _meta(lambda: VGGT(**{k: v for k, v in stored.items() if k in accepted}))


def _blip2(path: Path) -> torch.nn.Module:
    from transformers import Blip2Config, Blip2ForConditionalGeneration

    return _meta(lambda: Blip2ForConditionalGeneration(Blip2Config.from_pretrained(path)))


def loads_pretrained_components(cfg: BackboneConfig) -> bool:
    """True at paper scale: the codec or an encoder is read from a weights folder (the embedded default has none)."""
    kinds = {cfg.codec.kind, cfg.text_encoder.kind, cfg.reference_encoder.kind}
    return kinds != {"embedded"}


def deployment_holdings(cfg: BackboneConfig, adapters: Sequence[str], captioner: tuple[str, torch.dtype] | None,
                        accelerator: str) -> list[Holding]:
    """What a deployment / evaluation run on ``accelerator`` holds: the shared base, each adapter loaded on it
    (``adapters``: their names), the VAE, the encoders and the captioner (``captioner``: its BLIP-2 folder and
    dtype, or None)."""
    model = base_transformer(cfg)
    holdings = [Holding("transformer (shared base)", cfg.transformer.dtype, module_bytes(model), accelerator)]
    for name in adapters:
        add_adapter(model, name, cfg.lora)
        holdings.append(Holding(f"adapter {name}", "float32", _tensor_bytes(adapter_parameters(model, name)),
                                accelerator))
    if cfg.codec.kind == "cogvideox":  # the codec builds the VAE in float32 (codec.build_codec)
        vae = _vae(require_local_dir(cfg.codec.pretrained_path, "codec.pretrained_path"))
        holdings.append(Holding("VAE", "float32", module_bytes(vae), accelerator))
    home, visits = encoder_placement(accelerator, cfg.offload_encoders)
    encoders = []
    if cfg.text_encoder.kind == "t5":
        encoders.append(("T5 text encoder", cfg.text_encoder.dtype,
                         _t5(require_local_dir(cfg.text_encoder.pretrained_path, "text_encoder.pretrained_path"))))
    if cfg.reference_encoder.kind == "dinov2_vggt":
        ref = cfg.reference_encoder
        encoders.append(("DINOv2", ref.dtype, _dinov2(require_local_dir(ref.dino_path, "reference_encoder.dino_path"))))
        encoders.append(("VGGT", ref.dtype, _vggt(require_local_dir(ref.vggt_path, "reference_encoder.vggt_path"))))
    for name, dtype, module in encoders:
        holdings.append(Holding(name, dtype, module_bytes(module.to(torch_dtype(dtype, name))), home, visits))
    if captioner is not None:
        path, dtype = captioner
        blip2 = _blip2(require_local_dir(path, "deploy.captions.blip2_path")).to(dtype)
        home, visits = encoder_placement(accelerator, offload=True)  # released after each round (deploy/refine.py)
        holdings.append(Holding("BLIP-2 captioner", str(dtype).removeprefix("torch."), module_bytes(blip2), home,
                                visits))
    return holdings


def device_totals(holdings: Sequence[Holding]) -> dict[str, int]:
    """Peak bytes of weights per device: everything at home there, plus the largest visitor (one runs at a time)."""
    totals: dict[str, int] = {}
    for h in holdings:
        totals[h.home] = totals.get(h.home, 0) + h.bytes
    for device in {h.visits for h in holdings if h.visits is not None}:
        largest = max(h.bytes for h in holdings if h.visits == device)
        totals[device] = totals.get(device, 0) + largest
    return totals


def _size(n: int) -> str:
    return f"{n / GIB:.3f} GiB" if n >= GIB else f"{n / 2**20:.3f} MiB"


def holdings_table(holdings: Sequence[Holding]) -> str:
    """The per-component, per-device figure printed at the start of a paper-scale deployment / evaluation."""
    lines = ["weights each component holds (counted on the meta device):"]
    for h in holdings:
        where = h.home if h.visits is None else f"{h.home}, on {h.visits} only while it runs"
        lines.append(f"  {h.component:<26} {h.dtype:<9} {_size(h.bytes):>12}  {where}")
    lines.append("  peak per device (weights only, before activations): " + ", ".join(
        f"{device} {_size(total)}" for device, total in sorted(device_totals(holdings).items())))
    return "\n".join(lines)
