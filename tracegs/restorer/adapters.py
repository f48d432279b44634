"""Named LoRA adapters on one frozen restorer (supplement A.3, Eq. supp-lora, Eq. supp-adapter-clone).

peft does the LoRA work (injection through diffusers' ``PeftAdapterMixin``, state dicts). What we add is the
bookkeeping of which adapters are trainable: peft's ``set_adapter(name)`` turns ``requires_grad`` on for
``name`` and off for every other adapter, which would silently unfreeze a frozen
teacher or freeze the student. ``activate`` switches the active adapter and then restores the recorded flags.

LoRA factors are always float32, whatever the base dtype: diffusers' ``add_adapter`` gives new factors the
dtype of the layer they adapt, so on the paper's bf16 base they (and AdamW's state) would be bf16 and an lr
1e-5 step, far below bf16's ~4e-3 relative resolution, would mostly round away. Saved adapters therefore
hold float32 and say so in their metadata. An adapter this project wrote is refused in another dtype; a file
from elsewhere is copied into float32 factors (a bf16 file is upcast exactly, nothing is downcast).

Their products may still be computed in bfloat16 (``set_lora_compute``, ``backbone.lora.compute_bf16``): the float32
factors stay the master weights the optimiser updates, and each forward multiplies by a bf16 copy.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import re
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F
from peft import LoraConfig as PeftLoraConfig
from peft import get_peft_model_state_dict, set_peft_model_state_dict
from peft.tuners.lora import LoraLayer

from tracegs.errors import ConfigMismatchError, InputFileError
from tracegs.io import atomic_directory, bytes_digest, read_safetensors, save_safetensors_atomic
from tracegs.restorer.config import LoraConfig

# diffusers' key for the adapter config inside safetensors metadata (``save_lora_adapter`` format).
METADATA_KEY = "lora_adapter_metadata"
# What a saved adapter says it is (safetensors metadata), checked on loading: the training stage that wrote it,
# the base weights it was trained on, and its factors' dtype (rank and alpha are in METADATA_KEY's config).
STAGE_KEY, BASE_KEY, DTYPE_KEY = "tracegs_stage", "tracegs_base", "tracegs_dtype"
FACTOR_DTYPE = "float32"  # see the module docstring
# peft's own adapter folder (``PeftModel.from_pretrained`` reads it): a config and prefixed weights.
PEFT_CONFIG_FILE = "adapter_config.json"
PEFT_WEIGHTS_FILE = "adapter_model.safetensors"
PEFT_KEY_PREFIX = "base_model.model."


class AdapterFileError(ValueError):
    """An adapter file does not match the model (missing / unexpected LoRA tensors or bad metadata)."""


def target_pattern(cfg: LoraConfig) -> str:
    """Regex (peft full-match) for ``to_q/to_k/to_v/to_out.0`` of both attentions in every block."""
    modules = "|".join(re.escape(m) for m in cfg.attention_modules)
    targets = "|".join(re.escape(t) for t in cfg.target_modules)
    return rf".*\.({modules})\.({targets})"


def peft_config(cfg: LoraConfig) -> PeftLoraConfig:
    """rank r, alpha, dropout; peft's default init puts B = 0 so a new adapter leaves the model unchanged."""
    return PeftLoraConfig(
        r=cfg.rank,
        lora_alpha=cfg.alpha,
        lora_dropout=cfg.dropout,
        target_modules=target_pattern(cfg),
        init_lora_weights=True,
    )


def _inject(model: torch.nn.Module, config: PeftLoraConfig, name: str) -> None:
    # peft allocates and initialises the factors on the CPU before moving them next to the base weight;
    # for a model sized on the meta device, create them there directly (seconds -> milliseconds at 5B scale).
    on_meta = next(model.parameters()).is_meta
    with torch.device("meta") if on_meta else contextlib.nullcontext(), warnings.catch_warnings():
        # peft warns on every adapter after the first; several named adapters are the point here.
        warnings.filterwarnings("ignore", message="Already found a `peft_config`")
        model.add_adapter(config, adapter_name=name)
    for _, param in _lora_parameters(model, name):
        if param.dtype != torch.float32:
            # ``.data`` keeps the Parameter object (peft's layers and any optimiser hold references to it).
            param.data = param.data.float()
    set_lora_compute(model, getattr(model, "_lora_compute_bf16", False))


class Bf16Factor(torch.nn.Linear):
    """A LoRA factor (peft's ``lora_A`` / ``lora_B`` Linear) whose float32 weight is the master copy and whose
    product is computed in bfloat16: the gradient reaches the float32 weight through the cast."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        bias = None if self.bias is None else self.bias.to(torch.bfloat16)
        return F.linear(x.to(torch.bfloat16), self.weight.to(torch.bfloat16), bias)


def set_lora_compute(model: torch.nn.Module, bf16: bool) -> None:
    """Compute every adapter's products on ``model`` in bfloat16 (``bf16``) or in its factors' float32, the adapters
    added later included (``backbone.lora.compute_bf16``).

    peft's LoRA layer casts its input to the factors' dtype before multiplying (a float32 copy of every adapted
    activation on a bf16 base); with bf16 products that cast is turned off, and each factor's class is swapped
    for ``Bf16Factor``: the module, its Parameters (which peft's ModuleDicts and the optimiser hold) and its
    state-dict names stay the same, only its forward changes."""
    model._lora_compute_bf16 = bf16
    factor_class = Bf16Factor if bf16 else torch.nn.Linear
    for layer in model.modules():
        if isinstance(layer, LoraLayer):
            layer.cast_input_dtype_enabled = not bf16
            for factors in (layer.lora_A, layer.lora_B):
                for factor in factors.values():
                    if type(factor) in (torch.nn.Linear, Bf16Factor):
                        factor.__class__ = factor_class


def _trainable_flags(model: torch.nn.Module) -> dict[str, bool]:
    if not hasattr(model, "_adapter_trainable"):
        model._adapter_trainable = {}
    return model._adapter_trainable


def _lora_parameters(model: torch.nn.Module, name: str) -> list[tuple[str, torch.nn.Parameter]]:
    marker = re.compile(rf"\.lora_(A|B)\.{re.escape(name)}\.")
    return [(n, p) for n, p in model.named_parameters() if marker.search(n)]


def adapter_names(model: torch.nn.Module) -> list[str]:
    return list(getattr(model, "peft_config", {}) or {})


def _require(model: torch.nn.Module, name: str) -> None:
    if name not in adapter_names(model):
        raise KeyError(f"adapter {name!r} not on the model (have {adapter_names(model)})")


def activate(model: torch.nn.Module, name: str) -> None:
    """Make ``name`` the adapter used by the next forward, keeping every adapter's trainability as recorded."""
    _require(model, name)
    model.set_adapter(name)
    for adapter, trainable in _trainable_flags(model).items():
        for _, param in _lora_parameters(model, adapter):
            param.requires_grad_(trainable)


def active_adapter(model: torch.nn.Module) -> str | None:
    names = getattr(model, "active_adapters", None)
    active = names() if callable(names) else names
    return active[0] if active else None


def add_adapter(model: torch.nn.Module, name: str, cfg: LoraConfig, trainable: bool = True) -> None:
    """Attach a fresh adapter (B = 0) and freeze every non-LoRA weight (the base theta is always frozen).

    The previously active adapter stays active; the model's first adapter becomes active.
    """
    previous = active_adapter(model) if adapter_names(model) else None
    _inject(model, peft_config(cfg), name)
    for param_name, param in model.named_parameters():
        if ".lora_" not in param_name:
            param.requires_grad_(False)
    _trainable_flags(model)[name] = trainable
    activate(model, previous or name)


def adapter_parameters(model: torch.nn.Module, name: str) -> list[torch.nn.Parameter]:
    """The LoRA factors of one adapter (what the optimiser of that role should own)."""
    _require(model, name)
    return [p for _, p in _lora_parameters(model, name)]


def clone_adapter(model: torch.nn.Module, src: str, dst: str, trainable: bool) -> None:
    """phi_dst <- Clone(phi_src) (Eq. supp-adapter-clone): same config, deep-copied tensors, no shared storage."""
    _require(model, src)
    _inject(model, copy.deepcopy(model.peft_config[src]), dst)
    source = dict(_lora_parameters(model, src))
    with torch.no_grad():
        for param_name, param in _lora_parameters(model, dst):
            if not param.is_meta:  # a model sized on the meta device has no values to copy
                param.copy_(source[param_name.replace(f".{dst}.", f".{src}.")])
    _trainable_flags(model)[dst] = trainable
    activate(model, src)


def base_identity(model: torch.nn.Module) -> str:
    """What an adapter on ``model`` was trained on: the content digest of the weights folder the base was loaded
    from (diffusers records it as ``_name_or_path``), or, for a base made in memory (a tiny or randomly
    initialised one), a digest of its weights' values at bf16 precision: the weight files' digest does not
    depend on the dtype they are loaded in either, so one base at two precisions is one base."""
    source = dict(getattr(model, "config", {}) or {}).get("_name_or_path")
    if source and Path(source).is_dir():
        return f"weights {bytes_digest(source)}"
    sha = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        if ".lora_" not in name:
            sha.update(name.replace(".base_layer.", ".").encode())  # as named before peft wrapped the layer
            values = tensor.detach().cpu().reshape(-1)
            values = values.to(torch.bfloat16) if values.is_floating_point() else values
            sha.update(values.view(torch.uint8).numpy().tobytes())
    return f"in-memory {sha.hexdigest()[:16]}"


def save_adapter(model: torch.nn.Module, name: str, path: str | Path, state_dict: dict | None = None,
                 stage: str | None = None) -> None:
    """Save adapter ``name``: a ``*.safetensors`` path gets diffusers' ``save_lora_adapter`` layout (peft keys,
    adapter config in the metadata); any other path becomes peft's adapter folder, which
    ``PeftModel.from_pretrained(transformer, path)`` loads as it is. ``state_dict``: the model's weights when
    ``model.state_dict()`` does not hold them whole (a sharded model; tracegs.training.strategy.full_lora_state).
    The metadata also records ``stage`` (the training stage writing it), the base (:func:`base_identity`) and
    the factors' dtype, which :func:`load_adapter` checks."""
    _require(model, name)
    config = model.peft_config[name].to_dict()
    config = {k: (sorted(v) if isinstance(v, set) else v) for k, v in config.items()}
    tensors = get_peft_model_state_dict(model, state_dict=state_dict, adapter_name=name)
    metadata = {"format": "pt", METADATA_KEY: json.dumps(config, sort_keys=True), BASE_KEY: base_identity(model),
                DTYPE_KEY: FACTOR_DTYPE, **({STAGE_KEY: stage} if stage else {})}
    path = Path(path)
    if path.suffix == ".safetensors":
        save_safetensors_atomic(tensors, path, metadata=metadata)
        return
    with atomic_directory(path) as staging:
        prefixed = {PEFT_KEY_PREFIX + key: value for key, value in tensors.items()}
        save_safetensors_atomic(prefixed, staging / PEFT_WEIGHTS_FILE, metadata=metadata)
        (staging / PEFT_CONFIG_FILE).write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")


def read_adapter(path: str | Path, fix: str = "re-create it with the stage that writes it"
                 ) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """(peft-keyed tensors, safetensors metadata) of an adapter file or peft adapter folder."""
    path = Path(path)
    tensors, metadata = read_safetensors(path / PEFT_WEIGHTS_FILE if path.is_dir() else path, fix)
    if METADATA_KEY not in metadata and (path / PEFT_CONFIG_FILE).is_file():
        metadata[METADATA_KEY] = (path / PEFT_CONFIG_FILE).read_text()
    return {key.removeprefix(PEFT_KEY_PREFIX): value for key, value in tensors.items()}, metadata


def check_adapter_config(path: Path, stored: dict, expected: LoraConfig, field: str) -> None:
    """The file's rank, alpha and target modules must be the config's: peft would otherwise build the adapter
    from the file and train at the file's rank, or fail later on a size mismatch."""
    wanted = peft_config(expected)
    fields = {"r": ("rank", wanted.r), "lora_alpha": ("alpha", wanted.lora_alpha),
              "target_modules": ("target_modules / attention_modules", wanted.target_modules)}
    differing = [f"{name} {stored.get(key)!r} in the file, {value!r} in backbone.lora"
                 for key, (name, value) in fields.items() if stored.get(key) != value]
    if differing:
        raise ConfigMismatchError(
            path, "adapter saved with other LoRA settings: " + "; ".join(differing),
            f"set backbone.lora to the file's values or point {field} at an adapter trained with these settings",
        )


def check_adapter_records(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str],
                          model: torch.nn.Module, stage: str, field: str) -> None:
    """The file must say it was written by ``stage`` on ``model``'s base, with float32 factors (and hold
    them): an adapter of another stage, base or precision restores differently while looking alike."""
    wanted = {STAGE_KEY: ("stage", stage), BASE_KEY: ("base", base_identity(model)),
              DTYPE_KEY: ("dtype", FACTOR_DTYPE)}
    # The dtype the factors have, whatever the metadata claims (a converted file may keep the old record).
    have = {STAGE_KEY: metadata.get(STAGE_KEY), BASE_KEY: metadata.get(BASE_KEY),
            DTYPE_KEY: "/".join(sorted({str(t.dtype).removeprefix("torch.") for t in tensors.values()}))}
    differing = [f"{label} {have[key]!r} in the file, {value!r} here" for key, (label, value) in wanted.items()
                 if have[key] != value]
    if differing:
        raise ConfigMismatchError(path, "adapter of another kind: " + "; ".join(differing),
                                  f"point {field} at the {stage} adapter trained on this base, or re-run {stage}")


def load_adapter(model: torch.nn.Module, name: str, path: str | Path, trainable: bool,
                 expected: LoraConfig | None = None, field: str = "the adapter path", stage: str | None = None
                 ) -> None:
    """Load an adapter file or peft adapter folder as ``name`` (created from its config if absent); exact key
    match required.

    ``expected`` (the run's LoRA config) is compared with the file's before the model is touched, and so, when
    ``stage`` is given, are the stage, base and dtype the file records (:func:`check_adapter_records`);
    ``field`` is the config field that named the file (quoted in errors).
    """
    path = Path(path)
    fix = f"re-create it with the stage that writes it, or point {field} at another file"
    tensors, metadata = read_adapter(path, fix)
    stored = None
    if METADATA_KEY in metadata:
        try:
            stored = json.loads(metadata[METADATA_KEY])
        except ValueError as error:
            raise InputFileError(path, f"'{METADATA_KEY}' metadata is not JSON ({error})", fix) from error
    if expected is not None:
        if stored is None:
            raise InputFileError(path, f"no '{METADATA_KEY}' metadata to check against backbone.lora", fix)
        check_adapter_config(path, stored, expected, field)
    if stage is not None:
        check_adapter_records(path, tensors, metadata, model, stage, field)
    if name not in adapter_names(model):
        if stored is None:
            raise AdapterFileError(f"{path}: no '{METADATA_KEY}' metadata to rebuild adapter {name!r}")
        fields = PeftLoraConfig.__dataclass_fields__
        config = PeftLoraConfig(**{k: v for k, v in stored.items() if k in fields and fields[k].init})
        previous = active_adapter(model) if adapter_names(model) else None
        _inject(model, config, name)
        if previous is not None:
            model.set_adapter(previous)
    expected_keys = set(get_peft_model_state_dict(model, adapter_name=name))
    missing, unexpected = sorted(expected_keys - set(tensors)), sorted(set(tensors) - expected_keys)
    if missing or unexpected:
        raise AdapterFileError(f"{path}: missing LoRA tensors {missing[:8]}, unexpected {unexpected[:8]}")
    set_peft_model_state_dict(model, tensors, adapter_name=name)
    _trainable_flags(model)[name] = trainable
    activate(model, active_adapter(model) or name)
