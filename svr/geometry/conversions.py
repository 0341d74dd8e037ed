"""Pose vectors to and from the output representations of the baseline losses.

Every representation maps back to a pose vector ``(r, t)`` (rad, mm), so that all methods are
evaluated the same way.

* Quaternion + translation (PoseNet) (..., 7): ``(w, x, y, z, t_x, t_y, t_z)``.
* Anchor points (..., 9): three points of the slice plane in the target frame,
  ``P1 = T(-a, -a, 0)``, ``P2 = T(0, 0, 0) = t`` and ``P3 = T(a, -a, 0)`` for half-size ``a`` mm
  (Hou et al.; the plane coordinates ``(u, v, 0)`` are those of the conventions page,
  ``docs/conventions.md``: origin at the slice centre).
* 6D + translation (..., 9): ``(matrix_to_rotation_6d(R), t)`` (Zhou et al. 2019).
"""

from __future__ import annotations

import torch
from torch import Tensor

from svr.geometry._validation import check_tensor
from svr.geometry.so3 import (
    matrix_to_rotation_6d,
    quat_to_rotvec,
    rotation_6d_to_matrix,
    rotvec_to_quat,
    so3_exp,
    so3_log,
)

ANCHOR_HALF_SIZE_MM = 60.0
"""Default half-size ``a`` (mm) of the anchor-point triangle: of the order of a fetal brain."""


def pose_to_quat_translation(pose: Tensor) -> Tensor:
    """Pose vectors to quaternion + translation, ``(w, x, y, z, t)`` with ``w >= 0``.

    Args:
        pose: (..., 6) pose vectors.

    Returns:
        (..., 7) tensors.
    """
    check_tensor(pose, "pose_to_quat_translation", "pose", (6,))
    return torch.cat([rotvec_to_quat(pose[..., :3]), pose[..., 3:]], dim=-1)


def quat_translation_to_pose(qt: Tensor) -> Tensor:
    """Quaternion + translation to pose vectors (the quaternion need not be normalised).

    Args:
        qt: (..., 7) tensors ``(w, x, y, z, t_x, t_y, t_z)`` with a non-zero quaternion.

    Returns:
        (..., 6) pose vectors.
    """
    check_tensor(qt, "quat_translation_to_pose", "qt", (7,))
    return torch.cat([quat_to_rotvec(qt[..., :4]), qt[..., 4:]], dim=-1)


def _plane_points(half_size_mm: float, like: Tensor) -> Tensor:
    a = half_size_mm
    return like.new_tensor([[-a, -a, 0.0], [0.0, 0.0, 0.0], [a, -a, 0.0]])


def _check_half_size(half_size_mm: float, func: str) -> None:
    if not half_size_mm > 0:
        raise ValueError(f"{func}(): 'half_size_mm' must be > 0, got {half_size_mm}")


def pose_to_anchor_points(pose: Tensor, half_size_mm: float = ANCHOR_HALF_SIZE_MM) -> Tensor:
    """Pose vectors to the three anchor points ``(P1, P2, P3)`` in the target frame (mm).

    Args:
        pose: (..., 6) pose vectors.
        half_size_mm: Half-size ``a`` of the triangle ``(-a, -a), (0, 0), (a, -a)`` in the plane.

    Returns:
        (..., 9) points ``(P1, P2, P3)``.
    """
    check_tensor(pose, "pose_to_anchor_points", "pose", (6,))
    _check_half_size(half_size_mm, "pose_to_anchor_points")
    R = so3_exp(pose[..., :3])
    plane = _plane_points(half_size_mm, pose)
    points = plane @ R.transpose(-1, -2) + pose[..., None, 3:]
    return points.flatten(-2)


def anchor_points_to_pose(points: Tensor, half_size_mm: float = ANCHOR_HALF_SIZE_MM) -> Tensor:
    """Recover pose vectors from (possibly noisy) anchor points by orthonormalisation.

    The in-plane axes are estimated as ``u = P3 - P1`` and ``v = P2 - (P1 + P3)/2`` and made
    orthonormal by Gram-Schmidt (``u`` kept); the translation is the centroid of the points
    minus the rotated centroid of the plane template, which equals ``P2`` for exact points.
    ``half_size_mm`` does not affect the rotation and only enters through the template centroid.

    Args:
        points: (..., 9) points ``(P1, P2, P3)`` in mm.
        half_size_mm: Half-size ``a`` used to make the points.

    Returns:
        (..., 6) pose vectors.
    """
    check_tensor(points, "anchor_points_to_pose", "points", (9,))
    _check_half_size(half_size_mm, "anchor_points_to_pose")
    p = points.unflatten(-1, (3, 3))
    p1, p2, p3 = p.unbind(-2)
    R = rotation_6d_to_matrix(torch.cat([p3 - p1, p2 - 0.5 * (p1 + p3)], dim=-1))
    centroid_plane = _plane_points(half_size_mm, points).mean(0)
    t = p.mean(-2) - (R @ centroid_plane)
    return torch.cat([so3_log(R), t], dim=-1)


def pose_to_rotation_6d_translation(pose: Tensor) -> Tensor:
    """Pose vectors to 6D rotation + translation.

    Args:
        pose: (..., 6) pose vectors.

    Returns:
        (..., 9) tensors ``(R00, R10, R20, R01, R11, R21, t_x, t_y, t_z)``.
    """
    check_tensor(pose, "pose_to_rotation_6d_translation", "pose", (6,))
    return torch.cat([matrix_to_rotation_6d(so3_exp(pose[..., :3])), pose[..., 3:]], dim=-1)


def rotation_6d_translation_to_pose(d6t: Tensor) -> Tensor:
    """6D rotation + translation to pose vectors (Gram-Schmidt on the 6D part).

    Args:
        d6t: (..., 9) tensors, 6D rotation then translation (mm).

    Returns:
        (..., 6) pose vectors.
    """
    check_tensor(d6t, "rotation_6d_translation_to_pose", "d6t", (9,))
    return torch.cat([so3_log(rotation_6d_to_matrix(d6t[..., :6])), d6t[..., 6:]], dim=-1)
