"""The paper's pretrained components, in their published folder layouts, through the production loaders."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import pytest
import torch
from omegaconf import OmegaConf
from support.rehearsal import rehearsal_config

from tracegs.restorer.build import build_backbone
from tracegs.restorer.codec import CogVideoXCodec
from tracegs.restorer.encoders import PretrainedReferenceEncoder, T5TextEncoder, reference_grid
from tracegs.restorer.loading import MissingPackageError


def backbone_config(root):
    return OmegaConf.to_object(rehearsal_config(root).backbone)


@pytest.mark.parametrize("explicit", [True, False])
def test_t5_tokenizer_is_read_from_the_cogvideox_tokenizer_folder(rehearsal_root, explicit):
    """CogVideoX keeps the tokenizer in ``tokenizer/`` beside ``text_encoder/`` (no tokenizer files there);
    without ``tokenizer_path`` that folder is where it is read from."""
    cfg = backbone_config(rehearsal_root).text_encoder
    if not explicit:
        cfg.tokenizer_path = None
    encoder = T5TextEncoder(cfg)
    tokens = encoder.encode(["a photo of a scene", "a garden"])
    assert tokens.shape == (2, cfg.max_length, cfg.dim)
    assert not torch.allclose(tokens[0], tokens[1])


def test_paper_backbone_loads_every_component(rehearsal_root, vggt_double):
    cfg = backbone_config(rehearsal_root)
    backbone = build_backbone(cfg)
    assert isinstance(backbone.codec, CogVideoXCodec) and backbone.codec.spatial_factor == 8
    assert isinstance(backbone.reference_encoder, PretrainedReferenceEncoder)
    assert next(backbone.transformer.parameters()).dtype == torch.bfloat16  # the paper's dtype policy
    frames = torch.rand(1, cfg.transformer.sample_frames, 3, 8 * cfg.transformer.sample_height,
                        8 * cfg.transformer.sample_width)
    latents = backbone.codec.encode(frames)
    assert latents.shape == (1, 3, cfg.transformer.latent_channels, cfg.transformer.sample_height,
                             cfg.transformer.sample_width)
    ref_2d, ref_3d = backbone.reference_encoder(frames[:, :2])
    rows, cols = reference_grid(cfg.reference_encoder, frames.shape[-2], frames.shape[-1])
    tokens = 2 * rows * cols
    assert ref_2d.shape == (1, tokens, cfg.transformer.ref_2d_dim)
    assert ref_3d.shape == (1, tokens, cfg.transformer.ref_3d_dim)


@pytest.mark.parametrize("field", ["ref_2d_dim", "ref_3d_dim"])
def test_reference_widths_are_checked_against_the_transformer(rehearsal_root, vggt_double, field):
    cfg = backbone_config(rehearsal_root)
    setattr(cfg.transformer, field, 2 * getattr(cfg.transformer, field))
    cfg.transformer.pretrained_path = None
    with pytest.raises(ValueError, match=f"transformer.{field}"):
        build_backbone(cfg)


def test_training_backbone_builds_no_encoder(rehearsal_root, tmp_path):
    """A training rank needs neither VGGT (not even installed here), DINOv2, T5 nor the VAE: the cache holds
    their outputs. Their folders do not even have to exist."""
    cfg = backbone_config(rehearsal_root)
    for section, field in (("codec", "pretrained_path"), ("text_encoder", "pretrained_path"),
                           ("reference_encoder", "dino_path"), ("reference_encoder", "vggt_path")):
        setattr(getattr(cfg, section), field, str(tmp_path / "absent"))
    backbone = build_backbone(cfg, encoders=False)
    assert backbone.codec is None and backbone.text_encoder is None and backbone.reference_encoder is None
    assert next(backbone.transformer.parameters()).dtype == torch.bfloat16


def test_missing_vggt_names_the_package(rehearsal_root):
    with pytest.raises(MissingPackageError, match="'vggt' package"):
        build_backbone(backbone_config(rehearsal_root))


@pytest.mark.slow  # a subprocess through the entry point; test_missing_vggt_names_the_package runs by default
def test_missing_vggt_is_one_line_and_exit_2(rehearsal_root, paper_data):
    """A user without VGGT gets one line naming the package, not a traceback (the data is in place: its scene
    lists are checked first)."""
    run = subprocess.run([sys.executable, "-m", "tracegs.cli.prepare", "experiment=rehearsal",
                          f"paths.root_dir={rehearsal_root}", "hydra.run.dir=" + str(rehearsal_root / "run")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 2, run.stderr[-2000:]
    assert run.stderr.strip().count("\n") == 0 and "'vggt' package" in run.stderr


@pytest.mark.skipif(torch.cuda.is_available(), reason="the CPU-only refusal")
@pytest.mark.parametrize("entry_point", [pytest.param("prepare", marks=pytest.mark.slow),
                                         pytest.param("deploy", marks=pytest.mark.slow), "evaluate"])
def test_gsplat_without_cuda_is_refused_before_any_work(tmp_path, entry_point):
    """``experiment=paper`` rasterizes with gsplat; on a machine without CUDA every 3DGS entry point refuses
    at once, naming the field, instead of failing inside the first fit (after loading every model)."""
    # No weights or data here: LPIPS (required by the rehearsal too) and prepare's training scene lists, both
    # checked first, are taken out of the way.
    no_lists = ["data.source.scenes=[scene_000]", "data.source.train_list=null", "data.source.test_list=null"]
    run = subprocess.run([sys.executable, "-m", f"tracegs.cli.{entry_point}", "experiment=rehearsal",
                          "data.prepare.fit.backend=gsplat", "evaluation.require_lpips=false",
                          *(no_lists if entry_point == "prepare" else []),
                          f"paths.root_dir={tmp_path}", f"hydra.run.dir={tmp_path / 'run'}"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 2, run.stderr[-2000:]
    assert "data.prepare.fit.backend='gsplat' needs CUDA" in run.stderr
    assert list(tmp_path.iterdir()) == []  # no weights read, nothing written (the run folder removed again)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_offloaded_encoders_stay_on_the_cpu_between_encodes(rehearsal_root, vggt_double):
    """``backbone.offload_encoders``: T5, DINOv2 and VGGT live on the CPU, encode on the GPU, and give the tokens
    the resident encoders give."""
    cfg = backbone_config(rehearsal_root)
    resident = build_backbone(replace(cfg, offload_encoders=False), device="cuda")
    offloaded = build_backbone(replace(cfg, offload_encoders=True), device="cuda")
    encoders = (offloaded.text_encoder.model, offloaded.reference_encoder.dino.model,
                offloaded.reference_encoder.vggt.model)
    refs = torch.rand(1, 2, 3, 64, 96, device="cuda")

    def tokens(backbone):
        return [*backbone.reference_encoder(refs), backbone.text_encoder.encode(["a garden"])]

    want, got = tokens(resident), tokens(offloaded)
    assert all(next(m.parameters()).device.type == "cpu" for m in encoders)  # released after encoding
    assert all(t.device.type == "cuda" for t in got)
    assert all(torch.equal(a, b) for a, b in zip(want, got))
