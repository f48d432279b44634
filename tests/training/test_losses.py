"""Each loss term against a hand computation on small explicit tensors."""

import pytest
import torch

from tracegs.training.losses import (
    alignment_loss,
    distillation_state_loss,
    flow_matching_loss,
    normalize_tokens,
    retrieval_state_loss,
    trajectory_state_loss,
    warm_loss,
)


def test_flow_matching_is_mean_squared_error():
    pred = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    target = torch.tensor([[0.0, 2.0], [1.0, 8.0]])
    # squared errors 1, 0, 4, 16 -> mean 21 / 4
    assert flow_matching_loss(pred, target).item() == pytest.approx(21 / 4)


def test_weighted_flow_matching_weights_each_samples_mean_squared_error():
    pred = torch.tensor([[1.0, 3.0], [0.0, 2.0]])
    target = torch.zeros(2, 2)
    assert flow_matching_loss(pred, target, torch.tensor([1.0, 0.5])).item() == pytest.approx((5 + 0.5 * 2) / 2)
    assert flow_matching_loss(pred, target, torch.ones(2)).item() == pytest.approx(flow_matching_loss(pred, target).item())


def test_alignment_stops_gradient_into_teacher():
    student = torch.tensor([1.0, -1.0, 0.5], requires_grad=True)
    teacher = torch.tensor([0.0, 1.0, 0.5], requires_grad=True)
    loss = alignment_loss(student, teacher)
    assert loss.item() == pytest.approx((1 + 4 + 0) / 3)
    loss.backward()
    assert teacher.grad is None
    # d/ds mean((s - t)^2) = 2 (s - t) / n
    torch.testing.assert_close(student.grad, torch.tensor([2.0, -4.0, 0.0]) / 3)


def test_warm_loss_combines_terms_with_lambda_align():
    v_s = torch.tensor([1.0, 0.0], requires_grad=True)
    v_t = torch.tensor([0.0, 2.0], requires_grad=True)
    target = torch.tensor([1.0, 1.0])
    terms = warm_loss(v_s, v_t, target, lambda_align=0.5)
    assert terms["fm_student"].item() == pytest.approx((0 + 1) / 2)
    assert terms["fm_teacher"].item() == pytest.approx((1 + 1) / 2)
    assert terms["align"].item() == pytest.approx((1 + 4) / 2)
    assert terms["loss"].item() == pytest.approx(0.5 + 1.0 + 0.5 * 2.5)
    terms["loss"].backward()
    # teacher gets gradient only from its own flow-matching term: 2 (v_t - target) / 2
    torch.testing.assert_close(v_t.grad, torch.tensor([-1.0, 1.0]))
    # student: fm 2(v_s - target)/2 + 0.5 * 2 (v_s - v_t)/2
    torch.testing.assert_close(v_s.grad, torch.tensor([0.0, -1.0]) + 0.5 * torch.tensor([1.0, -2.0]))


def test_warm_loss_weights_its_flow_matching_terms_and_leaves_alignment_as_written():
    v_s = torch.tensor([[1.0, 0.0], [2.0, 2.0]])
    v_t = torch.tensor([[0.0, 2.0], [1.0, 1.0]])
    target = torch.ones(2, 2)
    weight = torch.tensor([2.0, 0.5])
    plain, weighted = warm_loss(v_s, v_t, target, 0.5), warm_loss(v_s, v_t, target, 0.5, weight)
    assert weighted["fm_student"].item() == pytest.approx((2 * 0.5 + 0.5 * 1.0) / 2)
    assert weighted["fm_teacher"].item() == pytest.approx((2 * 1.0 + 0.5 * 0.0) / 2)
    assert weighted["align"].item() == plain["align"].item()


def test_trajectory_term_is_per_state_mse_with_stop_gradient():
    u_s = torch.tensor([[3.0, 0.0]], requires_grad=True)
    u_t = torch.tensor([[0.0, 4.0]], requires_grad=True)
    loss = trajectory_state_loss(u_s, u_t)
    assert loss.item() == pytest.approx((9 + 16) / 2)
    loss.backward()
    assert u_t.grad is None


def test_token_normalisation_is_per_token_along_channels():
    responses = torch.tensor([[[3.0, 4.0], [0.0, 2.0]]])  # (B=1, tokens=2, d=2)
    eps = 1e-3
    expected = torch.tensor([[[3 / (5 + eps), 4 / (5 + eps)], [0.0, 2 / (2 + eps)]]])
    torch.testing.assert_close(normalize_tokens(responses, eps), expected)


def test_retrieval_loss_matches_hand_computation_and_ignores_scale():
    f_s = torch.tensor([[[1.0, 0.0], [0.0, 3.0]]], requires_grad=True)
    f_t = torch.tensor([[[0.0, 2.0], [0.0, 1.0]]], requires_grad=True)
    loss = retrieval_state_loss(f_s, f_t, eps=0.0)
    # normalised: S = [[1,0],[0,1]], T = [[0,1],[0,1]] -> squared diffs 1,1,0,0 -> mean 0.5
    assert loss.item() == pytest.approx(0.5)
    loss.backward()
    assert f_t.grad is None
    # rescaling a token's response does not change the normalised loss
    scaled = retrieval_state_loss(f_s.detach() * torch.tensor([[[7.0], [0.1]]]), f_t.detach(), eps=0.0)
    assert scaled.item() == pytest.approx(0.5)


def test_distillation_state_loss_weights_retrieval_and_skips_it_at_zero():
    u_s, u_t = torch.tensor([1.0, 1.0]), torch.tensor([0.0, 1.0])
    f_s = torch.tensor([[[1.0, 0.0]]])
    f_t = torch.tensor([[[0.0, 1.0]]])
    terms = distillation_state_loss(u_s, u_t, f_s, f_t, lambda_ret=0.15, eps=0.0)
    assert terms["traj"].item() == pytest.approx(0.5)
    assert terms["ret"].item() == pytest.approx(1.0)
    assert terms["loss"].item() == pytest.approx(0.5 + 0.15 * 1.0)
    without = distillation_state_loss(u_s, u_t, None, None, lambda_ret=0.0, eps=0.0)
    assert "ret" not in without and without["loss"].item() == pytest.approx(0.5)
    with pytest.raises(ValueError, match="lambda_ret"):
        distillation_state_loss(u_s, u_t, None, None, lambda_ret=0.15, eps=0.0)
