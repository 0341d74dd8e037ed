"""Super-resolution volume reconstruction from posed slices.

The volume ``x`` minimises

    sum_p w_p (c_{s(p)} (A x)_p - y_p)^2 + lambda * sum_d sum_v phi(D_d x)_v,

``A`` the slice acquisition model (:class:`~svr.reconstruction.operators.SliceProjector`), ``y`` the
observed pixels, ``w`` robust (EM) pixel weights, ``c`` per-slice intensity scales and ``phi`` an
edge-preserving penalty on forward differences along the three axes, linearised around the
current volume (lagged diffusivity, ``phi'(g)/g = 1 / sqrt(1 + (g / delta)^2)``, as SVRTK's
edge-preserving regulariser). Each round is a linear least-squares problem solved by conjugate
gradients started from the current volume. The first estimate is the PSF-weighted
scattered-data approximation ``x0 = A^T (w y) / A^T w``.

Optionally (:class:`Background`) pixels a few millimetres outside the slices' masks join the data
term as observations of background, ``y = 0``: the masks say that the brain ends before them.
Without them nothing in the data says where the brain ends, the volume spreads beyond the masks,
and slice-to-volume registration follows it outward round after round.
"""

from __future__ import annotations

import math
from typing import NamedTuple, cast

import torch
from torch import Tensor

from svr.reconstruction.operators import SliceProjector, VolumeGrid
from svr.reconstruction.slices import SliceSet, mask_points

__all__ = [
    "Background",
    "coverage",
    "output_grid",
    "scattered_data_approximation",
    "sda_ratio",
    "slice_intensity_scales",
    "super_resolution",
]


def output_grid(slices: SliceSet, resolution_mm: float, margin_mm: float = 4.0) -> VolumeGrid:
    """An axis-aligned grid in the slices' frame covering every masked pixel.

    Args:
        slices: The slices; their poses' frame is the grid's frame.
        resolution_mm: Isotropic voxel size in mm (> 0).
        margin_mm: Extra space on every side (>= 0), beyond half the largest slice thickness.

    Returns:
        The grid: voxel (0, 0, 0) at the box's minimum corner, axes along the frame's x, y, z.
    """
    if not resolution_mm > 0 or not math.isfinite(resolution_mm):
        raise ValueError(f"output_grid(): 'resolution_mm' must be > 0, got {resolution_mm}")
    points, _ = mask_points(slices)
    pad = margin_mm + float(slices.thickness_mm.max()) / 2
    low = points.min(dim=0).values - pad
    high = points.max(dim=0).values + pad
    shape = cast(
        "tuple[int, int, int]",
        tuple(int(n) + 1 for n in torch.ceil((high - low) / resolution_mm).long().tolist()),
    )
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] *= resolution_mm
    affine[:3, 3] = low.cpu()
    return VolumeGrid(shape, affine)


def coverage(projector: SliceProjector, points: Tensor, weights: Tensor) -> Tensor:
    """``A^T w``: how much weighted data reaches each voxel, (I, J, K)."""
    return projector.adjoint(weights, points)


def scattered_data_approximation(
    projector: SliceProjector, points: Tensor, observed: Tensor, weights: Tensor
) -> Tensor:
    """PSF-weighted average of the observed pixels around each voxel.

    Args:
        projector: The acquisition model.
        points: Its :meth:`~SliceProjector.grid_points` at the slices' poses.
        observed: (P,) observed pixel values (already divided by the slice scales).
        weights: (P,) pixel weights.

    Returns:
        (I, J, K) ``A^T (w y) / A^T w``, 0 where no data reaches.
    """
    numerator = projector.adjoint(weights * observed, points)
    return sda_ratio(numerator, coverage(projector, points, weights))


def sda_ratio(numerator: Tensor, denominator: Tensor) -> Tensor:
    """The scattered-data volume ``A^T (w y) / A^T w`` from its two sums, (I, J, K).

    Voxels whose coverage is below 1e-3 of the largest are 0. The sums are linear in the pixels,
    so a volume of a subset of the slices is the ratio of the subsets' sums.
    """
    floor = 1e-3 * float(denominator.max().clamp_min(1e-12))
    return torch.where(denominator > floor, numerator / denominator.clamp_min(floor), 0.0)


def slice_intensity_scales(
    projector: SliceProjector, simulated: Tensor, observed: Tensor, weights: Tensor
) -> Tensor:
    """Per-slice scale ``c`` minimising ``sum w (c s - y)^2``, clamped to [0.5, 2], (N,)."""
    num = projector.slice_sums(weights * simulated * observed)
    den = projector.slice_sums(weights * simulated * simulated)
    scales = torch.where(den > 0, num / den.clamp_min(1e-12), 1.0)
    return scales.clamp(0.5, 2.0)


def _differences(x: Tensor) -> list[Tensor]:
    return [torch.diff(x, dim=axis) for axis in range(3)]


def _edge_weights(x: Tensor, delta: float) -> list[Tensor]:
    return [torch.rsqrt(1.0 + (g / delta) ** 2) for g in _differences(x)]


def _regularizer(x: Tensor, edge: list[Tensor]) -> Tensor:
    """``sum_d D_d^T diag(b_d) D_d x`` for forward differences ``D_d`` along each axis."""
    out = torch.zeros_like(x)
    for axis, (g, b) in enumerate(zip(_differences(x), edge, strict=True)):
        flux = g * b
        n = x.shape[axis]
        out.narrow(axis, 0, n - 1).sub_(flux)
        out.narrow(axis, 1, n - 1).add_(flux)
    return out


class Background(NamedTuple):
    """Pixels outside the slices' masks, observed as background (0) by super-resolution.

    Attributes:
        projector: The acquisition model of the background pixels (same grid, slices and PSF
            as the brain pixels' projector).
        points: Its :meth:`~SliceProjector.grid_points` at the slices' poses, (K, B, 3).
        weights: (B,) weight of each background pixel (0 leaves it out).
    """

    projector: SliceProjector
    points: Tensor
    weights: Tensor


def super_resolution(
    projector: SliceProjector,
    points: Tensor,
    observed: Tensor,
    weights: Tensor,
    scales: Tensor,
    volume: Tensor,
    iterations: int,
    regularization: float,
    edge_delta: float,
    background: Background | None = None,
) -> Tensor:
    """Conjugate-gradient super-resolution from a starting volume.

    Args:
        projector: The acquisition model.
        points: Its :meth:`~SliceProjector.grid_points` at the slices' poses.
        observed: (P,) observed pixel values.
        weights: (P,) pixel weights (robust weights, 0 for excluded slices).
        scales: (N,) per-slice intensity scales.
        volume: (I, J, K) starting volume (also the point the edge weights are computed at).
        iterations: Conjugate-gradient iterations (>= 0).
        regularization: Weight of the edge-preserving term, relative to the mean data weight per
            covered voxel.
        edge_delta: Intensity step (normalised units) above which an edge is preserved.
        background: Background pixels (observed 0) added to the data term, scaled like their
            slices' pixels, or ``None``.

    Returns:
        (I, J, K) non-negative volume.

    Raises:
        ValueError: If ``background``'s projector models another PSF than ``projector``.
    """
    c = scales[projector.slice_of]
    data_weight = weights * c * c
    rhs_data = projector.adjoint(weights * c * observed, points)
    cover = coverage(projector, points, data_weight)
    covered = cover > 1e-3 * float(cover.max().clamp_min(1e-12))
    lam = regularization * float(cover[covered].mean()) if covered.any() else 0.0
    edge = _edge_weights(volume, edge_delta)

    if background is not None:
        if background.projector.blur_sigma_vox != projector.blur_sigma_vox:
            raise ValueError(
                "super_resolution(): 'background' must model the same in-plane PSF as 'projector'"
            )
        b_projector, b_points = background.projector, background.points
        b_scale = scales[b_projector.slice_of]
        b_weight = background.weights * b_scale * b_scale

    def normal_operator(x: Tensor) -> Tensor:
        # A^T W A x with the in-plane blur B applied once per side for both pixel sets.
        blurred = projector.blur(x)
        spread = projector.spread(data_weight * projector.sample(blurred, points), points)
        if background is not None:
            spread = spread + b_projector.spread(
                b_weight * b_projector.sample(blurred, b_points), b_points
            )
        return projector.blur(spread) + lam * _regularizer(x, edge)

    x = volume.clone()
    r = rhs_data - normal_operator(x)
    p = r.clone()
    rr = float((r * r).sum())
    for _ in range(iterations):
        if rr <= 1e-20:
            break
        hp = normal_operator(p)
        alpha = rr / max(float((p * hp).sum()), 1e-30)
        x.add_(p, alpha=alpha)
        r.sub_(hp, alpha=alpha)
        rr_new = float((r * r).sum())
        p.mul_(rr_new / rr).add_(r)
        rr = rr_new
    return x.clamp_min_(0.0)
