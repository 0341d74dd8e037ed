"""Rigid registration of slices (or groups of slices) to a volume by masked NCC.

Every group ``g`` (a single slice for slice-to-volume registration, a whole stack for stack
registration) gets a rigid correction applied on the frame side about the group's centre
``c_g``:

    T_i <- Trans(c_g + t_g) o R(r_g) o Trans(-c_g) o T_i,

so a stack moves as one rigid body and a single slice rotates about its own centre. The six
parameters per group are optimised by Adam on the mean of ``1 - NCC`` between each observed
slice and its simulation from the volume, coarse to fine: at level ``l`` of ``L`` the volume and
the slices are blurred by ``2^(L-1-l)`` times the volume's voxel size and every
``2^(L-1-l)``-th pixel is used. The rotation is parametrised as ``r_g = p / radius`` so that one
optimiser step moves points ``radius`` mm from the centre as far as a translation step does.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from reconstruction.operators import SliceProjector, gaussian_blur
from svr.geometry import so3_exp

__all__ = ["RegistrationConfig", "register_rigid", "slice_ncc"]


@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`register_rigid`.

    Attributes:
        levels: Resolution levels, coarse to fine (>= 1).
        iterations: Adam steps per level (>= 0).
        step_mm: Adam learning rate at the coarsest level in mm (halved at each finer level).
        radius_mm: Lever arm that converts rotation to displacement (mm).
    """

    levels: int = 3
    iterations: int = 20
    step_mm: float = 1.0
    radius_mm: float = 40.0


def slice_ncc(
    projector: SliceProjector, a: Tensor, b: Tensor, pixels: Tensor | None = None
) -> Tensor:
    """NCC of each slice between two pixel-value vectors over the slice's modelled pixels.

    Args:
        projector: Defines which slice each pixel belongs to.
        a: (P',) values.
        b: (P',) values.
        pixels: The indices into the projector's pixels that ``a`` and ``b`` hold (``None``: all).

    Returns:
        (N,) NCC in [-1, 1]; 0 for slices without pixels or without variance.
    """
    sid = projector.slice_of if pixels is None else projector.slice_of[pixels]
    n = torch.zeros(projector.num_slices, dtype=a.dtype, device=a.device)
    stats = torch.stack([torch.ones_like(a), a, b, a * a, b * b, a * b], dim=1)
    s = n[:, None].expand(-1, 6).index_add(0, sid, stats)
    count = s[:, 0].clamp_min(1)
    mean_a, mean_b = s[:, 1] / count, s[:, 2] / count
    var_a = s[:, 3] / count - mean_a**2
    var_b = s[:, 4] / count - mean_b**2
    cov = s[:, 5] / count - mean_a * mean_b
    denom = torch.sqrt((var_a * var_b).clamp_min(1e-24))
    return torch.where(denom > 1e-12, cov / denom.clamp_min(1e-12), torch.zeros_like(cov))


def _level_pixels(projector: SliceProjector, stride: int) -> Tensor:
    if stride == 1:
        return torch.arange(projector.num_pixels, device=projector.slice_of.device)
    w = projector.size[1]
    a, b = projector.pixel_of // w, projector.pixel_of % w
    return torch.nonzero((a % stride == 0) & (b % stride == 0)).flatten()


def _blur_slices(images: Tensor, sigma_px: float) -> Tensor:
    if sigma_px <= 0:
        return images
    return gaussian_blur(images.permute(1, 2, 0), (sigma_px, sigma_px, 0.0)).permute(2, 0, 1)


def register_rigid(
    projector: SliceProjector,
    volume: Tensor,
    observed: Tensor,
    poses: Tensor,
    groups: Tensor,
    config: RegistrationConfig = RegistrationConfig(),
    fixed: Tensor | None = None,
    slice_weights: Tensor | None = None,
) -> Tensor:
    """Rigidly align groups of slices to a volume.

    Args:
        projector: The acquisition model of the slices (its PSF is used for the simulations).
        volume: (I, J, K) volume on the projector's grid.
        observed: (N, H, W) observed slice images.
        poses: (N, 4, 4) starting poses in the volume's frame.
        groups: (N,) int64 group of each slice (0 .. G-1).
        config: Levels, iterations and step sizes.
        fixed: (G,) bool, groups that do not move (e.g. the template stack), or ``None``.
        slice_weights: (N,) weights of each slice in the objective (e.g. robust weights).

    Returns:
        (N, 4, 4) float64 registered poses.
    """
    poses = poses.to(torch.float64)
    num_groups = int(groups.max()) + 1
    ones = torch.ones(len(poses), dtype=torch.float64, device=poses.device)
    centres = torch.zeros(num_groups, 3, dtype=torch.float64, device=poses.device)
    centres = (
        centres.index_add(0, groups, poses[:, :3, 3])
        / torch.zeros(num_groups, dtype=torch.float64, device=poses.device)
        .index_add(0, groups, ones)
        .clamp_min(1)[:, None]
    )
    movable = torch.ones(num_groups, 1, dtype=torch.float64, device=poses.device)
    if fixed is not None:
        movable[fixed.to(poses.device)] = 0.0
    weights = (
        torch.ones(len(poses), device=poses.device)
        if slice_weights is None
        else slice_weights.to(device=poses.device, dtype=torch.float32)
    )
    voxel_mm = float(projector.grid.spacing.min())
    for level in range(config.levels):
        stride = 2 ** (config.levels - 1 - level)
        sigma_mm = voxel_mm * (stride if stride > 1 else 0)
        pixels = _level_pixels(projector, stride)
        blurred = projector.blur(
            gaussian_blur(volume, tuple(sigma_mm / float(s) for s in projector.grid.spacing))
            if sigma_mm > 0
            else volume
        ).detach()
        target = projector.gather(_blur_slices(observed, sigma_mm / projector.pixel_mm))[pixels]
        params = torch.zeros(num_groups, 6, dtype=torch.float64, device=poses.device)
        params.requires_grad_(True)
        step = config.step_mm / 2**level
        optimizer = torch.optim.Adam([params], lr=step)
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
            optimizer, max(config.iterations, 1), eta_min=step / 10
        )
        for _ in range(config.iterations):
            optimizer.zero_grad()
            moved = _apply(poses, params * movable, centres, groups, config.radius_mm)
            simulated = projector.sample(blurred, projector.grid_points(moved, pixels))
            ncc = slice_ncc(projector, simulated, target, pixels)
            loss = (weights * (1 - ncc)).sum() / weights.sum().clamp_min(1e-12)
            loss.backward()
            optimizer.step()
            schedule.step()
        with torch.no_grad():
            poses = _apply(poses, params * movable, centres, groups, config.radius_mm)
    return poses.detach()


def _apply(poses: Tensor, params: Tensor, centres: Tensor, groups: Tensor, radius: float) -> Tensor:
    """``Trans(c + t) R Trans(-c) T`` per slice from (G, 6) parameters ``(p, t)``, r = p / radius."""
    R = so3_exp(params[:, :3] / radius)  # (G, 3, 3)
    t = centres + params[:, 3:] - (R @ centres[..., None])[..., 0]
    Rg, tg = R[groups], t[groups]
    out = poses.clone()
    out[:, :3, :3] = Rg @ poses[:, :3, :3]
    out[:, :3, 3] = (Rg @ poses[:, :3, 3, None])[..., 0] + tg
    return out
