"""Weighted rigid fit of corresponding point sets (Horn's quaternion method), differentiable.

Given points ``x_i`` and their images ``y_i`` with weights ``w_i >= 0``, the fit is the rigid
transform ``T = (R, t)`` minimising ``sum_i w_i |R x_i + t - y_i|^2``: ``t`` makes the weighted
centroids coincide and ``R`` is the rotation of the unit quaternion that is the eigenvector of the
largest eigenvalue of Horn's symmetric 4 x 4 matrix built from the weighted cross-covariance
(Horn 1987; the same optimum as Kabsch/Umeyama's SVD, always a proper rotation).

Why not the SVD: its derivative divides by differences of singular values, which vanish when the
source points are spread alike in every direction (a cubic grid of cells, as the stack-pose
network's coordinate head has), so its gradients are infinite exactly where a network starts.
Horn's eigenvector only needs its own eigenvalue to be simple, which holds whenever the fit is
determined; its derivative is written out (:class:`_TopEigenvector`), so degenerate *other*
eigenvalues do no harm. A point set whose weighted spread is (nearly) collinear leaves the rotation
about that line undetermined and is rejected with a clear error (``min_spread_mm``).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from svr.geometry._validation import check_tensor
from svr.geometry.so3 import quat_to_matrix

__all__ = ["RigidFitError", "weighted_rigid_fit"]


class RigidFitError(ValueError):
    """A rigid fit that the points do not determine (too few, collinear, or all weights zero)."""


class _TopEigenvector(torch.autograd.Function):
    """Unit eigenvector of the largest eigenvalue of symmetric (..., n, n) matrices.

    Backward: ``dv = sum_{i != top} v_i (v_i^T dA v) / (l_top - l_i)``, so that
    ``grad_A = sym(sum_i c_i v_i v^T)`` with ``c_i = (v_i^T grad_v) / (l_top - l_i)``.
    """

    @staticmethod
    def forward(ctx: Any, matrix: Tensor) -> Tensor:
        values, vectors = torch.linalg.eigh(matrix)
        ctx.save_for_backward(values, vectors)
        return vectors[..., -1]

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tensor:
        values, vectors = ctx.saved_tensors
        top = vectors[..., -1]
        gap = values[..., -1:] - values[..., :-1]  # (..., n - 1), > 0 for a simple top
        proj = (vectors[..., :-1] * grad[..., :, None]).sum(-2) / gap  # (..., n - 1)
        direction = (vectors[..., :-1] * proj[..., None, :]).sum(-1)  # (..., n)
        outer = direction[..., :, None] * top[..., None, :]
        return 0.5 * (outer + outer.transpose(-1, -2))


def _horn_matrix(cov: Tensor) -> Tensor:
    """Horn's (..., 4, 4) matrix of ``S = sum w x y^T`` (source x, target y)."""
    sxx, sxy, sxz = cov[..., 0, 0], cov[..., 0, 1], cov[..., 0, 2]
    syx, syy, syz = cov[..., 1, 0], cov[..., 1, 1], cov[..., 1, 2]
    szx, szy, szz = cov[..., 2, 0], cov[..., 2, 1], cov[..., 2, 2]
    rows = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ]
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def weighted_rigid_fit(
    source: Tensor,
    target: Tensor,
    weights: Tensor | None = None,
    min_spread_mm: float = 1e-6,
) -> Tensor:
    """The rigid transform that best maps ``source`` points onto ``target`` points.

    Args:
        source: (..., N, 3) points (mm), N >= 3.
        target: (..., N, 3) corresponding points (mm), same shape.
        weights: (..., N) non-negative weights (default all 1); each batch needs a positive sum.
        min_spread_mm: The second-largest weighted standard deviation of ``source`` about its
            centroid must exceed this (mm), else the rotation is undetermined.

    Returns:
        (..., 4, 4) rigid transforms ``T`` with ``T x_i ~ y_i``, in the inputs' dtype.

    Raises:
        ValueError: Naming the argument, for wrong shapes or negative weights.
        RigidFitError: For a batch whose weights sum to 0 or whose points are (nearly) collinear.
    """
    func = "weighted_rigid_fit"
    check_tensor(source, func, "source", (3,))
    check_tensor(target, func, "target", (3,))
    if source.shape != target.shape:
        raise ValueError(
            f"{func}(): 'source' and 'target' must have the same shape, got "
            f"{tuple(source.shape)} and {tuple(target.shape)}"
        )
    if source.dim() < 2 or source.shape[-2] < 3:
        raise ValueError(f"{func}(): 'source' must hold N >= 3 points, got {tuple(source.shape)}")
    if weights is None:
        weights = torch.ones(source.shape[:-1], dtype=source.dtype, device=source.device)
    if weights.shape != source.shape[:-1]:
        raise ValueError(
            f"{func}(): 'weights' must have shape {tuple(source.shape[:-1])}, got "
            f"{tuple(weights.shape)}"
        )
    if bool((weights < 0).any()):
        raise ValueError(f"{func}(): 'weights' must be >= 0")
    total = weights.sum(-1, keepdim=True)
    if bool((total <= 0).any()):
        raise RigidFitError(f"{func}(): the weights of a point set sum to 0")
    w = (weights / total)[..., None]  # (..., N, 1)
    mu_x = (w * source).sum(-2, keepdim=True)
    mu_y = (w * target).sum(-2, keepdim=True)
    xc, yc = source - mu_x, target - mu_y
    if not (bool(torch.isfinite(source).all()) and bool(torch.isfinite(target).all())):
        raise ValueError(f"{func}(): 'source' and 'target' must be finite")
    with torch.no_grad():
        second = (w * xc).transpose(-1, -2) @ xc
        spread = torch.linalg.eigvalsh(second.to(torch.float64))  # ascending variances
    if bool((spread[..., 1] <= min_spread_mm**2).any()):
        raise RigidFitError(
            f"{func}(): the source points are (nearly) collinear or coincide "
            f"(spread <= {min_spread_mm} mm); the rotation is undetermined"
        )
    cov = (w * xc).transpose(-1, -2) @ yc  # (..., 3, 3) = sum w x y^T
    quat = _TopEigenvector.apply(_horn_matrix(cov))
    rotation = quat_to_matrix(quat)
    translation = mu_y[..., 0, :] - (rotation @ mu_x[..., 0, :, None])[..., 0]
    out = torch.zeros((*source.shape[:-2], 4, 4), dtype=source.dtype, device=source.device)
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out
