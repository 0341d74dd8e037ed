"""Rigid transforms: 6-vector and matrix forms, composition, inversion and the pose error.

Conventions:
    * Pose vector ``p`` (..., 6): ``(r_x, r_y, r_z, t_x, t_y, t_z)``, rotation vector in radians
      first, translation in millimetres second; it stands for ``x -> exp([r]x) x + t``.
    * Pose matrix ``T`` (..., 4, 4) (or (..., 3, 4) where stated), ``T = [[R, t], [0, 1]]``.
    * ``se3_compose(a, b)`` is ``a o b`` (apply ``b`` first).
"""

from __future__ import annotations

import torch
from torch import Tensor

from svr.geometry import _cf
from svr.geometry._validation import check_se3_matrix, check_tensor, promote_float64
from svr.geometry.so3 import (
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inverse,
    so3_log,
)


def _assemble(R: Tensor, t: Tensor) -> Tensor:
    top = torch.cat([R, t.unsqueeze(-1)], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def vector_to_se3(pose: Tensor) -> Tensor:
    """Pose matrix of a pose vector.

    Args:
        pose: (..., 6) pose vectors ``(r, t)``: rotation vector (rad), translation (mm).

    Returns:
        (..., 4, 4) matrices ``[[exp([r]x), t], [0, 1]]``.
    """
    check_tensor(pose, "vector_to_se3", "pose", (6,))
    return _assemble(so3_exp(pose[..., :3]), pose[..., 3:])


def se3_to_vector(matrix: Tensor) -> Tensor:
    """Pose vector of a pose matrix; the rotation vector has angle in ``[0, pi]``.

    Args:
        matrix: (..., 4, 4) or (..., 3, 4) rigid transforms.

    Returns:
        (..., 6) pose vectors ``(r, t)``.
    """
    check_se3_matrix(matrix, "se3_to_vector", "matrix")
    return torch.cat([so3_log(matrix[..., :3, :3]), matrix[..., :3, 3]], dim=-1)


def se3_compose(a: Tensor, b: Tensor) -> Tensor:
    """Composition ``a o b`` of rigid transforms (``b`` applied first): ``R_a R_b, R_a t_b + t_a``.

    Args:
        a: (..., 4, 4) or (..., 3, 4) rigid transforms.
        b: (..., 4, 4) or (..., 3, 4) rigid transforms, broadcastable with ``a``.

    Returns:
        (..., 4, 4) rigid transforms, or (..., 3, 4) if both inputs are (..., 3, 4).
    """
    check_se3_matrix(a, "se3_compose", "a")
    check_se3_matrix(b, "se3_compose", "b")
    Ra, ta = a[..., :3, :3], a[..., :3, 3:]
    Rb, tb = b[..., :3, :3], b[..., :3, 3:]
    out = torch.cat([Ra @ Rb, Ra @ tb + ta], dim=-1)
    if a.shape[-2] == 3 and b.shape[-2] == 3:
        return out
    return _assemble(out[..., :3], out[..., 3])


def se3_inverse(a: Tensor) -> Tensor:
    """Inverse of rigid transforms: ``R^T, -R^T t``.

    Args:
        a: (..., 4, 4) or (..., 3, 4) rigid transforms.

    Returns:
        Inverse transforms with the shape of ``a``.
    """
    check_se3_matrix(a, "se3_inverse", "a")
    Rt = a[..., :3, :3].transpose(-1, -2)
    t_inv = -(Rt @ a[..., :3, 3:])
    if a.shape[-2] == 3:
        return torch.cat([Rt, t_inv], dim=-1)
    return _assemble(Rt, t_inv[..., 0])


def half_turns(dtype: torch.dtype = torch.float64) -> Tensor:
    """The rigid half turns about the x, y and z axes: a frame's front-back twins.

    ``se3_compose(half_turns()[a], T)`` is ``T`` turned by 180 degrees about axis ``a`` of the
    frame ``T`` maps into (for a canonical pose, the canonical axis through the origin).

    Args:
        dtype: Floating dtype of the result.

    Returns:
        (3, 4, 4) rigid transforms, zero translation, in the order x, y, z.
    """
    out = torch.eye(4, dtype=dtype).repeat(3, 1, 1)
    out[:, :3, :3] = so3_exp(torch.eye(3, dtype=dtype) * torch.pi)
    return out


def se3_error(pred: Tensor, target: Tensor) -> Tensor:
    """Pose error at the identity, ``e = Log_id(pred^-1 o target)``.

    ``e = (rotvec(R_pred^T R_target), R_pred^T (t_target - t_pred))``: the rotation vector of
    the relative rotation (angle in ``[0, pi]``) and the translation difference expressed in the
    predicted frame. This is the error of the left-invariant metric (product metric on
    SO(3) x R^3), not the screw-motion log :func:`se3_group_log`. It is computed in float64 (via
    quaternions) and returned in the inputs' dtype, so that float32 inputs give errors accurate to
    float32 precision even when the error is far smaller than the poses.

    Args:
        pred: (..., 6) predicted pose vectors ``(r, t)``.
        target: (..., 6) true pose vectors, broadcastable with ``pred``.

    Returns:
        (..., 6) error vectors (rad, mm).
    """
    check_tensor(pred, "se3_error", "pred", (6,))
    check_tensor(target, "se3_error", "target", (6,))
    dtype = torch.result_type(pred, target)
    p, g = torch.broadcast_tensors(*promote_float64(pred, target))
    e, _ = error_cf(torch.stack([p, g]).movedim(-1, 0))
    return e.movedim(0, -1).to(dtype)


def error_cf(poses: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`se3_error` on component-first poses.

    Args:
        poses: (6, 2, ...) tensor; ``poses[:, 0]`` are the predictions, ``poses[:, 1]`` the targets.

    Returns:
        The (6, ...) errors and the (4, ...) quaternions of ``R_pred^-1``.
    """
    q = _cf.rotvec_to_quat(poses[:3], canonicalize=False)  # the error is sign-invariant
    q_pred_inv = _cf.quat_conjugate(q[:, 0])
    e_rot = _cf.quat_to_rotvec(_cf.quat_multiply(q_pred_inv, q[:, 1]))
    e_trans = _cf.quat_rotate(q_pred_inv, poses[3:, 1] - poses[3:, 0])
    return torch.cat([e_rot, e_trans]), q_pred_inv


def se3_group_exp(twist: Tensor) -> Tensor:
    """Group exponential of SE(3) (screw motion), for comparison with the pose-vector chart.

    ``exp((w, u)) = [[exp([w]x), V(w) u], [0, 1]]`` with ``V = J_l(w)``.

    Args:
        twist: (..., 6) twists ``(w, u)``: rotation part (rad) first, translation part (mm).

    Returns:
        (..., 4, 4) rigid transforms.
    """
    check_tensor(twist, "se3_group_exp", "twist", (6,))
    w, u = twist[..., :3], twist[..., 3:]
    return _assemble(so3_exp(w), (so3_left_jacobian(w) @ u.unsqueeze(-1))[..., 0])


def se3_group_log(matrix: Tensor) -> Tensor:
    """Group logarithm of SE(3) (screw motion), the inverse of :func:`se3_group_exp`.

    ``log(T) = (w, V(w)^-1 t)`` with ``w = so3_log(R)`` (angle in ``[0, pi]``). Its translation
    part differs from the pose vector's ``t`` perpendicular to the rotation axis.

    Args:
        matrix: (..., 4, 4) or (..., 3, 4) rigid transforms.

    Returns:
        (..., 6) twists ``(w, u)``.
    """
    check_se3_matrix(matrix, "se3_group_log", "matrix")
    w = so3_log(matrix[..., :3, :3])
    u = (so3_left_jacobian_inverse(w) @ matrix[..., :3, 3:])[..., 0]
    return torch.cat([w, u], dim=-1)
