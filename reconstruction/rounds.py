"""The steps of a reconstruction round, each public for scripts that need one on its own.

:func:`initial_volume` (the first estimate), :func:`svr_pass` (slice-to-volume registration),
:func:`recapture` (a wider search for slices that fit badly), :func:`reject_outliers` (intensity
scales, EM weights, NCC exclusion), :func:`super_resolve` and :func:`finalise` (the coverage mask
and final NCCs). Every step takes the acquisition model
(:func:`svr.reconstruction.acquisition.acquisition_model`) and the current volume and poses; the
schedules that chain them are :mod:`svr.reconstruction.schedule`.
"""

from __future__ import annotations

from typing import NamedTuple, TypeVar

import torch
from torch import Tensor

from svr.geometry import so3_exp
from svr.geometry.averaging import robust_mean_pose
from svr.reconstruction.acquisition import Acquisition, packet_neighbours, slice_groups
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.operators import SliceProjector
from svr.reconstruction.registration import (
    SVR_PSF_SAMPLES,
    RegistrationConfig,
    register_rigid,
    slice_ncc,
)
from svr.reconstruction.robust import robust_weights
from svr.reconstruction.superres import (
    Background,
    coverage,
    scattered_data_approximation,
    slice_intensity_scales,
    super_resolution,
)

__all__ = [
    "RECAPTURE_MARGIN",
    "FinalVolume",
    "OutlierWeights",
    "anchored",
    "coarse_turns",
    "finalise",
    "initial_volume",
    "per_round",
    "recapture",
    "reject_outliers",
    "super_resolve",
    "svr_pass",
    "volume_without",
]

_T = TypeVar("_T")

# recapture(): the NCC a wider search must gain over the current pose.
RECAPTURE_MARGIN = 0.01

# recapture(): the coarse search's turns of the head (degrees), each about 13 axes both ways, and
# how many of its best-fitting turns per slice go on to registration.
COARSE_TURNS_DEG = (30.0, 60.0)
COARSE_KEPT = 2


def _axes() -> Tensor:
    """(26, 3) unit axes: the 13 axes of a cube (faces, edges, corners), both ways."""
    ones = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1)]
    ones += [(0, 1, 1), (0, 1, -1), (1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1)]
    axes = torch.tensor(ones, dtype=torch.float64)
    axes = axes / axes.norm(dim=1, keepdim=True)
    return torch.cat([axes, -axes])


def coarse_turns(poses: Tensor, centre: Tensor, turns_deg: tuple[float, ...]) -> Tensor:
    """(N, T, 4, 4) each pose with the head turned about ``centre`` by each coarse rotation.

    Args:
        poses: (N, 4, 4) slice poses (slice-plane mm -> frame mm).
        centre: (3,) the centre of the head's turns, frame mm (e.g. the brain's centre).
        turns_deg: Rotation angles (degrees), each about 26 directions (:func:`_axes`).

    Returns:
        (N, 26 x len(turns_deg), 4, 4) float64 ``G_t @ P_n`` with ``G_t`` the rotation about
        ``centre``.
    """
    angles = torch.deg2rad(torch.tensor(turns_deg, dtype=torch.float64))
    vectors = torch.cat([_axes() * angle for angle in angles])
    turn = torch.eye(4, dtype=torch.float64).repeat(len(vectors), 1, 1)
    rotation = so3_exp(vectors)
    c = centre.to(torch.float64).cpu()
    turn[:, :3, :3] = rotation
    turn[:, :3, 3] = c - rotation @ c
    return turn.to(poses.device)[None] @ poses.to(torch.float64)[:, None]


def per_round(values: tuple[_T, ...], round_index: int) -> _T:
    """The value for round ``round_index``; the last one repeats."""
    return values[min(round_index, len(values) - 1)]


def initial_volume(acquisition: Acquisition, points: Tensor) -> Tensor:
    """The first volume estimate: the scattered-data approximation with unit pixel weights.

    Args:
        acquisition: The acquisition model.
        points: (K, P, 3) grid points of the slices' poses (:meth:`Acquisition.points`).

    Returns:
        (I, J, K) volume on ``acquisition.grid``, 0 where no data reaches.
    """
    observed = acquisition.observed
    return scattered_data_approximation(
        acquisition.projector, points, observed, torch.ones_like(observed)
    )


def volume_without(acquisition: Acquisition, points: Tensor, left_out: Tensor) -> Tensor:
    """The scattered-data volume of every slice but ``left_out``: a reference they did not shape.

    A slice registered against a volume it helped make is pulled towards where it already is;
    where a run of slices sits wrong together (a packet's end, turned with the head), the volume
    there is theirs and every search from it agrees with them. Without them, the other stacks'
    slices say what is there.

    Args:
        acquisition: The acquisition model.
        points: (K, P, 3) grid points of the slices' current poses.
        left_out: (N,) bool, the slices to leave out.

    Returns:
        (I, J, K) volume on ``acquisition.grid``, 0 where no kept slice reaches.
    """
    projector = acquisition.projector
    weights = (~left_out.to(projector.slice_of.device))[projector.slice_of].to(points.dtype)
    observed = acquisition.observed
    return scattered_data_approximation(projector, points, observed, weights.to(observed))


def svr_pass(
    acquisition: Acquisition,
    volume: Tensor,
    poses: Tensor,
    config: ReconstructionConfig,
    group_size: int = 1,
    slice_weights: Tensor | None = None,
    anchor: bool = True,
    active: Tensor | None = None,
) -> Tensor:
    """One slice-to-volume registration pass: every group of slices rigidly aligned to ``volume``.

    Groups are ``group_size`` slices acquired one after another
    (:func:`~svr.reconstruction.acquisition.slice_groups` with ``config.packets``); with
    ``group_size = 1`` every slice is registered alone and slices with fewer than
    ``config.schedule.min_slice_pixels`` brain pixels keep their pose (too little signal). The
    registration (:func:`svr.reconstruction.registration.register_rigid`) runs the schedule's
    ``svr_levels`` levels of ``svr_iterations`` Levenberg-Marquardt steps with the
    :data:`~svr.reconstruction.registration.SVR_PSF_SAMPLES`-node PSF.

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) volume on ``acquisition.grid``.
        poses: (N, 4, 4) starting poses: slice-plane mm -> the grid's frame (mm).
        config: Settings (``packets``, ``min_slice_pixels``, ``svr_levels``, ``svr_iterations``).
        group_size: Slices per group (>= 1).
        slice_weights: (N,) weight of each slice in its group's objective (0 leaves it out), or
            ``None`` for all 1.
        anchor: Take the common rigid motion of all slices back out of the corrections, so that
            the volume stays in the frame of ``poses`` (as every round of a reconstruction
            does); ``False`` returns the registered poses as they are.
        active: (N,) bool, with ``group_size = 1``: only these slices are registered (and
            computed); the others keep their poses. ``None`` for all.

    Returns:
        (N, 4, 4) float64 registered poses in the same frame.
    """
    slices = acquisition.slices
    settings = RegistrationConfig(
        levels=config.schedule.svr_levels, iterations=config.schedule.svr_iterations
    )
    if active is not None and group_size == 1:
        if active.shape != (len(slices),):
            raise ValueError(
                f"svr_pass(): 'active' must have shape ({len(slices)},), got {tuple(active.shape)}"
            )
        active = active.to(poses.device, torch.bool)
        # Slices with little brain keep their pose: too little signal to be registered alone.
        active = active & (acquisition.brain_pixels >= config.schedule.min_slice_pixels).to(active)
        registered = poses.to(torch.float64).clone()
        if bool(active.any()):
            subset = slices.subset(active)
            registered[active] = register_rigid(
                SliceProjector(acquisition.grid, subset, psf_samples=SVR_PSF_SAMPLES),
                volume,
                subset.images,
                poses[active],
                torch.arange(len(subset), device=poses.device),
                settings,
                slice_weights=None if slice_weights is None else slice_weights[active],
            ).to(registered)
    else:
        groups = slice_groups(slices, config.packets, group_size)
        small = (
            (acquisition.brain_pixels < config.schedule.min_slice_pixels)
            if group_size == 1
            else None
        )
        registered = register_rigid(
            acquisition.svr_projector,
            volume,
            slices.images,
            poses,
            groups,
            settings,
            fixed=small,
            slice_weights=slice_weights,
        )
    return anchored(registered, poses) if anchor else registered


def recapture(
    acquisition: Acquisition,
    volume: Tensor,
    poses: Tensor,
    start_poses: Tensor,
    candidates: Tensor,
    config: ReconstructionConfig,
    trajectory: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """A wider search for slices that still fit badly: their packet neighbours' motion as starts.

    Each slice in ``candidates`` is registered alone from its current pose, from the poses its
    temporal neighbours' motion gives it (the corrections that moved the previous and next slice
    of its packet since ``start_poses``, applied to it), with ``trajectory`` from the pose
    its packet's motion trajectory gives it at its time (fitted to the other slices:
    :func:`svr.reconstruction.trajectory.fit_slice_trajectory`), and from the coarse turns of the
    head about that pose that fit it best (:func:`coarse_turns`: 30 and 60 degrees about 13 axes
    both ways, scored by NCC before any registration). It takes the result that matches
    its simulation from ``volume`` best (NCC over its brain pixels), if that beats its current
    pose by ``RECAPTURE_MARGIN``.

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) the reference to match on ``acquisition.grid``: best one the searched
            slices did not shape (:func:`volume_without`).
        poses: (N, 4, 4) current poses.
        start_poses: (N, 4, 4) the poses the rounds started from (for the neighbours' motion).
        candidates: (N,) bool, the slices to search for.
        config: Settings (``packets`` and the schedule's registration levels and steps).
        trajectory: (N, 4, 4) each slice's pose on its packet's trajectory, or ``None``.

    Returns:
        (N, 4, 4) float64 poses (changed only where a search found a better fit) and (N,) bool,
        the slices whose pose changed.
    """
    slices = acquisition.slices
    device = poses.device
    poses = poses.to(torch.float64).clone()
    changed = torch.zeros(len(slices), dtype=torch.bool, device=device)
    index = torch.nonzero(candidates.to(device)).flatten()
    if index.numel() == 0:
        return poses, changed
    starts, owners = [], []
    neighbour = packet_neighbours(slices, config.packets)
    motion = poses @ torch.linalg.inv(start_poses.to(poses))
    coarse = _coarse_starts(acquisition, volume, poses, index, trajectory)
    for n, i in enumerate(index.tolist()):
        own = [poses[i]]
        for j in neighbour[i]:
            own.append(motion[j] @ start_poses[i].to(poses))
        if trajectory is not None:
            own.append(trajectory[i].to(poses))
        own += list(coarse[n])
        starts += own
        owners += [i] * len(own)
    owner = torch.tensor(owners, device=device)
    subset = slices.subset(owner)
    projector = SliceProjector(acquisition.grid, subset, psf_samples=SVR_PSF_SAMPLES)
    settings = RegistrationConfig(
        levels=config.schedule.svr_levels, iterations=config.schedule.svr_iterations
    )
    found = register_rigid(
        projector,
        volume,
        subset.images,
        torch.stack(starts),
        torch.arange(len(owner), device=device),
        settings,
    )
    observed = projector.gather(subset.images)
    ncc = slice_ncc(projector, projector.forward(volume, projector.grid_points(found)), observed)
    current = slice_ncc(
        projector, projector.forward(volume, projector.grid_points(torch.stack(starts))), observed
    )
    for i in index.tolist():
        mine = torch.nonzero(owner == i).flatten()
        best = mine[int(ncc[mine].argmax())]
        # The current pose as it is (first start) is the bar to beat.
        if float(ncc[best]) > float(current[mine[0]]) + RECAPTURE_MARGIN:
            poses[i] = found[best]
            changed[i] = True
    return poses, changed


def _coarse_starts(
    acquisition: Acquisition,
    volume: Tensor,
    poses: Tensor,
    index: Tensor,
    trajectory: Tensor | None,
) -> Tensor:
    """(len(index), COARSE_KEPT, 4, 4) the best-fitting coarse turns of the head per slice.

    Each slice in ``index`` is simulated from ``volume`` with the head turned about the brain's
    centre (the mean of all slices' centres) by every :func:`coarse_turns` rotation of its
    trajectory pose (its current pose without one); the ``COARSE_KEPT`` turns whose simulation
    matches the slice best (NCC over its brain pixels) are returned, to be registered.
    """
    slices = acquisition.slices
    around = (trajectory if trajectory is not None else poses)[index].to(poses)
    centre = poses[:, :3, 3].mean(dim=0)
    turned = coarse_turns(around, centre, COARSE_TURNS_DEG)
    count = turned.shape[1]
    owner = index.repeat_interleave(count)
    subset = slices.subset(owner)
    projector = SliceProjector(acquisition.grid, subset, psf_samples=SVR_PSF_SAMPLES)
    flat = turned.reshape(-1, 4, 4)
    observed = projector.gather(subset.images)
    ncc = slice_ncc(projector, projector.forward(volume, projector.grid_points(flat)), observed)
    best = ncc.reshape(len(index), count).topk(min(COARSE_KEPT, count), dim=1).indices
    return torch.gather(turned, 1, best[..., None, None].expand(-1, -1, 4, 4))


class OutlierWeights(NamedTuple):
    """What :func:`reject_outliers` found, at one volume and set of poses.

    Attributes:
        scales: (N,) per-slice intensity scales ``c`` (observed ~ ``c`` x simulated), in
            [0.5, 2], fitted with the previous pixel weights.
        ncc: (N,) NCC of each observed slice with its simulation (over its masked pixels).
        excluded: (N,) bool, slices left out: NCC below ``config.outliers.ncc_threshold`` and
            at least ``config.schedule.min_slice_pixels`` brain pixels.
        pixel_weights: (P,) EM pixel inlier probabilities (the previous ones when
            ``config.outliers.robust`` is off).
        slice_weights: (N,) EM slice inlier probabilities (likewise).
        weights: (P,) the data weights of super-resolution: the pixel weight times its slice's
            weight, 0 for the pixels of excluded slices.
        background_weights: (B,) the weights of the background pixels (their posterior inlier
            probability under the pixels' residual model times their slice's weight, 0 for
            excluded slices), or ``None`` when none were weighted.
    """

    scales: Tensor
    ncc: Tensor
    excluded: Tensor
    pixel_weights: Tensor
    slice_weights: Tensor
    weights: Tensor
    background_weights: Tensor | None = None


def reject_outliers(
    acquisition: Acquisition,
    volume: Tensor,
    points: Tensor,
    config: ReconstructionConfig,
    pixel_weights: Tensor | None = None,
    slice_weights: Tensor | None = None,
    background_points: Tensor | None = None,
) -> OutlierWeights:
    """Per-slice intensity scales, EM outlier weights and NCC exclusion at the current volume.

    Slices are simulated from ``volume`` at ``points``; the per-slice scales are fitted with the
    previous ``pixel_weights``; slices whose NCC with their simulation is below
    ``config.outliers.ncc_threshold`` are excluded unless they have fewer than
    ``config.schedule.min_slice_pixels`` brain pixels (their NCC is noise: they rely on the EM
    weights alone); with ``config.outliers.robust`` the EM pixel and slice weights are recomputed
    from the scaled residuals (:func:`svr.reconstruction.robust.robust_weights`). Background
    pixels, when given, are weighted by their posterior inlier probability under the same
    residual model (their residual is ``0 - c A x``): where other slices put brain, a misplaced
    slice's background is an outlier and does not carve the brain.

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) volume on ``acquisition.grid``.
        points: (K, P, 3) grid points of the current poses (:meth:`Acquisition.points`).
        config: Settings (``ncc_threshold``, ``min_slice_pixels``, ``robust``).
        pixel_weights: (P,) previous pixel weights, or ``None`` for all 1 (the first round).
        slice_weights: (N,) previous slice weights, or ``None`` for all 1 (the first round).
        background_points: (K, B, 3) grid points of the background pixels
            (:meth:`Acquisition.background_points`), or ``None`` to weight none.

    Returns:
        The scales, NCCs, exclusions and weights.
    """
    projector, observed = acquisition.projector, acquisition.observed
    num_slices = len(acquisition.slices)
    if pixel_weights is None:
        pixel_weights = torch.ones_like(observed)
    if slice_weights is None:
        slice_weights = torch.ones(num_slices, device=observed.device)
    simulated = projector.forward(volume, points)
    scales = slice_intensity_scales(projector, simulated, observed, pixel_weights)
    ncc = slice_ncc(projector, simulated, observed)
    # NCC of slices with little brain is noise: those rely on the EM weights alone.
    excluded = (ncc < config.outliers.ncc_threshold) & (
        acquisition.brain_pixels >= config.schedule.min_slice_pixels
    )
    robust = None
    if config.outliers.robust:
        robust = robust_weights(
            observed - scales[projector.slice_of] * simulated, projector.slice_of, num_slices
        )
        pixel_weights, slice_weights = robust.pixel, robust.slice
    kept = slice_weights * (~excluded)
    weights = pixel_weights * kept[projector.slice_of]
    background = None
    if acquisition.background is not None and background_points is not None:
        b_of = acquisition.background.slice_of
        background = kept[b_of]
        if robust is not None:
            b_simulated = acquisition.background.forward(volume, background_points)
            background = background * robust.pixel_posterior(-scales[b_of] * b_simulated)
    return OutlierWeights(scales, ncc, excluded, pixel_weights, slice_weights, weights, background)


def super_resolve(
    acquisition: Acquisition,
    volume: Tensor,
    points: Tensor,
    outliers: OutlierWeights,
    config: ReconstructionConfig,
    round_index: int,
    background_points: Tensor | None = None,
    settings: tuple[float, int] | None = None,
) -> Tensor:
    """Conjugate-gradient super-resolution from ``volume``, as round ``round_index`` does it.

    Round ``round_index`` (from 0) uses that round's ``config.superres.iterations`` and
    ``regularization`` (the last value repeats) and ``config.superres.edge_delta``
    (:func:`svr.reconstruction.superres.super_resolution`).

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) starting volume on ``acquisition.grid``.
        points: (K, P, 3) grid points of the current poses (:meth:`Acquisition.points`).
        outliers: The data weights and per-slice scales (:func:`reject_outliers`).
        config: Settings.
        round_index: The round (>= 0).
        background_points: (K, B, 3) grid points of the background pixels: with the weights
            ``outliers.background_weights`` they join the data term as observed background
            (:class:`svr.reconstruction.superres.Background`); ``None`` for none.
        settings: ``(regularization, CG iterations)`` instead of the round's from ``config``.

    Returns:
        (I, J, K) non-negative volume on ``acquisition.grid``.
    """
    background = None
    if (
        acquisition.background is not None
        and background_points is not None
        and outliers.background_weights is not None
    ):
        background = Background(
            acquisition.background, background_points, outliers.background_weights
        )
    if settings is None:
        settings = (
            per_round(config.superres.regularization, round_index),
            per_round(config.superres.iterations, round_index),
        )
    return super_resolution(
        acquisition.projector,
        points,
        acquisition.observed,
        outliers.weights,
        outliers.scales,
        volume,
        settings[1],
        settings[0],
        config.superres.edge_delta,
        background,
    )


class FinalVolume(NamedTuple):
    """What :func:`finalise` returns.

    Attributes:
        volume: (I, J, K) volume, 0 outside ``mask``.
        mask: (I, J, K) float 0/1, the voxels the slices cover.
        slice_ncc: (N,) NCC of each observed slice with its scaled simulation from the volume
            (before masking).
    """

    volume: Tensor
    mask: Tensor
    slice_ncc: Tensor


def finalise(
    acquisition: Acquisition, volume: Tensor, points: Tensor, pixel_weights: Tensor
) -> FinalVolume:
    """The final slice NCCs and the coverage mask, applied to the volume.

    The mask keeps the voxels whose coverage ``A^T 1`` exceeds 5% of its 99th percentile over
    the covered voxels.

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) volume on ``acquisition.grid``.
        points: (K, P, 3) grid points of the final poses (:meth:`Acquisition.points`).
        pixel_weights: (P,) pixel weights of the last round, for the intensity scales.

    Returns:
        The masked volume, the mask and the slices' NCCs.
    """
    projector, observed = acquisition.projector, acquisition.observed
    simulated = projector.forward(volume, points)
    scales = slice_intensity_scales(projector, simulated, observed, pixel_weights)
    ncc = slice_ncc(projector, scales[projector.slice_of] * simulated, observed)
    cover = coverage(projector, points, torch.ones_like(observed))
    # kthvalue, not torch.quantile: no limit on the number of voxels (NeSVoR #21).
    covered = cover[cover > 0].float()
    high = covered.kthvalue(max(1, int(0.99 * covered.numel()))).values
    mask = (cover > 0.05 * float(high)).float()
    return FinalVolume(volume * mask, mask, ncc)


def anchored(poses: Tensor, previous: Tensor) -> Tensor:
    """Remove the common rigid motion of all slices from a registration's corrections.

    Slice-to-volume registration can move every slice (and with them the volume) together; the
    robust mean of the per-slice corrections ``poses_i o previous_i^-1`` is taken back out so the
    volume stays in the frame of the initialisation (the template stack, or canonical space).
    """
    drift = robust_mean_pose(poses @ torch.linalg.inv(previous))
    return torch.linalg.inv(drift).to(poses) @ poses
