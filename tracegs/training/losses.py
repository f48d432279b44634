"""Loss terms of the three training stages, as pure functions of model outputs.

Every squared L2 norm of the paper is implemented as a mean squared error (mean over batch, frames,
channels and pixels / tokens), the reduction the supplement states for L_ret (Eq. supp-retrieval-loss) and
the one diffusers' CogVideoX training uses for the flow-matching term; it only rescales the loss weights.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def flow_matching_loss(predicted_velocity: Tensor, target_velocity: Tensor, weight: Tensor | None = None) -> Tensor:
    """L_fm: MSE between a predicted velocity and the schedule's velocity target (Sec. 3.3); with ``weight`` (B,),
    each sample's mean squared error is weighted before the batch mean."""
    if weight is None:
        return F.mse_loss(predicted_velocity, target_velocity.detach())
    per_sample = (predicted_velocity - target_velocity.detach()).pow(2).flatten(1).mean(dim=1)
    return (weight.to(per_sample) * per_sample).mean()


def alignment_loss(student_velocity: Tensor, teacher_velocity: Tensor) -> Tensor:
    """L_align (Eq. 3): ||v_S - sg[v_T]||^2 -- pulls the student toward the teacher, never the reverse."""
    return F.mse_loss(student_velocity, teacher_velocity.detach())


def warm_loss(
    student_velocity: Tensor, teacher_velocity: Tensor, target_velocity: Tensor, lambda_align: float,
    fm_weight: Tensor | None = None,
) -> dict[str, Tensor]:
    """Stage 1 objective L_warm = L_fm^S + L_fm^T + lambda_align L_align (supplement Eq. supp-stage1); ``fm_weight``
    weights the two L_fm terms per sample as ``flow_matching_loss`` does (L_align stays as written).

    Returns every term (keys ``fm_student``, ``fm_teacher``, ``align``, ``loss``) so each can be logged.
    """
    terms = {
        "fm_student": flow_matching_loss(student_velocity, target_velocity, fm_weight),
        "fm_teacher": flow_matching_loss(teacher_velocity, target_velocity, fm_weight),
        "align": alignment_loss(student_velocity, teacher_velocity),
    }
    terms["loss"] = terms["fm_student"] + terms["fm_teacher"] + lambda_align * terms["align"]
    return terms


def normalize_tokens(responses: Tensor, eps: float) -> Tensor:
    """Token-wise L2 normalisation F / (||F||_2 + eps) along channels (supplement Eq. supp-retrieval-normalization)."""
    return responses / (torch.linalg.vector_norm(responses, dim=-1, keepdim=True) + eps)


def retrieval_state_loss(student_response: Tensor, teacher_response: Tensor, eps: float) -> Tensor:
    """One visited state's term of L_ret (Eq. 8): MSE(Norm(F^S), sg[Norm(F^T)]) over (B, n_vid, d)."""
    return F.mse_loss(normalize_tokens(student_response, eps), normalize_tokens(teacher_response.detach(), eps))


def trajectory_state_loss(student_velocity: Tensor, teacher_velocity: Tensor) -> Tensor:
    """One visited state's term of L_traj (Eq. 6): ||u_i^S - sg[u_i^T]||^2."""
    return F.mse_loss(student_velocity, teacher_velocity.detach())


def distillation_state_loss(
    student_velocity: Tensor,
    teacher_velocity: Tensor,
    student_response: Tensor | None,
    teacher_response: Tensor | None,
    lambda_ret: float,
    eps: float,
) -> dict[str, Tensor]:
    """Eq. 9 at one visited state, before the 1/N average: traj_i + lambda_ret ret_i.

    With ``lambda_ret == 0`` the responses are not needed (pass None) and no ``ret`` term is returned,
    so variant F- pays nothing for the retrieval read-out.
    """
    terms = {"traj": trajectory_state_loss(student_velocity, teacher_velocity)}
    terms["loss"] = terms["traj"]
    if lambda_ret != 0.0:
        if student_response is None or teacher_response is None:
            raise ValueError("loss.lambda_ret != 0 needs the retrieval responses of both roles")
        terms["ret"] = retrieval_state_loss(student_response, teacher_response, eps)
        terms["loss"] = terms["loss"] + lambda_ret * terms["ret"]
    return terms
