"""Component-first kernels: vectors as (3, ...) and quaternions as (4, ...) tensors.

The public functions take (..., 3) and (..., 4) tensors and move the component axis to the front
before calling these. With components first, dot products reduce over an outer axis and scalars
broadcast along contiguous rows, which is several times faster in PyTorch's eager mode than
reducing a trailing axis of size 3; the fused SE(3) loss calls these kernels directly.

The ``out=`` forms and :func:`add_cross_` work row by row in place, with no temporaries: they do
not support autograd and are meant for code that computes its own gradients (the fused loss).
Wherever they take a vector, the sequence of its three rows (``v.unbind(0)``) works as well.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import torch
from torch import Tensor

from svr.geometry import _series


def dot(
    a: Tensor | Sequence[Tensor], b: Tensor | Sequence[Tensor], out: Tensor | None = None
) -> Tensor:
    """Dot products of (3, ...) vectors, kept as (1, ...), or written into ``out`` (...)."""
    if out is None:
        return (cast("Tensor", a) * cast("Tensor", b)).sum(0, keepdim=True)  # sequences need out
    (ax, ay, az), (bx, by, bz) = a, b
    return torch.mul(ax, bx, out=out).addcmul_(ay, by).addcmul_(az, bz)


def cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross products ``a x b`` of (3, ...) vectors of the same shape."""
    ax, ay, az = a
    bx, by, bz = b
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx])


def add_cross_(
    out: Sequence[Tensor], a: Sequence[Tensor], b: Sequence[Tensor], alpha: float = 1.0
) -> None:
    """Add ``alpha (a x b)`` to the (3, ...) vectors ``out`` in place."""
    (ax, ay, az), (bx, by, bz), (ox, oy, oz) = a, b, out
    ox.addcmul_(ay, bz, value=alpha).addcmul_(az, by, value=-alpha)
    oy.addcmul_(az, bx, value=alpha).addcmul_(ax, bz, value=-alpha)
    oz.addcmul_(ax, by, value=alpha).addcmul_(ay, bx, value=-alpha)


def canonical(q: Tensor) -> Tensor:
    """Flip (4, ...) quaternions to ``w >= 0``."""
    return torch.where(q[:1] < 0, -q, q)


def rotvec_to_quat(r: Tensor, canonicalize: bool = True) -> Tensor:
    """(3, ...) rotation vectors to (4, ...) unit quaternions (``w >= 0`` if ``canonicalize``)."""
    c, s = _series.half_angle(dot(r, r))
    q = torch.cat([c, s * r])
    return canonical(q) if canonicalize else q


def quat_to_rotvec(q: Tensor) -> Tensor:
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


def quat_rotate(
    q: Tensor, x: Tensor, *, inverse: bool = False, out: Tensor | None = None
) -> Tensor:
    """Rotate (3, ...) vectors by (4, ...) unit quaternions: ``x + 2 (w (u x x) + u x (u x x))``.

    Args:
        q: (4, ...) unit quaternions ``(w, u)``.
        x: (3, ...) vectors.
        inverse: Rotate by the conjugates instead (the inverse rotations).
        out: If given, (3, ...) tensor that receives the result, as ``x + 2 s u x m`` with
            ``m = w x + s u x x`` and ``s = -1`` for the inverse (no autograd).

    Returns:
        The (3, ...) rotated vectors (``out`` if given).
    """
    w, u = q[:1], q[1:]
    if out is None:
        ux = cross(u, x)
        return x + 2.0 * ((-w if inverse else w) * ux + cross(u, ux))
    sign = -1.0 if inverse else 1.0
    m = x * w
    rows_m, rows_u, rows_x = m.unbind(0), u.unbind(0), x.unbind(0)
    add_cross_(rows_m, rows_u, rows_x, sign)
    (ux, uy, uz), (mx, my, mz), (xx, xy, xz) = rows_u, rows_m, rows_x
    ox, oy, oz = out
    alpha = 2.0 * sign
    torch.addcmul(xx, uy, mz, value=alpha, out=ox).addcmul_(uz, my, value=-alpha)
    torch.addcmul(xy, uz, mx, value=alpha, out=oy).addcmul_(ux, mz, value=-alpha)
    torch.addcmul(xz, ux, my, value=alpha, out=oz).addcmul_(uy, mx, value=-alpha)
    return out
