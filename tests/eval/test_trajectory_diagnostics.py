"""The two trajectory diagnostics (exposure gap, teacher advantage) on the tiny restorer."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tracegs.eval.trajectory import ClipEncodings, Role, trajectory_diagnostics
from tracegs.restorer.build import build_backbone
from tracegs.restorer.config import BackboneConfig, Prediction
from tracegs.restorer.sampler import RestorationPipeline

STEPS = 4


def _clip(backbone, seed: int = 0, batch: int = 2):
    """A clip of ``batch`` noisy renderings R_s of one ground truth: (truth frames, R_s frames, encodings)."""
    g = torch.Generator().manual_seed(seed)
    truth = torch.rand(1, 5, 3, 24, 32, generator=g).expand(batch, -1, -1, -1, -1)
    rendered = (truth + 0.15 * torch.randn(truth.shape, generator=g)).clamp(0, 1)
    ref_2d, ref_3d = backbone.reference_encoder(truth[:, [0, -1]])
    shared = ClipEncodings(ref_2d, ref_3d, backbone.text_encoder.encode(["a scene"] * batch), truth[:, 1:-1])
    return truth, rendered, shared


@pytest.fixture(scope="module")
def backbone():
    torch.manual_seed(0)
    return build_backbone(BackboneConfig())


def test_exposure_gap_is_zero_where_the_visited_state_is_the_forward_noised_one(backbone):
    truth, rendered, shared = _clip(backbone)
    student = Role(None, backbone.codec.encode(rendered))
    result = trajectory_diagnostics(backbone, student, shared, seed=3, steps=STEPS,
                                    clean=backbone.codec.encode(truth[:1]))
    gap = result.exposure_gap
    assert len(gap) == len(result.visited) == len(result.noised) == STEPS
    # The first state is the pure noise both trajectories start from: the same state, the same prediction.
    assert gap[0] == 0.0
    # Later the student's own states differ from the forward-noised ones (a random restorer drifts).
    assert any(abs(g) > 1e-3 for g in gap[1:])
    # The visited-state curve ends at the deployed restorer's output for the same noise (rectified flow).
    restored = RestorationPipeline(backbone).restore(rendered, truth[:, [0, -1]], ["a scene"] * 2, seed=3,
                                                     steps=STEPS).clamp(0, 1)
    mse = ((restored[:, 1:-1] - truth[:, 1:-1]) ** 2).mean(dim=(2, 3, 4))
    assert result.final == pytest.approx(float((-10 * torch.log10(mse)).mean()), abs=1e-3)
    assert result.visited[-1] == pytest.approx(result.final, abs=1e-3)


def test_teacher_advantage_is_zero_for_the_student_itself_and_positive_for_a_better_condition():
    # A fresh residual restorer predicts its condition whatever the state: the cleanest case to reason about.
    torch.manual_seed(0)
    cfg = BackboneConfig()
    backbone = build_backbone(dataclasses.replace(
        cfg, transformer=dataclasses.replace(cfg.transformer, prediction=Prediction.residual)))
    truth, rendered, shared = _clip(backbone, seed=1)
    student = Role(None, backbone.codec.encode(rendered))
    same = trajectory_diagnostics(backbone, student, shared, seed=0, steps=STEPS, teacher=student)
    assert same.teacher_advantage == [0.0] * STEPS
    # The teacher conditioned on the clean clip (the most privileged R_d) predicts it at every student state.
    privileged = Role(None, backbone.codec.encode(truth))
    better = trajectory_diagnostics(backbone, student, shared, seed=0, steps=STEPS, teacher=privileged,
                                    clean=backbone.codec.encode(truth[:1]))
    assert all(a > 0.5 for a in better.teacher_advantage)
    # Its prediction ignores the state, so the visited and forward-noised states predict the same clean clip.
    assert better.exposure_gap == pytest.approx([0.0] * STEPS, abs=1e-4)
    assert better.noised is not None and same.noised is None and same.exposure_gap is None
