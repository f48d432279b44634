"""Assemble a restorer backbone from ``BackboneConfig`` (either scale) and load pretrained transformers."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from safetensors import SafetensorError

from tracegs.errors import InputFileError, one_line
from tracegs.restorer.codec import Codec, build_codec
from tracegs.restorer.config import BackboneConfig, TransformerConfig
from tracegs.restorer.encoders import TextEncoder, build_reference_encoder, build_text_encoder
from tracegs.restorer.loading import require_local_dir, torch_dtype
from tracegs.restorer.schedules import NoiseSchedule, build_schedule
from tracegs.restorer.transformer import ReferenceGuidedTransformer


class CheckpointMismatchError(ValueError):
    """A pretrained transformer directory does not hold exactly the weights the model needs."""


def transformer_kwargs(cfg: TransformerConfig) -> dict:
    """diffusers config keys of ``ReferenceGuidedTransformer`` for a ``TransformerConfig``."""
    return dict(
        num_layers=cfg.num_layers,
        num_attention_heads=cfg.num_attention_heads,
        attention_head_dim=cfg.attention_head_dim,
        in_channels=2 * cfg.latent_channels,
        out_channels=cfg.latent_channels,
        text_embed_dim=cfg.text_embed_dim,
        max_text_seq_length=cfg.max_text_seq_length,
        time_embed_dim=cfg.time_embed_dim,
        patch_size=cfg.patch_size,
        sample_frames=cfg.sample_frames,
        sample_height=cfg.sample_height,
        sample_width=cfg.sample_width,
        temporal_compression_ratio=cfg.temporal_compression_ratio,
        use_rotary_positional_embeddings=cfg.use_rotary_positional_embeddings,
        use_learned_positional_embeddings=cfg.use_learned_positional_embeddings,
        attention_bias=cfg.attention_bias,
        ref_2d_dim=cfg.ref_2d_dim,
        ref_3d_dim=cfg.ref_3d_dim,
        reference_norms=cfg.reference_norms,
        timestep_scale=cfg.timestep_scale,
        prediction=cfg.prediction,
        clean_min_time=cfg.clean_min_time,
        sigma_data=cfg.sigma_data,
    )


def create_transformer(
    cfg: TransformerConfig, device: torch.device | str = "cpu"
) -> ReferenceGuidedTransformer:
    """Randomly initialised model; ``device="meta"`` builds the paper-scale model without memory."""
    with torch.device(device):
        return ReferenceGuidedTransformer(**transformer_kwargs(cfg))


def load_transformer(
    cfg: TransformerConfig, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
) -> ReferenceGuidedTransformer:
    """Load ``cfg.pretrained_path`` (diffusers layout). The directory's config must agree with ``cfg`` and its
    weights must cover the model exactly; otherwise the error lists the differing fields / keys."""
    path = require_local_dir(cfg.pretrained_path, "transformer.pretrained_path")
    fix = ("point backbone.transformer.pretrained_path (or artifacts.baseline_weights) at a complete diffusers "
           "directory, or re-run tracegs-train stage=baseline")
    try:
        stored = ReferenceGuidedTransformer.load_config(path)
    except (OSError, ValueError) as error:  # diffusers: EnvironmentError / JSON errors, message names no field
        raise InputFileError(path / "config.json", f"no readable diffusers config ({one_line(error)})", fix) from error
    # Checkpoints without the key (plain CogVideoX, or ours from before it existed) predict velocity; reading
    # them as x0 predictions would silently change what the weights mean.
    stored.setdefault("prediction", "velocity")
    wanted = transformer_kwargs(cfg)
    differing = {k: (stored[k], v) for k, v in wanted.items() if k in stored and stored[k] != v}
    if differing:
        raise CheckpointMismatchError(
            f"{path}/config.json disagrees with the transformer config (stored, wanted): {differing}"
        )
    # Keys a plain CogVideoX config lacks (reference dims, timestep scale) come from ``cfg``.
    absent = {k: v for k, v in wanted.items() if k not in stored}
    try:
        # use_safetensors: without it diffusers falls back to unpickling a .bin file.
        model, info = ReferenceGuidedTransformer.from_pretrained(
            path, torch_dtype=dtype, output_loading_info=True, use_safetensors=True, **absent
        )
    except (OSError, SafetensorError, ValueError) as error:  # no weights file, or a truncated / garbage one
        raise InputFileError(path, f"cannot load the transformer weights ({one_line(error)})", fix) from error
    unmapped = unmapped_key(info)
    if unmapped:
        raise CheckpointMismatchError(f"{path}: {unmapped}")
    return model.to(device)


def unmapped_key(info: dict) -> str | None:
    """One line naming the first weight that does not map between the folder and the model, or None.

    Strict in both directions: a stored tensor the model does not use (a key that would be dropped) is as
    wrong as a model weight the folder lacks (one that would stay randomly initialised).
    """
    unexpected, missing = sorted(info.get("unexpected_keys", [])), sorted(info.get("missing_keys", []))
    mismatched = sorted(info.get("mismatched_keys", []))
    counts = f"({len(unexpected)} unused, {len(missing)} missing, {len(mismatched)} of another shape)"
    if unexpected:
        return f"stored weight '{unexpected[0]}' has no place in the model {counts}"
    if missing:
        return f"model weight '{missing[0]}' is not in the folder {counts}"
    if mismatched:
        key, stored, wanted = mismatched[0]
        return f"weight '{key}' is stored as {tuple(stored)} but the model needs {tuple(wanted)} {counts}"
    return None


@dataclass
class Backbone:
    """Runtime bundle of the frozen restorer: v_theta plus its frozen codec / encoders and the schedule."""

    transformer: ReferenceGuidedTransformer
    codec: Codec | None  # None: built for training, which reads latents and tokens from the cache
    reference_encoder: object | None
    text_encoder: TextEncoder | None
    schedule: NoiseSchedule
    cfg: BackboneConfig


def _check_compatible(cfg: BackboneConfig, codec: Codec | None, reference_encoder: object | None) -> None:
    t = cfg.transformer
    problems = []
    channels = cfg.codec.latent_channels if codec is None else codec.latent_channels
    if channels != t.latent_channels:
        problems.append(
            f"codec latent channels {channels} != transformer.latent_channels {t.latent_channels}"
        )
    if cfg.text_encoder.dim != t.text_embed_dim:
        problems.append(
            f"text_encoder.dim {cfg.text_encoder.dim} != transformer.text_embed_dim {t.text_embed_dim}"
        )
    if cfg.text_encoder.max_length != t.max_text_seq_length:
        problems.append(
            f"text_encoder.max_length {cfg.text_encoder.max_length} != "
            f"transformer.max_text_seq_length {t.max_text_seq_length}"
        )
    for attr, field in (("dim_2d", "ref_2d_dim"), ("dim_3d", "ref_3d_dim")):
        have = getattr(reference_encoder, attr, None)
        if have is not None and have != getattr(t, field):
            problems.append(
                f"reference encoder gives {have} features but transformer.{field}={getattr(t, field)}"
            )
    if problems:
        raise ValueError(f"backbone '{cfg.name}' is inconsistent: " + "; ".join(problems))


def with_encoders(backbone: Backbone, device: torch.device | str = "cpu") -> Backbone:
    """``backbone`` (built for training, ``encoders=False``) completed with its frozen codec and encoders, sharing
    its transformer: what deploying the restorer being trained needs."""
    if backbone.codec is not None:
        return backbone
    cfg, offload = backbone.cfg, backbone.cfg.offload_encoders
    codec = build_codec(cfg.codec, device)
    reference_encoder = build_reference_encoder(cfg.reference_encoder, device, offload)
    _check_compatible(cfg, codec, reference_encoder)
    return replace(backbone, codec=codec, reference_encoder=reference_encoder,
                   text_encoder=build_text_encoder(cfg.text_encoder, device, offload))


def build_backbone(cfg: BackboneConfig, device: torch.device | str = "cpu", encoders: bool = True) -> Backbone:
    """Frozen backbone theta (no adapters yet: see ``adapters.add_adapter`` / ``load_adapter``).

    ``encoders=False`` builds only the transformer and the schedule, what a training rank runs: the prepared
    cache already holds the VAE latents, reference tokens and text embeddings, so the VAE, DINOv2, VGGT and
    T5 (several GB per rank at paper scale) are neither loaded nor required to be installed.
    """
    codec = build_codec(cfg.codec, device) if encoders else None
    offload = cfg.offload_encoders
    reference_encoder = build_reference_encoder(cfg.reference_encoder, device, offload) if encoders else None
    _check_compatible(cfg, codec, reference_encoder)
    dtype = torch_dtype(cfg.transformer.dtype, "transformer.dtype")
    if cfg.transformer.pretrained_path:
        transformer = load_transformer(cfg.transformer, device, dtype)
    else:
        transformer = create_transformer(cfg.transformer, device)
        if dtype != torch.float32:  # (diffusers warns on any .to(dtype), even a no-op one)
            transformer.to(dtype)
    transformer.requires_grad_(False).eval()
    if cfg.transformer.gradient_checkpointing:
        transformer.enable_gradient_checkpointing()
    return Backbone(
        transformer=transformer,
        codec=codec,
        reference_encoder=reference_encoder,
        text_encoder=build_text_encoder(cfg.text_encoder, device, offload) if encoders else None,
        schedule=build_schedule(cfg.schedule),
        cfg=cfg,
    )
