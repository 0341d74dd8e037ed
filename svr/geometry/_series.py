"""Rotation-angle coefficients, finite with finite gradients at every angle.

Every coefficient is a function of ``theta2 = |r|^2``. Near zero, the exact closed form either
divides by zero or cancels catastrophically, so a Taylor series in ``theta2`` is used below a
dtype-dependent threshold. ``torch.where`` back-propagates through both branches, so the exact
branch is fed a safe ``theta2`` (1) wherever the series is used: the "double-where" pattern that
keeps gradients finite (one ``where`` alone gives NaN gradients at ``r = 0``).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

TINY = 1e-30
"""Offset under the square root of theta^2 that keeps it and its gradient finite at zero."""

_TINY_FLOAT16 = 1e-4  # 1e-30 underflows to 0 in float16; 1e-4 changes no value at its precision

# Below these values of theta^2 the series replaces the closed form. Coefficients whose closed
# form is free of cancellation only need to avoid 0/0; those that cancel (theta - sin theta,
# 1 - x cot x) need the series up to larger angles, more so in low precision.
_NO_CANCEL_THRESHOLD = {torch.float64: 1e-6, torch.float32: 1e-4}
_CANCEL_THRESHOLD = {torch.float64: 4e-3, torch.float32: 1.0}
_LOW_PRECISION = (torch.float16, torch.bfloat16)


def _threshold(table: dict[torch.dtype, float], dtype: torch.dtype) -> float:
    return table[torch.float32] if dtype in _LOW_PRECISION else table[dtype]


def _series_or_exact(
    theta2: Tensor, exact: Callable[[Tensor], Tensor], series: tuple[float, ...], threshold: float
) -> Tensor:
    small = theta2 < threshold
    safe_theta2 = torch.where(small, torch.ones_like(theta2), theta2)
    poly = theta2 * series[-1] + series[-2]
    for c in reversed(series[:-2]):
        poly = poly * theta2 + c
    return torch.where(small, poly, exact(safe_theta2))


def half_angle(theta2: Tensor, out: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """``cos(theta / 2)`` and ``sin(theta / 2) / theta`` as functions of ``theta^2``.

    These are the scalar part and the vector-part scale of the quaternion of a rotation vector.
    Both are free of cancellation, so no series is needed: the tiny offset in
    ``theta = sqrt(theta2 + 1e-30)`` makes the second exactly 1/2 at ``theta2 = 0`` (``sin x = x``
    in floating point for tiny ``x``) and keeps the gradients finite there, where
    ``d theta2 / d r = 2 r`` is exactly zero. The derivative of the second in ``theta`` cancels
    for small angles, but it only ever enters multiplied by ``r r^T / theta``, which bounds the
    resulting gradient error by ~eps.

    With ``out``, the two are written into its tensors in place (no autograd); the values are the
    same, as ``sin(theta/2) / (theta/2) / 2`` is ``sin(theta/2) / theta`` exactly.
    """
    if out is None:
        theta = (theta2 + (_TINY_FLOAT16 if theta2.dtype == torch.float16 else TINY)).sqrt()
        half = 0.5 * theta
        return half.cos(), half.sin() / theta
    c, s = out  # in-place transcendental functions are slow with several threads: avoided
    half = torch.sqrt(torch.add(theta2, TINY, out=c), out=s).mul_(0.5)
    torch.cos(half, out=c)
    return c, torch.div(half.sin(), half, out=s).mul_(0.5)


def one_minus_cos_over_theta2(theta2: Tensor) -> Tensor:
    """``(1 - cos theta) / theta^2``, as ``2 (sin(theta/2) / theta)^2`` (no cancellation)."""
    return 2.0 * half_angle(theta2)[1].square()


def theta_minus_sin_over_theta3(theta2: Tensor) -> Tensor:
    """``(theta - sin theta) / theta^3`` as a function of ``theta^2``."""

    def exact(t2: Tensor) -> Tensor:
        t = t2.sqrt()
        return (t - t.sin()) / (t2 * t)

    return _series_or_exact(
        theta2,
        exact,
        (1 / 6, -1 / 120, 1 / 5040, -1 / 362880),
        _threshold(_CANCEL_THRESHOLD, theta2.dtype),
    )


def inverse_jacobian_coefficient(theta2: Tensor) -> Tensor:
    """``(1 - (theta/2) cot(theta/2)) / theta^2``: the ``[r]x^2`` coefficient of ``J_l(r)^-1``.

    Finite for ``theta`` in ``[0, 2 pi)``; equals ``1 / pi^2`` at ``theta = pi``.
    """

    def exact(t2: Tensor) -> Tensor:
        half = 0.5 * t2.sqrt()
        return (1.0 - half * half.cos() / half.sin()) / t2

    return _series_or_exact(
        theta2,
        exact,
        (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600),
        _threshold(_CANCEL_THRESHOLD, theta2.dtype),
    )


def atan_ratio(n2: Tensor, w: Tensor) -> Tensor:
    """``atan2(n, w) / n`` for ``n = sqrt(n2) >= 0`` and ``w >= 0`` (quaternion -> half angle).

    Uses the series ``(1/w)(1 - x^2/3 + x^4/5 - x^6/7)`` with ``x = n / w`` where ``x`` is small.
    ``w`` and ``n`` must not both be zero.
    """
    small = n2 < _threshold(_NO_CANCEL_THRESHOLD, n2.dtype) * w.square()
    safe_n2 = torch.where(small, torch.ones_like(n2), n2)
    safe_w = torch.where(small, w, torch.ones_like(w))
    x2 = n2 / safe_w.square()
    series = (1.0 + x2 * (-1 / 3 + x2 * (1 / 5 - x2 / 7))) / safe_w
    n = safe_n2.sqrt()
    return torch.where(small, series, torch.atan2(n, w) / n)
