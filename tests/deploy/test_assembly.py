"""Restorer assembly: variant A and TRACE-GS share one backbone and restore exactly what a backbone built for
each alone restores (the evaluation-memory rule of deploy/assembly.py)."""

from dataclasses import replace

import pytest
import torch

from tracegs.deploy.assembly import RestorerArtifacts, build_restorers
from tracegs.restorer import adapters
from tracegs.restorer.build import build_backbone, create_transformer, load_transformer
from tracegs.restorer.config import BackboneConfig
from tracegs.restorer.sampler import RestorationPipeline


@pytest.fixture(scope="module")
def artifacts(tmp_path_factory) -> RestorerArtifacts:
    """A random tiny base in diffusers layout and a random (non-zero) student adapter for it."""
    folder = tmp_path_factory.mktemp("restorers")
    cfg = BackboneConfig()
    torch.manual_seed(3)
    model = create_transformer(cfg.transformer)
    with torch.no_grad():
        for p in model.parameters():  # the residual head starts at zero: give every weight a value
            p.normal_(std=0.05)
    model.save_pretrained(folder / "baseline")
    # Trained, as Stage 2 trains it, on the base loaded from the baseline folder (the adapter records that base).
    model = load_transformer(replace(cfg.transformer, pretrained_path=str(folder / "baseline")))
    adapters.add_adapter(model, "student", cfg.lora)
    with torch.no_grad():
        for p in adapters.adapter_parameters(model, "student"):
            p.normal_(std=0.05)
    adapters.save_adapter(model, "student", folder / "student.safetensors", stage="stage2")
    return RestorerArtifacts(baseline_weights=str(folder / "baseline"),
                             student_adapter=str(folder / "student.safetensors"))


def _separate(cfg: BackboneConfig, artifacts: RestorerArtifacts, student: bool) -> RestorationPipeline:
    """What evaluation used to build per method: a backbone of its own, with only its own adapter."""
    cfg = replace(cfg, transformer=replace(cfg.transformer, pretrained_path=artifacts.baseline_weights))
    backbone = build_backbone(cfg)
    if student:
        adapters.load_adapter(backbone.transformer, "student", artifacts.student_adapter, trainable=False)
    return RestorationPipeline(backbone, adapter="student" if student else None)


def test_shared_backbone_restores_bitwise_like_separate_backbones(artifacts):
    cfg = BackboneConfig()
    shared = build_restorers(cfg, artifacts, ["3dgs", "baseline", "tracegs"], batch=2, steps=3)
    assert shared["3dgs"] is None
    a, student = shared["baseline"].pipeline, shared["tracegs"].pipeline
    assert a.backbone is student.backbone  # one transformer, codec and encoder set in memory
    frames, refs = torch.rand(2, 5, 3, 48, 72, generator=torch.Generator().manual_seed(0)), torch.rand(
        2, 2, 3, 48, 72, generator=torch.Generator().manual_seed(1))
    bb = a.backbone
    inputs = (bb.codec.encode(frames), *bb.reference_encoder(refs), bb.text_encoder.encode(["a room", "a desk"]))
    # Interleave the two methods on the shared backbone: switching must leave no trace.
    got_a, got_student, got_a_again = (p.restore_latents(*inputs, seed=4, steps=3) for p in (a, student, a))
    want_a = _separate(cfg, artifacts, student=False).restore_latents(*inputs, seed=4, steps=3)
    want_student = _separate(cfg, artifacts, student=True).restore_latents(*inputs, seed=4, steps=3)
    assert not torch.equal(want_a, want_student)  # the adapter matters, so the comparison can fail
    assert torch.equal(got_a, want_a) and torch.equal(got_a_again, want_a)
    assert torch.equal(got_student, want_student)
    # The deployed restorers' identities still name the base and the student file.
    assert shared["baseline"].identity.startswith("base=") and " student=" in shared["tracegs"].identity


def test_only_the_methods_asked_for_are_built(artifacts):
    only_a = build_restorers(BackboneConfig(), replace(artifacts, student_adapter=None), ["baseline"], batch=1)
    assert list(only_a) == ["baseline"]
    assert adapters.adapter_names(only_a["baseline"].pipeline.backbone.transformer) == []
    assert build_restorers(BackboneConfig(), artifacts, ["3dgs"], batch=1) == {"3dgs": None}


def test_missing_student_adapter_names_the_field(artifacts, tmp_path):
    missing = replace(artifacts, student_adapter=str(tmp_path / "none.safetensors"))
    with pytest.raises(FileNotFoundError, match="artifacts.student_adapter"):
        build_restorers(BackboneConfig(), missing, ["baseline", "tracegs"], batch=1)
