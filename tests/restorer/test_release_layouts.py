"""``load_transformer`` reads every folder layout GSFixer's own loader reads, and stays strict.

GSFixer's ``from_pretrained_2d`` (``Reconstruction/gsfixer/cogvideo/crosstransformer3d.py`` l. 862-951) reads
``config.json`` in the folder it is given (its scripts pass the downloaded ``checkpoints/GSFixer``), then
``diffusion_pytorch_model.bin``, else ``diffusion_pytorch_model.safetensors``, else every ``*.safetensors``
merged, and drops the keys it cannot use. Ours reads the same layouts (plus diffusers' ``transformer/``
subfolder), safetensors first and a ``.bin`` only with ``weights_only``, and refuses unused stored tensors
unless ``skip_stored_keys`` lists them.
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from safetensors.torch import load_file, save_file
from support.gsfixer_layout import write_gsfixer_folder

from tracegs.cli.app import CONF_DIR
from tracegs.config.schema import register_configs
from tracegs.errors import InputFileError
from tracegs.restorer.build import (
    CheckpointMismatchError,
    build_backbone,
    create_transformer,
    load_transformer,
)
from tracegs.restorer.config import TransformerConfig
from tracegs.restorer.transformer import ReferenceGuidedTransformer

# Sin-cos positional embedding: a non-persistent buffer the folder does not hold (re-created after the meta build).
PLAIN = TransformerConfig(
    num_layers=2, num_attention_heads=2, attention_head_dim=8, latent_channels=4, text_embed_dim=8,
    max_text_seq_length=4, time_embed_dim=16, sample_frames=3, sample_height=4, sample_width=6,
    ref_2d_dim=6, ref_3d_dim=5,
)
# GSFixer's options (CogVideoX-5b-I2V): RoPE, a learned (persistent) positional embedding, the reference norms.
GSFIXER = replace(PLAIN, attention_head_dim=16, sample_frames=9, temporal_compression_ratio=4,
                  use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True,
                  reference_norms=True, timestep_scale=1.0)
LAYOUTS = ("folder", "parent", "shards", "shards_without_index", "bin")


def _saved(cfg: TransformerConfig, seed: int = 0) -> ReferenceGuidedTransformer:
    """A random tiny transformer in float32 (its sin-cos positional embeddings are built in float64)."""
    torch.manual_seed(seed)
    return create_transformer(cfg).float().eval()


def _write(model: ReferenceGuidedTransformer, root: Path, layout: str) -> Path:
    """``model`` saved in ``layout`` under ``root``; returns what ``pretrained_path`` names."""
    folder = root / "gsfixer" / "transformer" if layout == "parent" else root / "gsfixer"
    if layout.startswith("shards"):
        total = sum(t.numel() * t.element_size() for t in model.state_dict().values())
        model.save_pretrained(folder, max_shard_size=total // 3)
        assert len(list(folder.glob("diffusion_pytorch_model-*.safetensors"))) >= 2
        if layout == "shards_without_index":
            (folder / "diffusion_pytorch_model.safetensors.index.json").unlink()
    elif layout == "bin":
        model.save_config(folder)
        torch.save(model.state_dict(), folder / "diffusion_pytorch_model.bin")
    else:
        model.save_pretrained(folder)
    assert not list(folder.glob("*.safetensors")) if layout == "bin" else not list(folder.glob("*.bin"))
    return root / "gsfixer"


def _inputs(cfg: TransformerConfig, seed: int = 1) -> dict[str, torch.Tensor]:
    """Inputs on the sample grid, so the stored (or re-created) positional embedding is the one added."""
    g = torch.Generator().manual_seed(seed)
    frames = (cfg.sample_frames - 1) // cfg.temporal_compression_ratio + 1
    latent = (2, frames, cfg.latent_channels, cfg.sample_height, cfg.sample_width)
    return dict(noisy=torch.randn(latent, generator=g), cond=torch.randn(latent, generator=g),
                timestep=torch.rand(2, generator=g),
                text=torch.randn(2, cfg.max_text_seq_length, cfg.text_embed_dim, generator=g),
                ref_2d=torch.randn(2, 5, cfg.ref_2d_dim, generator=g),
                ref_3d=torch.randn(2, 5, cfg.ref_3d_dim, generator=g))


def _meta_tensors(model: torch.nn.Module) -> list[str]:
    """Every parameter, buffer (persistent or not) or tensor attribute of a module that is on the meta device."""
    found = [n for n, t in (*model.named_parameters(), *model.named_buffers()) if t.is_meta]
    for name, module in model.named_modules():
        found += [f"{name}.{k}" for k, v in vars(module).items() if isinstance(v, torch.Tensor) and v.is_meta]
    return found


def _assert_same_model(loaded: ReferenceGuidedTransformer, saved: ReferenceGuidedTransformer, cfg,
                       forward: bool = True) -> None:
    state, expected = loaded.state_dict(), saved.state_dict()
    assert list(state) == list(expected)
    for key, value in expected.items():
        assert state[key].dtype == value.dtype and torch.equal(state[key], value), key
    buffers = dict(loaded.named_buffers())  # the non-persistent ones too (kept as built: float64, see below)
    for key, value in saved.named_buffers():
        assert torch.equal(buffers[key].to(value.dtype), value), key
    if forward:
        with torch.no_grad():
            assert torch.equal(loaded(**_inputs(cfg)).velocity, saved(**_inputs(cfg)).velocity)


@pytest.mark.parametrize("cfg", [PLAIN, GSFIXER], ids=["sincos", "gsfixer"])
@pytest.mark.parametrize("layout", LAYOUTS)
def test_every_release_layout_loads_bit_for_bit(tmp_path, layout, cfg):
    saved = _saved(cfg)
    path = _write(saved, tmp_path, layout)
    loaded = load_transformer(replace(cfg, pretrained_path=str(path)))
    assert _meta_tensors(loaded) == []
    _assert_same_model(loaded, saved, cfg)
    # as diffusers' from_pretrained leaves it: eval mode, config registered with where it came from
    holder = path / "transformer" if layout == "parent" else path
    assert not loaded.training and loaded.config["_name_or_path"] == str(holder)
    assert loaded.config["num_layers"] == cfg.num_layers and loaded.config["prediction"] == "velocity"


@pytest.mark.parametrize("keep_in_fp32", [None, ["proj_out"]])
def test_what_from_pretrained_gives_bf16_and_fp32_modules_included(tmp_path, monkeypatch, keep_in_fp32):
    """The same tensors, dtypes, buffers and config as diffusers' ``from_pretrained(torch_dtype=...)``, which
    keeps a class's ``_keep_in_fp32_modules`` in float32 (ReferenceGuidedTransformer sets none today)."""
    monkeypatch.setattr(ReferenceGuidedTransformer, "_keep_in_fp32_modules", keep_in_fp32)
    path = _write(_saved(PLAIN), tmp_path, "folder")
    ours = load_transformer(replace(PLAIN, pretrained_path=str(path)), dtype=torch.bfloat16)
    theirs = ReferenceGuidedTransformer.from_pretrained(str(path), torch_dtype=torch.bfloat16)
    assert (ours.proj_out.weight.dtype == torch.float32) == bool(keep_in_fp32)
    assert ours.patch_embed.proj.weight.dtype == torch.bfloat16
    # (a float32 proj_out behind bf16 blocks is the class's business: diffusers' forward does not cast for it)
    _assert_same_model(ours, theirs, PLAIN, forward=not keep_in_fp32)
    assert {k: b.dtype for k, b in ours.named_buffers()} == {k: b.dtype for k, b in theirs.named_buffers()}
    assert dict(ours.config) == dict(theirs.config)


def test_a_loaded_model_saves_and_loads_again(tmp_path):
    saved = _saved(GSFIXER)
    loaded = load_transformer(replace(GSFIXER, pretrained_path=str(_write(saved, tmp_path / "a", "bin"))))
    loaded.save_pretrained(tmp_path / "b")
    assert json.loads((tmp_path / "b" / "config.json").read_text())["_class_name"] == "ReferenceGuidedTransformer"
    _assert_same_model(load_transformer(replace(GSFIXER, pretrained_path=str(tmp_path / "b"))), saved, GSFIXER)


def test_an_unused_stored_tensor_is_refused_unless_listed(tmp_path, caplog):
    saved = _saved(PLAIN)
    path = _write(saved, tmp_path, "folder")
    weights = path / "diffusion_pytorch_model.safetensors"
    save_file({**load_file(weights), "extra.weight": torch.ones(3)}, weights)
    with pytest.raises(CheckpointMismatchError) as error:
        load_transformer(replace(PLAIN, pretrained_path=str(path)))
    message = str(error.value)
    assert "\n" not in message and "'extra.weight' has no place in the model (1 unused, 0 missing" in message
    assert "backbone.transformer.skip_stored_keys" in message

    listed = replace(PLAIN, pretrained_path=str(path), skip_stored_keys=["extra.weight", "not.stored"])
    with caplog.at_level(logging.WARNING, logger="tracegs.restorer.build"):
        loaded = load_transformer(listed)
    _assert_same_model(loaded, saved, PLAIN)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("skipping stored tensor 'extra.weight'" in m for m in warned)
    assert any("'not.stored', which the folder does not hold" in m for m in warned)

    # a weight the model needs cannot be skipped
    with pytest.raises(CheckpointMismatchError, match="lists 'proj_out.bias', a weight the model needs"):
        load_transformer(replace(listed, skip_stored_keys=["proj_out.bias"]))


def test_a_tensor_stored_in_two_shards_is_refused_naming_both(tmp_path):
    path = _write(_saved(PLAIN), tmp_path, "shards_without_index")
    first, second = sorted(path.glob("*.safetensors"))[:2]
    key = sorted(load_file(second))[0]
    save_file({**load_file(first), key: load_file(second)[key]}, first)
    with pytest.raises(InputFileError) as error:
        load_transformer(replace(PLAIN, pretrained_path=str(path)))
    message = str(error.value)
    assert "\n" not in message and f"weight '{key}' is stored twice, in {first.name} and {second.name}" in message


class _Payload:
    """A pickled object that would leave a file behind if unpickled."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return _leave_marker, (self.marker,)


def _leave_marker(marker: str) -> int:
    Path(marker).touch()
    return 0


@pytest.mark.parametrize("extra", ["object", "int"])
def test_a_bin_is_read_with_weights_only(tmp_path, extra):
    saved = _saved(PLAIN)
    path = _write(saved, tmp_path, "bin")
    marker = tmp_path / "executed"
    state = {**saved.state_dict(), "extra": _Payload(marker) if extra == "object" else 3}
    torch.save(state, path / "diffusion_pytorch_model.bin")
    with pytest.raises(InputFileError) as error:
        load_transformer(replace(PLAIN, pretrained_path=str(path)))
    message = str(error.value)
    assert "\n" not in message and "diffusion_pytorch_model.bin" in message
    assert ("cannot load the transformer weights" if extra == "object" else "holds int under 'extra'") in message
    assert not marker.exists()


def test_missing_damaged_or_incomplete_weights_are_one_line_errors(tmp_path):
    path = _write(_saved(PLAIN), tmp_path, "shards")
    cfg = replace(PLAIN, pretrained_path=str(path))
    index = path / "diffusion_pytorch_model.safetensors.index.json"
    last = sorted(path.glob("*.safetensors"))[-1]
    data = last.read_bytes()
    last.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputFileError, match=f"{last.name}: cannot load the transformer weights"):
        load_transformer(cfg)
    last.unlink()
    with pytest.raises(InputFileError, match=f"{index.name}: names shard '{last.name}'"):
        load_transformer(cfg)
    for shard in path.glob("*.safetensors"):
        shard.unlink()
    with pytest.raises(InputFileError) as error:
        load_transformer(cfg)
    assert "\n" not in str(error.value) and "holds no diffusion_pytorch_model.safetensors" in str(error.value)
    assert "backbone.transformer.pretrained_path" in str(error.value)  # the fix
    (path / "config.json").unlink()
    with pytest.raises(InputFileError, match="no diffusers config here nor in"):
        load_transformer(cfg)


@pytest.mark.parametrize("where", ["gsfixer", "gsfixer/transformer"])
def test_the_paper_config_reads_gsfixers_download_and_the_rehearsal_tree(tmp_path, where):
    """``conf/backbone/cogvideox5b.yaml`` names ``weights/gsfixer`` (GSFixer's download); the rehearsal's tree
    (tests/rehearsal/paper_weights.py) keeps the folder one level down, in ``transformer/``: both load."""
    register_configs()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=["experiment=rehearsal", f"paths.root_dir={tmp_path}"])
    backbone = OmegaConf.to_object(cfg.backbone)
    weights = Path(cfg.paths.weights_dir)
    assert backbone.transformer.pretrained_path == str(weights / "gsfixer")
    stored = write_gsfixer_folder(weights / where, backbone.transformer)
    transformer = build_backbone(backbone, encoders=False).transformer  # bf16, as the paper scale loads it
    assert _meta_tensors(transformer) == []
    state = transformer.state_dict()
    assert set(state) == set(stored)
    for key, value in stored.items():
        assert state[key].dtype == torch.bfloat16 and torch.equal(state[key], value.to(torch.bfloat16)), key
