"""Component-first kernels: vectors as (3, ...) and quaternions as (4, ...) tensors.

The public functions take (..., 3) and (..., 4) tensors and move the component axis to the front
before calling these. With components first, dot products reduce over an outer axis and scalars
broadcast along contiguous rows, which is several times faster in PyTorch's eager mode than
reducing a trailing axis of size 3; the fused SE(3) loss calls these kernels directly.
"""

from __future__ import annotations

import torch
from torch import Tensor

from svr.geometry import _series


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot products of (3, ...) vectors, kept as (1, ...)."""
    return (a * b).sum(0, keepdim=True)


def cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross products ``a x b`` of (3, ...) vectors of the same shape."""
    ax, ay, az = a
    bx, by, bz = b
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx])


def canonical(q: Tensor) -> Tensor:
    """Flip (4, ...) quaternions to ``w >= 0``."""
    return torch.where(q[:1] < 0, -q, q)


def quat_from_rotvec(r: Tensor, canonicalize: bool = True) -> Tensor:
    """(3, ...) rotation vectors to (4, ...) unit quaternions, with ``w >= 0`` if ``canonicalize``."""
    theta2 = dot(r, r)
    q = torch.cat([_series.half_cos(theta2), _series.half_sinc(theta2) * r])
    return canonical(q) if canonicalize else q


def rotvec_from_quat(q: Tensor) -> Tensor:
    """(4, ...) non-zero quaternions to (3, ...) rotation vectors with angle in ``[0, pi]``."""
    q = canonical(q)
    v = q[1:]
    return 2.0 * _series.atan_ratio(dot(v, v), q[:1]) * v


def quat_conjugate(q: Tensor) -> Tensor:
    """Conjugate ``(w, -v)`` of (4, ...) quaternions (the inverse rotation for unit ones)."""
    return torch.cat([q[:1], -q[1:]])


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of (4, ...) quaternions (same trailing shape)."""
    aw, av, bw, bv = a[:1], a[1:], b[:1], b[1:]
    return torch.cat([aw * bw - dot(av, bv), aw * bv + bw * av + cross(av, bv)])


def quat_rotate(q: Tensor, x: Tensor) -> Tensor:
    """Rotate (3, ...) vectors by (4, ...) unit quaternions: ``x + 2 (w (u x x) + u x (u x x))``."""
    w, u = q[:1], q[1:]
    ux = cross(u, x)
    return x + 2.0 * (w * ux + cross(u, ux))
