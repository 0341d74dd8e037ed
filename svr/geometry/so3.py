"""Rotations: rotation vectors, quaternions, matrices, Euler angles and the 6D representation.

All functions are batched over any leading dimensions, work in float32 and float64 on CPU and CUDA,
and are differentiable with finite gradients at every input (see :mod:`svr.geometry._series`).

Conventions:
    * Rotation vector ``r`` (..., 3): axis times angle in radians, ``R = exp([r]x)``.
    * Quaternion ``q`` (..., 4): ``(w, x, y, z)``, scalar first, unit norm; functions that return
      quaternions canonicalise them to ``w >= 0``.
    * Matrices ``R`` (..., 3, 3) act on column vectors: ``x' = R x``.
    * Euler angles (..., 3) in radians, extrinsic ``"xyz"`` by default, i.e. scipy's
      ``Rotation.from_euler("xyz", angles)``: ``R = Rz(angles[2]) Ry(angles[1]) Rx(angles[0])``.
      Upper-case sequences are intrinsic, as in scipy.
    * 6D representation (..., 6): the first two columns of ``R`` concatenated,
      ``(R00, R10, R20, R01, R11, R21)`` (Zhou et al. 2019), mapped back by Gram-Schmidt.
"""

from __future__ import annotations

import torch
from torch import Tensor

from svr.geometry import _cf, _series
from svr.geometry._validation import check_tensor


def hat(v: Tensor) -> Tensor:
    """Skew-symmetric cross-product matrix ``[v]x`` with ``[v]x w = v x w``.

    Args:
        v: (..., 3) vectors.

    Returns:
        (..., 3, 3) matrices.
    """
    check_tensor(v, "hat", "v", (3,))
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).unflatten(-1, (3, 3))


def rotvec_to_quat(rotvec: Tensor) -> Tensor:
    """Unit quaternion of a rotation vector.

    Args:
        rotvec: (..., 3) rotation vectors in radians, any norm.

    Returns:
        (..., 4) quaternions ``(w, x, y, z)`` with ``w >= 0``.
    """
    check_tensor(rotvec, "rotvec_to_quat", "rotvec", (3,))
    return _cf.rotvec_to_quat(rotvec.movedim(-1, 0)).movedim(0, -1)


def quat_to_rotvec(quat: Tensor) -> Tensor:
    """Rotation vector of a quaternion, with angle in ``[0, pi]``.

    Uses ``angle = 2 atan2(|v|, |w|)`` (no ``acos``, finite at ``pi``). The quaternion need not be
    normalised; ``q`` and ``-q`` give the same result.

    Args:
        quat: (..., 4) quaternions ``(w, x, y, z)``, non-zero.

    Returns:
        (..., 3) rotation vectors in radians.
    """
    check_tensor(quat, "quat_to_rotvec", "quat", (4,))
    return _cf.quat_to_rotvec(quat.movedim(-1, 0)).movedim(0, -1)


def quat_to_matrix(quat: Tensor) -> Tensor:
    """Rotation matrix of a quaternion (normalised internally, so any non-zero ``q`` is valid).

    Args:
        quat: (..., 4) quaternions ``(w, x, y, z)``.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    check_tensor(quat, "quat_to_matrix", "quat", (4,))
    w, x, y, z = quat.unbind(-1)
    s = 2.0 / quat.square().sum(-1)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    return torch.stack(
        [
            1 - yy - zz,
            xy - wz,
            xz + wy,
            xy + wz,
            1 - xx - zz,
            yz - wx,
            xz - wy,
            yz + wx,
            1 - xx - yy,
        ],
        dim=-1,
    ).unflatten(-1, (3, 3))


def matrix_to_quat(matrix: Tensor) -> Tensor:
    """Unit quaternion of a rotation matrix (Shepperd's method: pivot on the largest component).

    Args:
        matrix: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) quaternions ``(w, x, y, z)`` with ``w >= 0``.
    """
    check_tensor(matrix, "matrix_to_quat", "matrix", (3, 3))
    m = matrix.flatten(-2)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.unbind(-1)
    # 4 q_i^2 for i = w, x, y, z; the largest is >= 1, so its square root is well conditioned.
    four_q2 = torch.stack(
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        dim=-1,
    )
    # Each row is 4 q_i q_j for the pivot i; dividing by 2 sqrt(4 q_i^2) = 4 |q_i| gives q.
    candidates = torch.stack(
        [
            torch.stack([four_q2[..., 0], m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, four_q2[..., 1], m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, four_q2[..., 2], m21 + m12], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, four_q2[..., 3]], dim=-1),
        ],
        dim=-2,
    )
    # The clamp only touches pivots that are not selected; it keeps their gradients finite.
    candidates = candidates / (2.0 * four_q2.clamp_min(0.1).sqrt()).unsqueeze(-1)
    pivot = four_q2.argmax(dim=-1, keepdim=True)
    q = torch.gather(candidates, -2, pivot.unsqueeze(-1).expand(*pivot.shape, 4)).squeeze(-2)
    return _cf.canonical(q.movedim(-1, 0)).movedim(0, -1)


def so3_exp(rotvec: Tensor) -> Tensor:
    """Rotation matrix of a rotation vector (Rodrigues' formula via the unit quaternion).

    Args:
        rotvec: (..., 3) rotation vectors in radians, any norm.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    check_tensor(rotvec, "so3_exp", "rotvec", (3,))
    return quat_to_matrix(rotvec_to_quat(rotvec))


def so3_log(matrix: Tensor) -> Tensor:
    """Rotation vector of a rotation matrix, angle in ``[0, pi]``.

    At exactly ``pi`` the sign of the axis is arbitrary (``r`` and ``-r`` are the same rotation).
    In float32, the angle is limited by what the matrix entries hold: errors of order 1e-7 rad
    absolute in the angle, and of the axis near ``pi`` (see the test suite for the bound reached).

    Args:
        matrix: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors in radians.
    """
    check_tensor(matrix, "so3_log", "matrix", (3, 3))
    return quat_to_rotvec(matrix_to_quat(matrix))


def rotation_angle(a: Tensor, b: Tensor) -> Tensor:
    """Angle of the rotation that takes ``a`` to ``b``: of ``A^T B`` for their rotation parts.

    Args:
        a: (..., 3, 3) rotation matrices or (..., 4, 4) rigid transforms (their top-left 3 x 3).
        b: The same, broadcastable with ``a``.

    Returns:
        (...) angles in radians, in ``[0, pi]``.
    """
    ra, rb = a[..., :3, :3], b[..., :3, :3]
    check_tensor(ra, "rotation_angle", "a", (3, 3))
    check_tensor(rb, "rotation_angle", "b", (3, 3))
    return so3_log(ra.transpose(-1, -2) @ rb).norm(dim=-1)


def regularize_rotvec(rotvec: Tensor) -> Tensor:
    """Equivalent rotation vector with norm in ``[0, pi]``.

    Args:
        rotvec: (..., 3) rotation vectors in radians, any norm.

    Returns:
        (..., 3) rotation vectors of the same rotations with angle in ``[0, pi]``.
    """
    check_tensor(rotvec, "regularize_rotvec", "rotvec", (3,))
    return quat_to_rotvec(rotvec_to_quat(rotvec))


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a * b`` (the rotation ``b`` followed by ``a``).

    Args:
        a: (..., 4) quaternions ``(w, x, y, z)``.
        b: (..., 4) quaternions, broadcastable with ``a``.

    Returns:
        (..., 4) quaternions, not canonicalised.
    """
    check_tensor(a, "quat_multiply", "a", (4,))
    check_tensor(b, "quat_multiply", "b", (4,))
    a, b = torch.broadcast_tensors(a, b)
    return _cf.quat_multiply(a.movedim(-1, 0), b.movedim(-1, 0)).movedim(0, -1)


def quat_rotate(quat: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors by unit quaternions: ``R(q) v``.

    Args:
        quat: (..., 4) unit quaternions ``(w, x, y, z)``.
        v: (..., 3) vectors, broadcastable with ``quat``.

    Returns:
        (..., 3) rotated vectors.
    """
    check_tensor(quat, "quat_rotate", "quat", (4,))
    check_tensor(v, "quat_rotate", "v", (3,))
    shape = torch.broadcast_shapes(quat.shape[:-1], v.shape[:-1])
    q_cf = quat.expand(*shape, 4).movedim(-1, 0)
    return _cf.quat_rotate(q_cf, v.expand(*shape, 3).movedim(-1, 0)).movedim(0, -1)


_AXES = {"x": 0, "y": 1, "z": 2}


def _parse_convention(convention: str, func: str) -> tuple[tuple[int, int, int], bool]:
    if not isinstance(convention, str):
        raise TypeError(
            f"{func}(): 'convention' must be a string such as 'xyz', "
            f"got {type(convention).__name__}"
        )
    seq = convention.lower()
    if (
        len(convention) != 3
        or not (convention.islower() or convention.isupper())
        or set(seq) != {"x", "y", "z"}
    ):
        raise ValueError(
            f"{func}(): 'convention' must be a Tait-Bryan sequence such as 'xyz' "
            f"(extrinsic) or 'XYZ' (intrinsic), got {convention!r}"
        )
    return tuple(_AXES[c] for c in seq), convention.isupper()  # type: ignore[return-value]


def _axis_rotation(angle: Tensor, axis: int) -> Tensor:
    c, s = angle.cos(), angle.sin()
    o, one = torch.zeros_like(angle), torch.ones_like(angle)
    rows = {
        0: [one, o, o, o, c, -s, o, s, c],
        1: [c, o, s, o, one, o, -s, o, c],
        2: [c, -s, o, s, c, o, o, o, one],
    }[axis]
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def euler_to_matrix(angles_rad: Tensor, convention: str = "xyz") -> Tensor:
    """Rotation matrix from Euler angles, as scipy's ``Rotation.from_euler(convention, angles)``.

    Args:
        angles_rad: (..., 3) angles in radians, in the order of ``convention``.
        convention: A Tait-Bryan axis sequence; lower case is extrinsic (rotations about the fixed
            axes, ``"xyz"`` gives ``Rz @ Ry @ Rx``), upper case intrinsic (``"XYZ"`` gives
            ``Rx @ Ry @ Rz``).

    Returns:
        (..., 3, 3) rotation matrices.
    """
    check_tensor(angles_rad, "euler_to_matrix", "angles_rad", (3,))
    axes, intrinsic = _parse_convention(convention, "euler_to_matrix")
    mats = [_axis_rotation(a, ax) for a, ax in zip(angles_rad.unbind(-1), axes, strict=True)]
    if intrinsic:
        return mats[0] @ mats[1] @ mats[2]
    return mats[2] @ mats[1] @ mats[0]


def matrix_to_euler(matrix: Tensor, convention: str = "xyz") -> Tensor:
    """Euler angles of a rotation matrix, as scipy's ``Rotation.as_euler(convention)``.

    The middle angle is in ``[-pi/2, pi/2]``, the others in ``(-pi, pi]``. At gimbal lock
    (middle angle ``+-pi/2``) the third angle is set to zero, as scipy does.

    Args:
        matrix: (..., 3, 3) rotation matrices.
        convention: Axis sequence, as in :func:`euler_to_matrix`.

    Returns:
        (..., 3) angles in radians, in the order of ``convention``.
    """
    check_tensor(matrix, "matrix_to_euler", "matrix", (3, 3))
    axes, intrinsic = _parse_convention(convention, "matrix_to_euler")
    if intrinsic:  # intrinsic (a, b, c) about (I, J, K) == extrinsic (c, b, a) about (K, J, I)
        return _extrinsic_angles(matrix, axes[::-1], lock_zero_first=True).flip(-1)
    return _extrinsic_angles(matrix, axes, lock_zero_first=False)


def _extrinsic_angles(m: Tensor, axes: tuple[int, ...], lock_zero_first: bool) -> Tensor:
    # R = R_k(c) R_j(b) R_i(a); s is the parity of the permutation (i, j, k). At gimbal lock
    # (cos b = 0), R_j(b) R_i(a) = R_k(-s sin(b) a) R_j(b), so only c - s sin(b) a is determined:
    # with c = 0 it is a = a_locked, with a = 0 it is c = -s sign(sin b) a_locked.
    i, j, k = axes
    s = 1.0 if (j - i) % 3 == 1 else -1.0
    sin_b = -s * m[..., k, i]
    cos_b = (m[..., k, j].square() + m[..., k, k].square()).clamp_min(1e-30).sqrt()
    b = torch.atan2(sin_b, cos_b)
    locked = cos_b < 1e-7 if m.dtype == torch.float64 else cos_b < 1e-4
    a_free = torch.atan2(s * m[..., k, j], m[..., k, k])
    c_free = torch.atan2(s * m[..., j, i], m[..., i, i])
    a_locked = torch.atan2(-s * m[..., j, k], m[..., j, j])
    zero = torch.zeros_like(a_free)
    if lock_zero_first:
        a = torch.where(locked, zero, a_free)
        c = torch.where(locked, -s * torch.sign(sin_b) * a_locked, c_free)
    else:
        a = torch.where(locked, a_locked, a_free)
        c = torch.where(locked, zero, c_free)
    return torch.stack([a, b, c], dim=-1)


def rotation_6d_to_matrix(d6: Tensor) -> Tensor:
    """Rotation matrix from the 6D representation by Gram-Schmidt (Zhou et al. 2019).

    Args:
        d6: (..., 6) two 3-vectors ``(a1, a2)``: the first and (not necessarily orthogonal)
            second column of the rotation; they must not be parallel.

    Returns:
        (..., 3, 3) rotation matrices with columns ``b1 = a1/|a1|``, ``b2`` (``a2`` made
        orthogonal to ``b1`` and normalised) and ``b3 = b1 x b2``.
    """
    check_tensor(d6, "rotation_6d_to_matrix", "d6", (6,))
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = torch.nn.functional.normalize(a1, dim=-1)
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def matrix_to_rotation_6d(matrix: Tensor) -> Tensor:
    """6D representation of a rotation matrix: its first two columns.

    The layout is ``(R00, R10, R20, R01, R11, R21)``.

    Args:
        matrix: (..., 3, 3) rotation matrices.

    Returns:
        (..., 6) vectors.
    """
    check_tensor(matrix, "matrix_to_rotation_6d", "matrix", (3, 3))
    return matrix[..., :, :2].transpose(-1, -2).flatten(-2)


def so3_left_jacobian(rotvec: Tensor) -> Tensor:
    """Left Jacobian ``J_l(r) = I + (1 - cos t)/t^2 [r]x + (t - sin t)/t^3 [r]x^2`` of SO(3).

    ``exp(r + d) ~ exp(J_l(r) d) exp(r)`` for small ``d``; the right Jacobian is ``J_l(-r)``.
    It is also the ``V`` matrix of the SE(3) exponential.

    Args:
        rotvec: (..., 3) rotation vectors in radians.

    Returns:
        (..., 3, 3) matrices.
    """
    check_tensor(rotvec, "so3_left_jacobian", "rotvec", (3,))
    theta2 = rotvec.square().sum(-1)[..., None, None]
    k = hat(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return (
        eye
        + _series.one_minus_cos_over_theta2(theta2) * k
        + _series.theta_minus_sin_over_theta3(theta2) * (k @ k)
    )


def so3_left_jacobian_inverse(rotvec: Tensor) -> Tensor:
    """Inverse left Jacobian ``J_l(r)^-1 = I - [r]x / 2 + (1 - (t/2) cot(t/2))/t^2 [r]x^2``.

    Valid for rotation angles in ``[0, 2 pi)``; the inverse right Jacobian is ``J_l(-r)^-1``.

    Args:
        rotvec: (..., 3) rotation vectors in radians.

    Returns:
        (..., 3, 3) matrices.
    """
    check_tensor(rotvec, "so3_left_jacobian_inverse", "rotvec", (3,))
    theta2 = rotvec.square().sum(-1)[..., None, None]
    k = hat(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye - 0.5 * k + _series.inverse_jacobian_coefficient(theta2) * (k @ k)
