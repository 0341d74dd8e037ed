"""Rigid registration of slices (or groups of slices) to a volume by masked NCC.

Every group ``g`` (a single slice for slice-to-volume registration, a whole stack for stack
registration) gets a rigid correction applied on the frame side about the group's centre
``c_g`` (the mean of its slices' centres):

    X <- R(r_g) (X - c_g) + c_g + t_g   for every point X of the group's slices,

so a stack moves as one rigid body and a single slice rotates about its own centre.

The six parameters per group are found by Levenberg-Marquardt on the intensity-fitted
sum of squared differences between each observed slice ``y`` and its simulation ``s`` from the
volume (``min_{a,b} |y - a s - b|^2 = |y - mean(y)|^2 (1 - NCC^2)``, so it maximises NCC). The
Jacobian is analytic: ``ds/dt = grad V(X)`` and ``ds/dr = (X - c) x grad V(X)``, summed over the
PSF nodes, with the volume's gradient sampled together with the volume (one 4-channel
``grid_sample``). Steps that do not raise a group's weighted NCC are rejected and the damping is
increased (per group). Coarse to fine: at level ``l`` of ``L`` the volume and slices are blurred
by ``2^(L-1-l) - 1`` voxels and every ``2^(L-1-l)``-th pixel is used.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from svr.geometry import so3_exp
from svr.image import sample_channels
from svr.reconstruction.operators import SliceProjector, VolumeGrid, gaussian_blur
from svr.reconstruction.slices import SliceSet
from svr.reconstruction.superres import (
    coverage,
    output_grid,
    scattered_data_approximation,
    sda_ratio,
)
from svr.validation import check_int, check_number

__all__ = [
    "STACK_REGISTRATION",
    "SVR_PSF_SAMPLES",
    "RegistrationConfig",
    "SliceAgreement",
    "register_rigid",
    "slice_agreement",
    "slice_ncc",
    "stack_ncc",
    "stack_registration",
]

# PSF nodes along the normal for registration (the volume model uses more).
SVR_PSF_SAMPLES = 3


@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`register_rigid`.

    Attributes:
        levels: Resolution levels, coarse to fine (>= 1).
        iterations: Levenberg-Marquardt steps per level (>= 0).
        damping: Initial Marquardt damping (relative to the diagonal of the normal matrix).

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    levels: int = 3
    iterations: int = 6
    damping: float = 1e-2

    def __post_init__(self) -> None:
        owner = "RegistrationConfig"
        check_int(owner, "levels", self.levels, minimum=1)
        check_int(owner, "iterations", self.iterations, minimum=0)
        check_number(owner, "damping", self.damping, gt=0)


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


def _with_gradient(projector: SliceProjector, blurred: Tensor) -> Tensor:
    """(4, I, J, K): the volume and its gradient in frame coordinates (per mm)."""
    voxel_gradient = torch.stack(torch.gradient(blurred))  # d/di, d/dj, d/dk
    inverse = torch.linalg.inv(projector.grid.affine[:3, :3].to(torch.float64))
    frame_gradient = torch.einsum("ax,aijk->xijk", inverse.to(blurred), voxel_gradient)
    return torch.cat([blurred[None], frame_gradient])


def _move(poses: Tensor, rotvec: Tensor, shift: Tensor, centres: Tensor, groups: Tensor) -> Tensor:
    """Apply ``X -> R (X - c) + c + t`` per group to (N, 4, 4) poses; (G, 3) rotvec and shift."""
    R = so3_exp(rotvec)
    t = centres + shift - (R @ centres[..., None])[..., 0]
    Rg, tg = R[groups], t[groups]
    out = poses.clone()
    out[:, :3, :3] = Rg @ poses[:, :3, :3]
    out[:, :3, 3] = (Rg @ poses[:, :3, 3, None])[..., 0] + tg
    return out


def _group_sums(values: Tensor, groups: Tensor, num_groups: int) -> Tensor:
    return values.new_zeros((num_groups, *values.shape[1:])).index_add(0, groups, values)


def register_rigid(
    projector: SliceProjector,
    volume: Tensor,
    observed: Tensor,
    poses: Tensor,
    groups: Tensor,
    config: RegistrationConfig | None = None,
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
        config: Levels, iterations and damping.
        fixed: (G,) bool, groups that do not move (e.g. the template stack), or ``None``.
        slice_weights: (N,) weights of each slice in its group's objective (0 leaves it out).

    Returns:
        (N, 4, 4) float64 registered poses.
    """
    config = config or RegistrationConfig()
    device = volume.device
    poses = poses.to(device=device, dtype=torch.float64)
    groups = groups.to(device)
    num_groups = int(groups.max()) + 1
    ones = torch.ones(len(poses), dtype=torch.float64, device=device)
    centres = (
        _group_sums(poses[:, :3, 3], groups, num_groups)
        / _group_sums(ones, groups, num_groups).clamp_min(1)[:, None]
    )
    movable = torch.ones(num_groups, dtype=torch.bool, device=device)
    if fixed is not None:
        movable &= ~fixed.to(device)
    weights = ones if slice_weights is None else slice_weights.to(device, torch.float64)
    voxel = projector.grid.spacing.to(device)
    weights_k = projector.weights.to(device)
    for level in range(config.levels):
        stride = 2 ** (config.levels - 1 - level)
        pixels = _level_pixels(projector, stride)
        sid = projector.slice_of[pixels]
        gid = groups[sid]
        blur_vox = float(stride - 1)
        blurred = projector.blur(
            gaussian_blur(volume, (blur_vox,) * 3) if blur_vox > 0 else volume
        ).detach()
        channels = _with_gradient(projector, blurred)
        pixel_mm = float(voxel.min()) / projector.pixel_mm
        target = projector.gather(_blur_slices(observed, blur_vox * pixel_mm))[pixels]

        damping = torch.full((num_groups,), config.damping, dtype=torch.float64, device=device)
        current = _group_cost(projector, blurred, target, pixels, poses, weights, groups)
        for _ in range(config.iterations):
            points = projector.world_points(poses, pixels)  # (K, P, 3)
            samples = sample_channels(channels, projector.to_grid_coordinates(points))  # (4, K, P)
            sim = weights_k @ samples[0]
            gradient = samples[1:].permute(1, 2, 0)  # (K, P, 3)
            lever = points - centres.float()[gid][None]
            jac_r = torch.einsum("k,kpx->px", weights_k, torch.linalg.cross(lever, gradient))
            jac_t = torch.einsum("k,kpx->px", weights_k, gradient)
            jac = torch.cat([jac_r, jac_t], dim=1)  # (P, 6)
            # Per-slice intensity fit y ~ a s + b.
            stats = _slice_stats(projector, sid, sim, target)
            n = stats[:, 0].clamp_min(1)
            mean_s, mean_y = stats[:, 1] / n, stats[:, 2] / n
            var_s = stats[:, 3] / n - mean_s**2
            cov = stats[:, 4] / n - mean_s * mean_y
            a = torch.where(var_s > 1e-12, cov / var_s.clamp_min(1e-12), torch.zeros_like(cov))
            b = mean_y - a * mean_s
            residual = target - a[sid] * sim - b[sid]
            scale = (weights.float() * a)[sid]
            jw = jac * scale[:, None]
            hessian = (
                _group_sums(
                    (jw[:, :, None] * jac[:, None, :] * a[sid][:, None, None]).reshape(-1, 36),
                    gid,
                    num_groups,
                )
                .reshape(num_groups, 6, 6)
                .double()
            )
            rhs = _group_sums(jw * residual[:, None], gid, num_groups).double()
            diagonal = torch.diagonal(hessian, dim1=1, dim2=2)
            lhs = hessian + torch.diag_embed(damping[:, None] * diagonal + 1e-9)
            step = torch.linalg.solve(lhs, rhs[..., None])[..., 0]
            step = torch.where(movable[:, None], step, torch.zeros_like(step))
            candidate = _move(poses, step[:, :3], step[:, 3:], centres, groups)
            trial = _group_cost(projector, blurred, target, pixels, candidate, weights, groups)
            better = (trial < current) & movable
            accept = better[groups]
            poses = torch.where(accept[:, None, None], candidate, poses)
            current = torch.where(better, trial, current)
            damping = torch.where(better, damping / 3, damping * 4).clamp(1e-6, 1e6)
    return poses


def _group_cost(
    projector: SliceProjector,
    blurred: Tensor,
    target: Tensor,
    pixels: Tensor,
    poses: Tensor,
    weights: Tensor,
    groups: Tensor,
) -> Tensor:
    """(G,) weighted sum of ``1 - NCC`` of each group's slices at ``poses``."""
    points = projector.grid_points(poses, pixels)
    ncc = slice_ncc(projector, projector.sample(blurred, points), target, pixels)
    return _group_sums(weights * (1 - ncc.double()), groups, int(groups.max()) + 1)


def _slice_stats(projector: SliceProjector, sid: Tensor, sim: Tensor, target: Tensor) -> Tensor:
    """(N, 5) per-slice sums of 1, s, y, s^2 and s y."""
    values = torch.stack([torch.ones_like(sim), sim, target, sim * sim, sim * target], dim=1)
    return values.new_zeros(projector.num_slices, 5).index_add(0, sid, values)


# Stack-to-template registration: coarser and longer than a slice's.
STACK_REGISTRATION = RegistrationConfig(levels=3, iterations=10)


def _sda(slices: SliceSet, grid: VolumeGrid, psf_samples: int = SVR_PSF_SAMPLES) -> Tensor:
    projector = SliceProjector(grid, slices, psf_samples=psf_samples)
    observed = projector.gather(slices.images)
    points = projector.grid_points(slices.poses)
    return scattered_data_approximation(projector, points, observed, torch.ones_like(observed))


def stack_registration(
    slices: SliceSet, grid_mm: float, template: int | None = None
) -> tuple[Tensor, int]:
    """Rigid registration of every stack to a volume estimated from the template stack.

    Args:
        slices: All slices at their starting poses.
        grid_mm: Voxel size of the template volume (mm).
        template: Template stack index, or ``None`` for the stack with the most masked pixels.

    Returns:
        (N, 4, 4) registered poses (in the template stack's frame, i.e. unchanged for the
        template's slices) and the template index.
    """
    num_stacks = len(slices.stack_names)
    if template is None:
        counts = torch.zeros(num_stacks, device=slices.device).index_add(
            0, slices.stack_ids, slices.masks.flatten(1).sum(1).float()
        )
        template = int(counts.argmax())
    if not 0 <= template < num_stacks:
        raise ValueError(
            f"stack_registration(): 'template' must be in [0, {num_stacks}), got {template}"
        )
    grid = output_grid(slices, grid_mm)
    reference = _sda(slices.subset(slices.stack_ids == template), grid)
    projector = SliceProjector(grid, slices, psf_samples=SVR_PSF_SAMPLES)
    fixed = torch.zeros(num_stacks, dtype=torch.bool)
    fixed[template] = True
    poses = register_rigid(
        projector,
        reference,
        slices.images,
        slices.poses,
        slices.stack_ids,
        STACK_REGISTRATION,
        fixed=fixed,
    )
    return poses, template


def slice_agreement(
    slices: SliceSet, grid_mm: float, leave_out: bool = False, at: Tensor | None = None
) -> Tensor:
    """(N,) each slice's NCC with its simulation from a volume of the slices.

    The volume is the scattered-data approximation of the slices on a grid of ``grid_mm``. With
    ``leave_out`` (and at least two stacks), each stack's slices are simulated from the volume of
    the *other* stacks' slices only, so that a stack cannot agree with itself: a stack whose
    packets are placed apart, one of them the wrong twin, fits its own volume better the more
    freely it is placed, but fits the other stacks only where it is right.

    Args:
        slices: The slices at the poses the volume is made from.
        grid_mm: The grid spacing (mm).
        leave_out: Score each stack against the other stacks only.
        at: (N, 4, 4) other poses to score the slices at (slice array -> ``slices``' frame),
            the volume still made from ``slices`` at their own: how well a moved slice agrees
            with the other stacks as they are. Default: the slices' own poses.

    Returns:
        (N,) float32 slice NCC (0 for a slice with no modelled pixels).

    Raises:
        ValueError: If ``at`` is not (N, 4, 4).
    """
    return SliceAgreement(slices, grid_mm, leave_out)(at)


class SliceAgreement:
    """The volumes of :func:`slice_agreement`, made once, to score the slices at several poses.

    Args:
        slices: The slices at the poses the volumes are made from.
        grid_mm: The grid spacing (mm).
        leave_out: Score each stack against the other stacks only.
    """

    def __init__(self, slices: SliceSet, grid_mm: float, leave_out: bool = False) -> None:
        self.slices = slices
        grid = output_grid(slices, grid_mm)
        num_stacks = len(slices.stack_names)
        leave = leave_out and num_stacks > 1
        # Each stack's SDA sums once: the volume of all stacks is the ratio of their totals, the
        # volume without stack s that of the totals less s's, so leaving every stack out in turn
        # still costs one pass over the pixels.
        parts: dict[int, tuple[SliceProjector, Tensor, Tensor, Tensor, Tensor]] = {}
        for sid in range(num_stacks):
            mine = slices.subset(slices.stack_ids == sid)
            if len(mine) == 0:
                continue
            projector = SliceProjector(grid, mine, psf_samples=SVR_PSF_SAMPLES)
            observed = projector.gather(mine.images)
            points = projector.grid_points(mine.poses)
            covered = coverage(projector, points, torch.ones_like(observed))
            numerator = projector.adjoint(observed, points)
            parts[sid] = (projector, observed, points, numerator, covered)
        # Per stack: its projector, its pixels, their points at the slices' poses, its volume.
        self._stacks: dict[int, tuple[SliceProjector, Tensor, Tensor, Tensor]] = {}
        if not parts:
            return
        total_numerator = torch.stack([part[3] for part in parts.values()]).sum(0)
        total_coverage = torch.stack([part[4] for part in parts.values()]).sum(0)
        for sid, (projector, observed, points, numerator, covered) in parts.items():
            if leave:
                volume = sda_ratio(total_numerator - numerator, total_coverage - covered)
            else:
                volume = sda_ratio(total_numerator, total_coverage)
            self._stacks[sid] = (projector, observed, points, volume)

    def __call__(self, at: Tensor | None = None) -> Tensor:
        """(N,) float32 each slice's NCC at ``at`` (default its own pose).

        Args:
            at: (N, 4, 4) poses to score the slices at (:func:`slice_agreement`), or ``None``.

        Returns:
            (N,) float32 slice NCC (0 for a slice with no modelled pixels).

        Raises:
            ValueError: If ``at`` is not (N, 4, 4).
        """
        slices = self.slices
        if at is not None and tuple(at.shape) != (len(slices), 4, 4):
            raise ValueError(
                f"slice_agreement(): 'at' must be ({len(slices)}, 4, 4), got {tuple(at.shape)}"
            )
        out = torch.zeros(len(slices), dtype=torch.float32, device=slices.images.device)
        for sid, (projector, observed, points, volume) in self._stacks.items():
            if at is not None:
                points = projector.grid_points(at[slices.stack_ids == sid].to(slices.poses))
            ncc = slice_ncc(projector, projector.forward(volume, points), observed)
            out[slices.stack_ids == sid] = ncc.to(out)
        return out


def stack_ncc(slices: SliceSet, grid_mm: float, leave_out: bool = False) -> Tensor:
    """(S,) mean NCC of each stack's slices with their simulation from a volume of the slices.

    The mean over each stack of :func:`slice_agreement` (``leave_out``: against the *other*
    stacks' volume only).

    Args:
        slices: The slices at the poses to score.
        grid_mm: The grid spacing (mm).
        leave_out: Score each stack against the other stacks only.

    Returns:
        (S,) mean slice NCC per stack (0 for a stack without slices).
    """
    ncc = slice_agreement(slices, grid_mm, leave_out)
    num_stacks = len(slices.stack_names)
    out = torch.zeros(num_stacks, dtype=torch.float32, device=slices.images.device)
    for sid in range(num_stacks):
        mine = slices.stack_ids == sid
        if bool(mine.any()):
            out[sid] = ncc[mine].mean()
    return out
