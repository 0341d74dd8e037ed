"""The steps of a reconstruction round, each public for scripts that need one on its own.

:func:`initial_volume` (the first estimate), :func:`svr_pass` (slice-to-volume registration),
:func:`reject_outliers` (intensity
scales, EM weights, NCC exclusion), :func:`super_resolve` and :func:`finalise` (the coverage mask
and final NCCs). Every step takes the acquisition model
(:func:`svr.reconstruction.acquisition.acquisition_model`) and the current volume and poses; the
schedules that chain them are :mod:`svr.reconstruction.schedule`.
"""

from __future__ import annotations

from typing import NamedTuple, TypeVar

import torch
from torch import Tensor

from svr.geometry.averaging import robust_mean_pose
from svr.reconstruction.acquisition import Acquisition, slice_groups
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
    "FinalVolume",
    "OutlierWeights",
    "anchored",
    "finalise",
    "initial_volume",
    "per_round",
    "reject_outliers",
    "super_resolve",
    "svr_pass",
    "volume_without",
]

_T = TypeVar("_T")


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
