"""Robust averaging of rigid transforms, batched: an L1 rotation median and a geometric median.

:func:`robust_mean_pose` averages ``M`` rigid transforms (for each of any number of independent
batches) so that a minority of gross outliers cannot move the result: the rotation is the L1
median under the bi-invariant metric of SO(3) (Hartley et al., "L1 rotation averaging using the
Weiszfeld algorithm", CVPR 2011) and the translation the geometric median. It is used to make
stacks of CNN slice poses rigid (:mod:`svr.reconstruction.cnn_init`) and to measure how far a
volume's frame is from another's.
"""

from __future__ import annotations

import torch
from torch import Tensor

from svr.geometry.so3 import so3_exp, so3_log

__all__ = ["robust_mean_pose"]

_DISTANCE_FLOOR = 1e-12  # rad or mm: Weiszfeld weights are 1 / max(distance, this)


def _weiszfeld_step(offsets: Tensor, weights: Tensor) -> Tensor:
    """One Weiszfeld step of the weighted geometric median, from the current estimate.

    Args:
        offsets: (B, M, 3) the points relative to the current estimate.
        weights: (B, M) non-negative weights.

    Returns:
        (B, 3) the move to the next estimate: ``sum(w_i x_i / |x_i|) / sum(w_i / |x_i|)``, with
        distances floored at ``_DISTANCE_FLOOR`` (a point on the estimate pulls hardest).
    """
    inverse = weights / offsets.norm(dim=-1).clamp_min(_DISTANCE_FLOOR)
    return (inverse[..., None] * offsets).sum(dim=-2) / inverse.sum(dim=-1, keepdim=True)


def _chordal_mean(rotations: Tensor, weights: Tensor) -> Tensor:
    """(B, 3, 3) weighted mean of (B, M, 3, 3) rotation matrices projected to SO(3) by SVD."""
    u, _, vh = torch.linalg.svd((weights[..., None, None] * rotations).sum(dim=-3))
    flip = torch.ones(u.shape[:-1], dtype=rotations.dtype, device=rotations.device)
    flip[..., 2] = torch.sign(torch.linalg.det(u @ vh))
    return (u * flip[..., None, :]) @ vh


def robust_mean_pose(
    transforms: Tensor,
    weights: Tensor | None = None,
    max_iterations: int = 100,
    tolerance: float = 1e-12,
) -> Tensor:
    """A robust average of rigid transforms: geodesic L1 median rotation, geometric median shift.

    The rotation minimises ``sum_i w_i angle(R^T R_i)`` by Weiszfeld iterations in the tangent
    space, ``R <- R exp(d)`` with ``d`` the Weiszfeld step of ``log(R^T R_i)``, started at the
    chordal mean projected to SO(3) by SVD. The translation minimises ``sum_i w_i |t - t_i|`` by
    Weiszfeld iterations from the weighted mean. Both medians tolerate up to half of the weight
    in gross outliers, and the result is equivariant: ``robust_mean_pose(G o T_i) = G o
    robust_mean_pose(T_i)`` for any rigid ``G``. Batches iterate together; each stops updating
    once its own step is shorter than ``tolerance``.

    Args:
        transforms: (..., M, 4, 4) rigid transforms, M >= 1 (any float dtype; computed in
            float64).
        weights: (..., M) non-negative weights, not all zero in any batch; default all 1.
        max_iterations: Most Weiszfeld iterations for each of rotation and translation, >= 1.
        tolerance: A batch's iterations stop once its step is shorter than this (rad for the
            rotation, mm for the translation), > 0.

    Returns:
        (..., 4, 4) float64 rigid transforms on the device of ``transforms``.

    Raises:
        TypeError: If ``transforms`` is not a floating-point tensor.
        ValueError: Naming the argument, for a wrong shape, an empty set, non-finite values,
            negative or all-zero weights, ``max_iterations`` < 1 or ``tolerance`` <= 0.
    """
    if not isinstance(transforms, Tensor) or not transforms.is_floating_point():
        raise TypeError(
            "robust_mean_pose(): 'transforms' must be a floating-point tensor (..., M, 4, 4), got "
            f"{getattr(transforms, 'dtype', type(transforms).__name__)}"
        )
    if transforms.dim() < 3 or tuple(transforms.shape[-2:]) != (4, 4) or transforms.shape[-3] == 0:
        raise ValueError(
            "robust_mean_pose(): 'transforms' must have shape (..., M, 4, 4) with M >= 1, got "
            f"{tuple(transforms.shape)}"
        )
    if not bool(transforms.isfinite().all()):
        raise ValueError("robust_mean_pose(): 'transforms' holds non-finite values")
    batch, m = transforms.shape[:-3], transforms.shape[-3]
    T = transforms.to(torch.float64).reshape(-1, m, 4, 4)
    if weights is None:
        w = torch.ones(T.shape[:2], dtype=torch.float64, device=T.device)
    else:
        if tuple(weights.shape) != (*batch, m):
            raise ValueError(
                f"robust_mean_pose(): 'weights' must have shape {(*batch, m)}, got "
                f"{tuple(weights.shape)}"
            )
        w = weights.to(device=T.device, dtype=torch.float64).reshape(-1, m)
        if not bool(w.isfinite().all()) or bool((w < 0).any()) or not bool((w > 0).any(-1).all()):
            raise ValueError(
                "robust_mean_pose(): 'weights' must be finite, non-negative and not all zero"
            )
    if not (isinstance(max_iterations, int) and max_iterations >= 1):
        raise ValueError(
            f"robust_mean_pose(): 'max_iterations' must be an int >= 1, got {max_iterations!r}"
        )
    if not tolerance > 0:
        raise ValueError(f"robust_mean_pose(): 'tolerance' must be > 0, got {tolerance!r}")
    rotations, translations = T[..., :3, :3], T[..., :3, 3]
    R = _chordal_mean(rotations, w)
    active = torch.ones(len(T), dtype=torch.bool, device=T.device)
    for _ in range(max_iterations):
        step = _weiszfeld_step(so3_log(R.transpose(-1, -2)[:, None] @ rotations), w)
        R = torch.where(active[:, None, None], R @ so3_exp(step), R)
        active = active & (step.norm(dim=-1) >= tolerance)
        if not bool(active.any()):
            break
    t = (w[..., None] * translations).sum(dim=-2) / w.sum(dim=-1, keepdim=True)
    active = torch.ones(len(T), dtype=torch.bool, device=T.device)
    for _ in range(max_iterations):
        step = _weiszfeld_step(translations - t[:, None], w)
        t = torch.where(active[:, None], t + step, t)
        active = active & (step.norm(dim=-1) >= tolerance)
        if not bool(active.any()):
            break
    out = torch.eye(4, dtype=torch.float64, device=T.device).repeat(len(T), 1, 1)
    out[:, :3, :3], out[:, :3, 3] = R, t
    return out.reshape(*batch, 4, 4)
