"""Assemble a restorer backbone from ``BackboneConfig`` (either scale) and load pretrained transformers."""

from __future__ import annotations

import json
import logging
import pickle
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from diffusers.models.embeddings import CogVideoXPatchEmbed
from diffusers.utils import CONFIG_NAME, SAFE_WEIGHTS_INDEX_NAME, SAFETENSORS_WEIGHTS_NAME, WEIGHTS_NAME
from safetensors import SafetensorError, safe_open
from torch import nn

from tracegs.errors import InputFileError, one_line
from tracegs.restorer.codec import Codec, build_codec
from tracegs.restorer.config import BackboneConfig, TransformerConfig
from tracegs.restorer.encoders import TextEncoder, build_reference_encoder, build_text_encoder
from tracegs.restorer.loading import require_local_dir, torch_dtype
from tracegs.restorer.schedules import NoiseSchedule, build_schedule
from tracegs.restorer.speed import apply_switches
from tracegs.restorer.transformer import ReferenceGuidedTransformer

log = logging.getLogger(__name__)

# The escape hatch for stored tensors the class has no place for (TransformerConfig.skip_stored_keys).
SKIP_FIELD = "backbone.transformer.skip_stored_keys"


class CheckpointMismatchError(ValueError):
    """A pretrained transformer directory does not hold exactly the weights the model needs."""


def transformer_kwargs(cfg: TransformerConfig) -> dict:
    """diffusers config keys of ``ReferenceGuidedTransformer`` for a ``TransformerConfig`` (not its loading
    settings: ``pretrained_path``, ``skip_stored_keys``, ``dtype`` and the execution switches of tracegs.restorer.speed)."""
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
        noise_scale=cfg.noise_scale,
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
    """Load ``cfg.pretrained_path`` strictly, in every layout GSFixer's own loader reads.

    GSFixer's ``CogVideoXCrossTransformer3DModel.from_pretrained_2d`` (``Reconstruction/gsfixer/cogvideo/
    crosstransformer3d.py`` l. 862-951) reads ``config.json`` in the folder it is given (l. 871-875; its scripts
    pass the downloaded ``checkpoints/GSFixer`` itself), so ``pretrained_path`` is that folder; a folder whose
    ``transformer/`` subfolder holds ``config.json`` is accepted as well (diffusers' ``subfolder`` convention,
    as in a CogVideoX pipeline folder; GSFixer's ``subfolder`` argument, l. 865-866). The folder itself wins
    when both hold one. Its weights are read as ``_weight_files`` lists them.

    Where GSFixer's loader resizes a ``patch_embed.proj.weight`` of another shape and then drops every key
    it cannot use and loads the rest non-strictly (l. 900-951), ours is strict: the stored config must agree
    with ``cfg``, and the stored tensors must cover the model exactly, shapes included (``unmapped_key``);
    a stored tensor the class has no place for loads only when ``cfg.skip_stored_keys`` names it.

    The model is built on the meta device (the paper's has 5B parameters: random weights would be
    materialised only to be overwritten) and takes the stored tensors as they are, cast to ``dtype`` as
    diffusers' ``from_pretrained(torch_dtype=...)`` casts them (tensor by tensor, a ``_keep_in_fp32_modules``
    module's staying float32); it comes back in eval mode with its config registered (``_name_or_path``
    included), so ``model.config`` and ``save_pretrained`` work as after ``from_pretrained``.
    """
    path = require_local_dir(cfg.pretrained_path, "transformer.pretrained_path")
    fix = ("point backbone.transformer.pretrained_path (or artifacts.baseline_weights) at a complete diffusers "
           "directory, or re-run tracegs-train stage=baseline")
    folder = _config_folder(path, fix)
    try:
        stored = ReferenceGuidedTransformer.load_config(folder)
    except (OSError, ValueError) as error:  # diffusers: EnvironmentError / JSON errors, message names no field
        raise InputFileError(folder / CONFIG_NAME, f"no readable diffusers config ({one_line(error)})",
                             fix) from error
    # Checkpoints without the key (plain CogVideoX, or ours from before it existed) predict velocity; reading
    # them as x0 predictions would silently change what the weights mean.
    stored.setdefault("prediction", "velocity")
    wanted = transformer_kwargs(cfg)
    differing = {k: (stored[k], v) for k, v in wanted.items() if k in stored and stored[k] != v}
    if differing:
        raise CheckpointMismatchError(
            f"{folder}/config.json disagrees with the transformer config (stored, wanted): {differing}"
        )
    # Keys a plain CogVideoX config lacks (reference dims, timestep scale) come from ``cfg``.
    absent = {k: v for k, v in wanted.items() if k not in stored}
    with torch.device("meta"):
        model = ReferenceGuidedTransformer.from_config(stored, **absent)
    needed = {key: tuple(value.shape) for key, value in model.state_dict().items()}

    weights = _StoredWeights(folder, fix)
    skip = _skipped_keys(folder, weights.shapes, needed, cfg.skip_stored_keys)
    unmapped = unmapped_key(*_key_differences({k: s for k, s in weights.shapes.items() if k not in skip}, needed))
    if unmapped:
        raise CheckpointMismatchError(f"{folder}: {unmapped}")
    state = weights.read(needed, fix)
    # Cast tensor by tensor, as diffusers' load_model_dict_into_meta does, rather than ``model.to(dtype)``
    # afterwards: that would also cast the non-persistent buffers from_pretrained leaves as built, ignore
    # _keep_in_fp32_modules, and ModelMixin.to warns on every dtype cast.
    keep_fp32 = ReferenceGuidedTransformer._keep_in_fp32_modules or []
    for key, value in state.items():
        if value.is_floating_point():
            fp32 = any(module in key.split(".") for module in keep_fp32)
            state[key] = value.to(torch.float32 if fp32 else dtype)
    model.load_state_dict(state, strict=True, assign=True)
    del state  # the model holds the tensors now; moving it to ``device`` frees each CPU copy in turn
    _rebuild_non_persistent_buffers(model)
    model.register_to_config(_name_or_path=str(folder))  # as from_pretrained
    return model.eval().to(device)


def unmapped_key(
    unexpected: Sequence[str], missing: Sequence[str], mismatched: Sequence[tuple[str, tuple, tuple]]
) -> str | None:
    """One line naming the first weight that does not map between the folder and the model, or None.

    Strict in both directions: a stored tensor the model does not use (a key GSFixer's loader would drop) is
    as wrong as a model weight the folder lacks (one that would stay randomly initialised). ``mismatched``
    holds (key, stored shape, wanted shape).
    """
    unexpected, missing, mismatched = sorted(unexpected), sorted(missing), sorted(mismatched)
    counts = f"({len(unexpected)} unused, {len(missing)} missing, {len(mismatched)} of another shape)"
    if unexpected:
        return (f"stored weight '{unexpected[0]}' has no place in the model {counts}; if such stored tensors "
                f"are meant to go unused, list them in {SKIP_FIELD}")
    if missing:
        return f"model weight '{missing[0]}' is not in the folder {counts}"
    if mismatched:
        key, stored, wanted = mismatched[0]
        return f"weight '{key}' is stored as {tuple(stored)} but the model needs {tuple(wanted)} {counts}"
    return None


def _key_differences(
    stored: Mapping[str, tuple[int, ...]], needed: Mapping[str, tuple[int, ...]]
) -> tuple[list[str], list[str], list[tuple[str, tuple[int, ...], tuple[int, ...]]]]:
    """(unexpected, missing, shape-mismatched) keys of a folder's tensors against the model's state dict."""
    unexpected = [key for key in stored if key not in needed]
    missing = [key for key in needed if key not in stored]
    mismatched = [(key, stored[key], shape) for key, shape in needed.items()
                  if key in stored and stored[key] != shape]
    return unexpected, missing, mismatched


def _config_folder(path: Path, fix: str) -> Path:
    """The folder holding ``config.json``: ``path`` itself (GSFixer's download; its loader reads the folder it
    is given, crosstransformer3d.py l. 871-875) or else ``path/transformer`` (diffusers' subfolder layout)."""
    for folder in (path, path / "transformer"):
        if (folder / CONFIG_NAME).is_file():
            return folder
    raise InputFileError(path / CONFIG_NAME, f"no diffusers config here nor in {path / 'transformer'}", fix)


def _weight_files(folder: Path, fix: str) -> list[Path]:
    """The files holding a transformer's tensors, in order of preference.

    GSFixer's loader (crosstransformer3d.py l. 880-898) takes ``diffusion_pytorch_model.bin`` first (unpickled
    by ``torch.load``), then ``diffusion_pytorch_model.safetensors``, then every ``*.safetensors`` in the folder
    merged (shards, whether or not an index lies beside them). We prefer safetensors, which cannot run code
    when read, and read a ``.bin`` only as the last resort and only with ``weights_only`` (``_read_bin``).
    """
    single = folder / SAFETENSORS_WEIGHTS_NAME
    if single.is_file():
        return [single]
    shards = sorted(p for p in folder.glob("*.safetensors") if p.is_file())
    if shards:
        _check_shard_index(folder, shards, fix)
        return shards
    pickled = folder / WEIGHTS_NAME
    if pickled.is_file():
        return [pickled]
    raise InputFileError(folder, f"holds no {SAFETENSORS_WEIGHTS_NAME}, *.safetensors shards or {WEIGHTS_NAME}",
                         fix)


def _check_shard_index(folder: Path, shards: list[Path], fix: str) -> None:
    """A shard the index names but the folder lacks (an interrupted download) is named as such, rather than
    surfacing as the first model weight missing from the shards that are there."""
    index = folder / SAFE_WEIGHTS_INDEX_NAME
    if not index.is_file():
        return
    try:
        named = set(json.loads(index.read_text())["weight_map"].values())
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
        raise InputFileError(index, f"is not a readable shard index ({one_line(error)})", fix) from error
    absent = sorted(named - {p.name for p in shards})
    if absent:
        raise InputFileError(index, f"names shard '{absent[0]}' ({len(absent)} absent in all), which the folder "
                             "does not hold", fix)


def _read_bin(file: Path, fix: str) -> dict[str, torch.Tensor]:
    """A pickled state dict, read without unpickling anything but tensors and plain containers: a ``.bin``
    can carry code that ``torch.load`` would otherwise run (GSFixer's loader reads it unrestricted, l. 883)."""
    try:
        state = torch.load(file, map_location="cpu", weights_only=True, mmap=True)
    except (OSError, RuntimeError, ValueError, EOFError, pickle.UnpicklingError) as error:
        raise InputFileError(file, f"cannot load the transformer weights ({one_line(error)})", fix) from error
    if not isinstance(state, Mapping):
        raise InputFileError(file, f"holds a {type(state).__name__}, not a state dict", fix)
    for key, value in state.items():
        if not isinstance(key, str) or not isinstance(value, torch.Tensor):
            raise InputFileError(file, f"holds {type(value).__name__} under {key!r}, not a tensor", fix)
    return dict(state)


class _StoredWeights:
    """A folder's tensors (``_weight_files``): their shapes, then the tensors themselves (``read``).

    Safetensors shapes come from the file headers, so a folder that does not map is refused before gigabytes
    are read; a ``.bin`` is memory-mapped."""

    def __init__(self, folder: Path, fix: str) -> None:
        self.files = _weight_files(folder, fix)
        self.shapes: dict[str, tuple[int, ...]] = {}
        self._where: dict[str, Path] = {}
        self._tensors: dict[str, torch.Tensor] | None = None
        if self.files[0].name == WEIGHTS_NAME:
            self._tensors = _read_bin(self.files[0], fix)
            self.shapes = {key: tuple(value.shape) for key, value in self._tensors.items()}
            return
        for file in self.files:
            try:
                with safe_open(file, framework="pt") as handle:
                    shapes = {key: tuple(handle.get_slice(key).get_shape()) for key in handle.keys()}
            except (OSError, SafetensorError) as error:  # a truncated / garbage file
                raise InputFileError(file, f"cannot load the transformer weights ({one_line(error)})",
                                     fix) from error
            for key, shape in shapes.items():
                if key in self._where:  # GSFixer's merge would keep whichever file it read last
                    raise InputFileError(folder, f"weight '{key}' is stored twice, in {self._where[key].name} "
                                         f"and {file.name}", "leave one copy of each tensor in the folder")
                self._where[key], self.shapes[key] = file, shape

    def read(self, keys: Iterable[str], fix: str) -> dict[str, torch.Tensor]:
        """The tensors under ``keys``, on the CPU as stored."""
        if self._tensors is not None:
            return {key: self._tensors[key] for key in keys}
        by_file: dict[Path, list[str]] = {}
        for key in keys:
            by_file.setdefault(self._where[key], []).append(key)
        state = {}
        for file, names in by_file.items():
            try:
                with safe_open(file, framework="pt") as handle:
                    state.update((key, handle.get_tensor(key)) for key in names)
            except (OSError, SafetensorError) as error:
                raise InputFileError(file, f"cannot load the transformer weights ({one_line(error)})",
                                     fix) from error
        return state


def _skipped_keys(folder: Path, stored: Iterable[str], needed: Mapping[str, tuple], listed: list[str]) -> set[str]:
    """The stored keys ``transformer.skip_stored_keys`` lists, each logged; a listed key the folder does not
    hold is harmless and logged too, one the model needs is refused (skipping it would leave it unloaded)."""
    stored = set(stored)
    for key in listed:
        if key in needed:
            raise CheckpointMismatchError(f"{folder}: {SKIP_FIELD} lists '{key}', a weight the model needs; "
                                          "remove it from the list")
        if key in stored:
            log.warning("%s: skipping stored tensor '%s', which the model has no place for (listed in %s)",
                        folder, key, SKIP_FIELD)
        else:
            log.warning("%s: %s lists '%s', which the folder does not hold (nothing to skip)",
                        folder, SKIP_FIELD, key)
    return stored & set(listed)


def _rebuild_non_persistent_buffers(model: nn.Module) -> None:
    """Re-create on the CPU the buffers a checkpoint does not hold, which stayed on the meta device.

    ReferenceGuidedTransformer has one: CogVideoXPatchEmbed's fixed sin-cos positional embedding
    (``pos_embedding``, non-persistent when the positional embeddings are not learned), rebuilt by the call its
    constructor makes. Any other would be a meta tensor at the first forward, so it is refused here.
    """
    for name, module in model.named_modules():
        for buffer in sorted(module._non_persistent_buffers_set):
            value = module._buffers.get(buffer)
            if value is None or not value.is_meta:
                continue
            if isinstance(module, CogVideoXPatchEmbed) and buffer == "pos_embedding":
                setattr(module, buffer, module._get_positional_embeddings(
                    module.sample_height, module.sample_width, module.sample_frames, device=torch.device("cpu")))
            else:
                raise NotImplementedError(f"load_transformer does not know how to re-create the non-persistent "
                                          f"buffer '{name}.{buffer}' of a model built on the meta device")


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
    apply_switches(transformer, cfg)
    return Backbone(
        transformer=transformer,
        codec=codec,
        reference_encoder=reference_encoder,
        text_encoder=build_text_encoder(cfg.text_encoder, device, offload) if encoders else None,
        schedule=build_schedule(cfg.schedule),
        cfg=cfg,
    )
