"""The reconstruction pipeline: slices -> initial poses -> (SVR, super-resolution) rounds.

Phases (each timed and logged):
    1. slices: every stack cut into slices, each its own rigid body (:func:`extract_slices`);
    2. initialisation: ``"none"`` keeps the scanner poses; ``"stack"`` registers every stack
       rigidly to a volume estimated from the template stack; ``"cnn"`` predicts every slice's
       canonical pose, replaces predictions that disagree with their stack's robust consensus
       by the consensus pose, and keeps per stack whichever of these poses and the stack
       registration (mapped to canonical space) makes the simulated slices match the observed
       ones better by NCC, as NeSVoR does
       (:func:`svr.reconstruction.cnn_init.learned_initialisation`; stack registration is
       :func:`svr.reconstruction.registration.stack_registration`);
    3. rounds: slice-to-volume registration of every slice (skipped in the first round),
       per-slice intensity scales, EM outlier weights, exclusion of slices whose NCC with their
       simulation is below the threshold, then conjugate-gradient super-resolution.

Each step of a round is public, for scripts that need one of them on their own volume and poses:
:func:`acquisition_model` (the setup), :func:`initial_volume`, :func:`svr_pass`,
:func:`reject_outliers`, :func:`super_resolve` and :func:`finalise`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import NamedTuple, TypeVar

import torch
from torch import Tensor
from tqdm import tqdm

from svr.geometry import so3_exp
from svr.geometry.averaging import robust_mean_pose
from svr.models.network import SlicePoseNet
from svr.models.stack_pose import StackPoseNet
from svr.reconstruction.atlas_frame import align_to_atlas
from svr.reconstruction.cnn_init import (
    cnn_slice_poses,
    learned_initialisation,
    stack_pose_initialisation,
)
from svr.reconstruction.config import REGISTRATIONS, ReconstructionConfig, ReconstructionResult
from svr.reconstruction.convergence import RoundRecord, pose_change, round_summary
from svr.reconstruction.operators import SliceProjector, VolumeGrid
from svr.reconstruction.registration import (
    SVR_PSF_SAMPLES,
    RegistrationConfig,
    register_rigid,
    slice_ncc,
    stack_registration,
)
from svr.reconstruction.robust import robust_weights
from svr.reconstruction.slices import SliceSet, Stack, extract_slices
from svr.reconstruction.superres import (
    Background,
    coverage,
    output_grid,
    scattered_data_approximation,
    slice_intensity_scales,
    super_resolution,
)
from svr.sampling.volume import CanonicalVolume

__all__ = [
    "Acquisition",
    "FinalVolume",
    "OutlierWeights",
    "acquisition_model",
    "finalise",
    "initial_volume",
    "learned_initialisation",
    "reconstruct",
    "reject_outliers",
    "stack_registration",
    "super_resolve",
    "svr_pass",
]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

# Background pixels are taken on a lattice of this step (pixels) in each slice.
BACKGROUND_STRIDE = 2
# recapture(): the NCC a wider search must gain over the current pose.
RECAPTURE_MARGIN = 0.01
# The adaptive schedule lets a slice sit out one round once it has moved less than half the
# convergence thresholds in this many registered one-by-one rounds in a row.
QUIET_ROUNDS = 2


class _Timer:
    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        yield
        elapsed = time.perf_counter() - start
        self.timings[name] = self.timings.get(name, 0.0) + elapsed
        log.info("%s: %.1f s", name, elapsed)


def slice_groups(slices: SliceSet, packets: int, size: int) -> Tensor:
    """Groups of up to ``size`` slices acquired one after another, for hierarchical SVR.

    With ``packets`` interleaved packets per stack (slices ``k = p, p + packets, p + 2 packets,
    ...`` acquired in turn), slices of one packet that are neighbours in that order are
    neighbours in time, so under smooth fetal motion they moved alike. ``size = 1`` gives one
    group per slice.

    Args:
        slices: The slices.
        packets: Interleaved packets per stack (>= 1; 1 for sequential acquisition).
        size: Slices per group (>= 1).

    Returns:
        (N,) int64 group ids, consecutive from 0.
    """
    if size <= 1:
        return torch.arange(len(slices), device=slices.device)
    k = slices.slice_indices
    key = _packet_key(slices, packets) * (int(k.max()) + 1) + (k // packets) // size
    return torch.unique(key, return_inverse=True)[1]


def _packet_key(slices: SliceSet, packets: int) -> Tensor:
    """(N,) int64 the same for slices of one interleaved packet of one stack."""
    return slices.stack_ids * packets + slices.slice_indices % packets


def _group_size(config: ReconstructionConfig, round_index: int) -> int:
    sizes = config.group_sizes
    return sizes[round_index - 1] if round_index - 1 < len(sizes) else 1


def _per_round(values: tuple[_T, ...], round_index: int) -> _T:
    """The value for round ``round_index``; the last one repeats."""
    return values[min(round_index, len(values) - 1)]


def reconstruct(
    stacks: list[Stack],
    config: ReconstructionConfig | None = None,
    model: SlicePoseNet | StackPoseNet | None = None,
    initial_poses: Tensor | None = None,
    frame: str = "scanner",
    initialisation: tuple[str, ...] | None = None,
    device: str | torch.device = "cpu",
    progress: bool = True,
    atlas: CanonicalVolume | Sequence[CanonicalVolume] | None = None,
) -> ReconstructionResult:
    """Reconstruct a volume from prepared stacks.

    Args:
        stacks: The stacks (:func:`svr.reconstruction.stacks.load_stacks`).
        config: Settings.
        model: For ``registration="cnn"``: a stack-pose network
            (:func:`svr.models.stack_pose.load_stack_pose_model`; every stack placed from its own
            data, :func:`svr.reconstruction.cnn_init.stack_pose_initialisation`) or a slice-pose
            network with its configuration ``model.config``
            (:func:`svr.models.predict.load_pose_model`; per-slice predictions made rigid per
            stack, :func:`svr.reconstruction.cnn_init.learned_initialisation`).
        initial_poses: (N, 4, 4) starting poses of :func:`extract_slices`'s slices in ``frame``;
            when given, ``config.registration`` is not run.
        frame: The frame of ``initial_poses``.
        initialisation: Per stack, how ``initial_poses`` were obtained (for the report).
        device: Where to compute.
        progress: Show a progress bar.
        atlas: For ``registration="cnn"``: a brain of about the fetus's age in canonical space,
            or several, the preferred first (for example the fetus's age, then the weeks either
            side). The final volume is brought into the first's frame unless another fits it
            clearly better
            (:func:`svr.reconstruction.atlas_frame.align_to_atlas`); without a stack-pose model,
            each stack's pose hypotheses are also chosen by agreement with it and fitted to it.

    Returns:
        The result: volume in the canonical frame for ``"cnn"``, in ``frame`` for given poses,
        in the scanner frame otherwise.

    Raises:
        ValueError: If ``registration="cnn"`` comes without a model, or the registration is
            unknown.
    """
    config = config or ReconstructionConfig()
    timer = _Timer()
    notes: tuple[str, ...] = ()
    with timer.phase("slices"):
        slices = extract_slices(stacks).to(device)
        log.info("%d slices from %d stacks", len(slices), len(stacks))
    with timer.phase("initialisation"):
        if initial_poses is not None:
            slices = slices.with_poses(initial_poses.to(device), frame)
            init = initialisation or ("given",) * len(stacks)
        elif config.registration == "stack":
            poses, template = stack_registration(
                slices, config.output_resolution_mm, config.template
            )
            log.info("stack registration to template stack %d", template)
            slices = slices.with_poses(poses)
            init = ("stack",) * len(stacks)
        elif config.registration == "none":
            init = ("none",) * len(stacks)
        elif config.registration == "cnn" and (
            isinstance(model, StackPoseNet) or (model is None and atlas is not None)
        ):
            slices, init, notes = stack_pose_initialisation(
                slices,
                stacks,
                model if isinstance(model, StackPoseNet) else None,
                config,
                atlas,
            )
        elif config.registration == "cnn":
            if not isinstance(model, SlicePoseNet):
                raise ValueError("reconstruct(): registration 'cnn' needs a model or an atlas")
            learned = cnn_slice_poses(
                model,
                stacks,
                slices,
                max_rotation_deg=config.cnn_max_deviation_deg,
                max_translation_mm=config.cnn_max_deviation_mm,
            )
            slices, init, notes = learned_initialisation(slices, learned, config)
        else:
            raise ValueError(
                f"reconstruct(): 'registration' must be one of {REGISTRATIONS}, "
                f"got {config.registration!r}"
            )
    result = _rounds(slices, config, init, timer, progress)
    if notes:
        result = dataclasses.replace(result, initialisation_notes=notes)
    if atlas is not None and config.registration == "cnn":
        with timer.phase("atlas frame"):
            result = align_to_atlas(result, atlas)
    return result


class Acquisition(NamedTuple):
    """The slices' acquisition model on a volume grid: what every step of a round shares.

    Built once per reconstruction by :func:`acquisition_model`. The slices' poses are not part of
    it: every step takes the current poses (or their grid points) as an argument.

    Attributes:
        slices: The slices (images, masks, spacing and thickness).
        grid: The volume grid; its affine maps voxel indices to the frame of the poses (mm).
        projector: The acquisition model with the default PSF (5 Gauss-Hermite nodes along the
            normal), for simulation, outlier rejection and super-resolution.
        svr_projector: The same with :data:`SVR_PSF_SAMPLES` nodes, for slice-to-volume
            registration.
        observed: (P,) observed values of the P modelled (masked) pixels, in ``projector``'s
            pixel order.
        brain_pixels: (N,) int64 number of masked pixels of each slice.
        background: The acquisition model of the background pixels
            (:func:`background_pixels`), or ``None`` for none.
    """

    slices: SliceSet
    grid: VolumeGrid
    projector: SliceProjector
    svr_projector: SliceProjector
    observed: Tensor
    brain_pixels: Tensor
    background: SliceProjector | None = None

    def points(self, poses: Tensor) -> Tensor:
        """(K, P, 3) float32 ``grid_sample`` coordinates of every PSF node of every modelled pixel.

        Args:
            poses: (N, 4, 4) slice poses: slice-plane mm -> the grid's frame (mm).
        """
        return self.projector.grid_points(poses)

    def background_points(self, poses: Tensor) -> Tensor | None:
        """(K, B, 3) grid coordinates of the background pixels, or ``None`` without them.

        Args:
            poses: (N, 4, 4) slice poses: slice-plane mm -> the grid's frame (mm).
        """
        return None if self.background is None else self.background.grid_points(poses)


def background_pixels(
    slices: SliceSet, inner_mm: float, outer_mm: float, stride: int = 1
) -> Tensor:
    """The pixels between ``inner_mm`` and ``outer_mm`` from each slice's mask, in its plane.

    A brain mask cuts the slice where the (blurred) brain fades out; the pixels just outside it
    still hold some brain (partial volume), those a little farther out hold none. The distance is
    the chessboard distance in pixels of the slices' smallest in-plane spacing.

    Args:
        slices: The slices.
        inner_mm: Pixels nearer to the mask than this are left out (mm, >= 0).
        outer_mm: Pixels up to this distance are kept (mm, >= ``inner_mm``).
        stride: Keep only the pixels whose array indices are both multiples of this (>= 1): the
            background is smooth, so a sparser band says as much for less work.

    Returns:
        (N, H, W) bool, none of them inside a mask; all false for ``outer_mm = 0``.
    """
    if stride < 1:
        raise ValueError(f"background_pixels(): 'stride' must be >= 1, got {stride}")
    if not 0 <= inner_mm <= outer_mm:
        raise ValueError(
            "background_pixels(): need 0 <= 'inner_mm' <= 'outer_mm', got "
            f"{inner_mm} and {outer_mm}"
        )
    pixel = float(slices.spacing_mm.min())

    def grown(mm: float) -> Tensor:
        width = round(mm / pixel)
        if width <= 0:
            return slices.masks
        return (
            torch.nn.functional.max_pool2d(
                slices.masks[:, None].float(), 2 * width + 1, stride=1, padding=width
            )[:, 0]
            > 0.5
        )

    band = grown(outer_mm) & ~grown(inner_mm)
    if stride > 1:
        lattice = torch.zeros_like(band[0])
        lattice[::stride, ::stride] = True
        band = band & lattice
    return band


def acquisition_model(
    slices: SliceSet, grid: VolumeGrid, background_mm: tuple[float, float] = (0.0, 0.0)
) -> Acquisition:
    """The acquisition model of ``slices`` on ``grid`` (the setup of :func:`reconstruct`'s rounds).

    Args:
        slices: The slices; their poses' frame must be ``grid``'s frame.
        grid: The volume grid (:func:`svr.reconstruction.superres.output_grid` in
            :func:`reconstruct`).
        background_mm: ``(inner, outer)`` band of background pixels around the masks
            (:func:`background_pixels`); ``(0, 0)`` for none.

    Returns:
        The projectors, the observed pixel values and the slices' brain pixel counts.
    """
    projector = SliceProjector(grid, slices)
    band = background_pixels(slices, *background_mm, stride=BACKGROUND_STRIDE)
    return Acquisition(
        slices=slices,
        grid=grid,
        projector=projector,
        svr_projector=SliceProjector(grid, slices, psf_samples=SVR_PSF_SAMPLES),
        observed=projector.gather(slices.images),
        brain_pixels=slices.masks.flatten(1).sum(1),
        background=SliceProjector(grid, slices, pixels=band) if bool(band.any()) else None,
    )


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

    Groups are ``group_size`` slices acquired one after another (:func:`slice_groups` with
    ``config.packets``); with ``group_size = 1`` every slice is registered alone and slices with
    fewer than ``config.min_slice_pixels`` brain pixels keep their pose (too little signal). The
    registration (:func:`svr.reconstruction.registration.register_rigid`) runs
    ``config.svr_levels`` levels of ``config.svr_iterations`` Levenberg-Marquardt steps with the
    :data:`SVR_PSF_SAMPLES`-node PSF.

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) volume on ``acquisition.grid``.
        poses: (N, 4, 4) starting poses: slice-plane mm -> the grid's frame (mm).
        config: Settings (``packets``, ``min_slice_pixels``, ``svr_levels``, ``svr_iterations``).
        group_size: Slices per group (>= 1).
        slice_weights: (N,) weight of each slice in its group's objective (0 leaves it out), or
            ``None`` for all 1.
        anchor: Take the common rigid motion of all slices back out of the corrections, so that
            the volume stays in the frame of ``poses`` (as every round of :func:`reconstruct`
            does); ``False`` returns the registered poses as they are.
        active: (N,) bool, with ``group_size = 1``: only these slices are registered (and
            computed); the others keep their poses. ``None`` for all.

    Returns:
        (N, 4, 4) float64 registered poses in the same frame.
    """
    slices = acquisition.slices
    settings = RegistrationConfig(levels=config.svr_levels, iterations=config.svr_iterations)
    if active is not None and group_size == 1:
        if active.shape != (len(slices),):
            raise ValueError(
                f"svr_pass(): 'active' must have shape ({len(slices)},), got {tuple(active.shape)}"
            )
        active = active.to(poses.device, torch.bool)
        # Slices with little brain keep their pose: too little signal to be registered alone.
        active = active & (acquisition.brain_pixels >= config.min_slice_pixels).to(active)
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
        small = (acquisition.brain_pixels < config.min_slice_pixels) if group_size == 1 else None
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
    return _anchored(registered, poses) if anchor else registered


def recapture(
    acquisition: Acquisition,
    volume: Tensor,
    poses: Tensor,
    start_poses: Tensor,
    candidates: Tensor,
    config: ReconstructionConfig,
    turn_rad: float | None = None,
    extra_levels: int = 0,
) -> tuple[Tensor, Tensor]:
    """A wider search for slices that still fit badly: their packet neighbours' motion as starts.

    Each slice in ``candidates`` is registered alone from its current pose and from the poses its
    temporal neighbours' motion gives it (the corrections that moved the previous and next slice
    of its packet since ``start_poses``, applied to it); with ``turn_rad``, also from its current
    pose turned by ``+-turn_rad`` about each of its own axes; with ``extra_levels``, with that
    many more coarse levels (each at twice the previous blur). It takes the result that matches
    its simulation from ``volume`` best (NCC over its brain pixels), if that beats its current
    pose by ``RECAPTURE_MARGIN``. On sb24-large the neighbours' starts shortened the tail of
    pose errors most for the least time; turns and an extra level added time and nothing
    measurable (``benchmarks/results/reconstruction-convergence.md``).

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) volume on ``acquisition.grid``.
        poses: (N, 4, 4) current poses.
        start_poses: (N, 4, 4) the poses the rounds started from (for the neighbours' motion).
        candidates: (N,) bool, the slices to search for.
        config: Settings (``packets``, ``svr_levels``, ``svr_iterations``).
        turn_rad: The turn of the rotated starts (radians), or ``None`` for none.
        extra_levels: Coarse levels added to ``config.svr_levels`` (>= 0).

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
    neighbour = _packet_neighbours(slices, config.packets)
    motion = poses @ torch.linalg.inv(start_poses.to(poses))
    turns = []
    if turn_rad is not None:
        axes = torch.eye(3, dtype=torch.float64, device=device)
        turns = [so3_exp(sign * turn_rad * axis) for axis in axes for sign in (1, -1)]
    for i in index.tolist():
        own = [poses[i]]
        for j in neighbour[i]:
            own.append(motion[j] @ start_poses[i].to(poses))
        for turn in turns:
            turned = poses[i].clone()
            turned[:3, :3] = poses[i, :3, :3] @ turn
            own.append(turned)
        starts += own
        owners += [i] * len(own)
    owner = torch.tensor(owners, device=device)
    subset = slices.subset(owner)
    projector = SliceProjector(acquisition.grid, subset, psf_samples=SVR_PSF_SAMPLES)
    settings = RegistrationConfig(
        levels=config.svr_levels + extra_levels, iterations=config.svr_iterations
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


def _packet_neighbours(slices: SliceSet, packets: int) -> list[list[int]]:
    """Per slice, the slices acquired just before and after it in its stack's packet."""
    key = _packet_key(slices, packets)
    order = torch.argsort(key * (int(slices.slice_indices.max()) + 1) + slices.slice_indices)
    out: list[list[int]] = [[] for _ in range(len(slices))]
    sorted_key = key[order].tolist()
    ranked = order.tolist()
    for a in range(len(ranked)):
        for b in (a - 1, a + 1):
            if 0 <= b < len(ranked) and sorted_key[b] == sorted_key[a]:
                out[ranked[a]].append(ranked[b])
    return out


class OutlierWeights(NamedTuple):
    """What :func:`reject_outliers` found, at one volume and set of poses.

    Attributes:
        scales: (N,) per-slice intensity scales ``c`` (observed ~ ``c`` x simulated), in
            [0.5, 2], fitted with the previous pixel weights.
        ncc: (N,) NCC of each observed slice with its simulation (over its masked pixels).
        excluded: (N,) bool, slices left out: NCC below ``config.ncc_threshold`` and at least
            ``config.min_slice_pixels`` brain pixels.
        pixel_weights: (P,) EM pixel inlier probabilities (the previous ones when
            ``config.robust`` is off).
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
    ``config.ncc_threshold`` are excluded unless they have fewer than
    ``config.min_slice_pixels`` brain pixels (their NCC is noise: they rely on the EM weights
    alone); with ``config.robust`` the EM pixel and slice weights are recomputed from the scaled
    residuals (:func:`svr.reconstruction.robust.robust_weights`). Background pixels, when given,
    are weighted by their posterior inlier probability under the same residual model (their
    residual is ``0 - c A x``): where other slices put brain, a misplaced slice's background is
    an outlier and does not carve the brain.

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
    excluded = (ncc < config.ncc_threshold) & (acquisition.brain_pixels >= config.min_slice_pixels)
    robust = None
    if config.robust:
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

    Round ``round_index`` (from 0) uses that round's ``config.sr_iterations`` and
    ``config.regularization`` (the last value repeats) and ``config.edge_delta``
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
            _per_round(config.regularization, round_index),
            _per_round(config.sr_iterations, round_index),
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
        config.edge_delta,
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


@dataclasses.dataclass
class _RoundState:
    """What the rounds change: poses (and their grid points), weights and the volume."""

    poses: Tensor
    points: Tensor
    background_points: Tensor | None
    pixel_w: Tensor
    slice_w: Tensor
    excluded: Tensor
    volume: Tensor


def _register(
    model: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: _Timer,
    group_size: int,
    active: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """One slice-to-volume registration pass on ``state``; returns each slice's pose change."""
    with timer.phase("slice-to-volume registration"):
        before = state.poses
        state.poses = svr_pass(
            model,
            state.volume,
            before,
            config,
            group_size,
            slice_weights=state.slice_w * (~state.excluded),
            active=active,
        )
        state.points = model.points(state.poses)
        state.background_points = model.background_points(state.poses)
    return pose_change(before, state.poses)


def _reconstruct_volume(
    model: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: _Timer,
    round_index: int,
    settings: tuple[float, int] | None = None,
) -> OutlierWeights:
    """Outlier weights then super-resolution on ``state``; returns the weights."""
    with timer.phase("outlier rejection"):
        outliers = reject_outliers(
            model,
            state.volume,
            state.points,
            config,
            state.pixel_w,
            state.slice_w,
            state.background_points,
        )
        state.pixel_w, state.slice_w = outliers.pixel_weights, outliers.slice_weights
        state.excluded = outliers.excluded
    with timer.phase("super-resolution"):
        state.volume = super_resolve(
            model,
            state.volume,
            state.points,
            outliers,
            config,
            round_index,
            state.background_points,
            settings,
        )
    return outliers


def _record(
    index: int,
    stage: str,
    changes: tuple[Tensor, Tensor] | None,
    registered: Tensor | None,
    config: ReconstructionConfig,
    outliers: OutlierWeights,
    previous_excluded: Tensor,
    started: float,
    ncc: Tensor | None = None,
) -> RoundRecord:
    """The round's record (also logged).

    ``changes`` is ``None`` for a round without SVR; otherwise ``registered`` (N,) bool says
    which slices it registered. ``ncc`` (N,) replaces the NCCs of ``outliers`` (those at the
    round's start).
    """
    if changes is None or registered is None:
        rotation, translation = torch.zeros(0), torch.zeros(0)
    else:
        registered = registered.cpu()
        rotation, translation = changes[0][registered], changes[1][registered]
    still_deg, still_mm = config.convergence
    moving = (rotation > still_deg) | (translation > still_mm)
    excluded = outliers.excluded.cpu()
    median_r, p90_r, median_t, p90_t = round_summary(rotation, translation)
    record = RoundRecord(
        index=index,
        stage=stage,
        registered=int(rotation.numel()),
        moving=int(moving.sum()),
        rotation_deg=median_r,
        rotation_p90_deg=p90_r,
        translation_mm=median_t,
        translation_p90_mm=p90_t,
        ncc=float((outliers.ncc if ncc is None else ncc).mean()),
        excluded=int(excluded.sum()),
        newly_excluded=int((excluded & ~previous_excluded.cpu()).sum()),
        seconds=time.perf_counter() - started,
    )
    log.info(record.line())
    return record


def _fixed_rounds(
    model: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: _Timer,
    progress: bool,
) -> tuple[list[RoundRecord], bool | None]:
    """``config.rounds`` rounds with the per-round settings (fetal-svr 0.1.0's schedule)."""
    records = []
    bar = tqdm(range(config.rounds), desc="reconstruction", disable=not progress)
    for round_index in bar:
        started, before = time.perf_counter(), state.excluded
        changes = None
        size = _group_size(config, round_index)
        if round_index > 0:
            changes = _register(model, state, config, timer, size)
        outliers = _reconstruct_volume(model, state, config, timer, round_index)
        registered = _registrable(model, config, size) & ~before.cpu()
        stage = "first" if changes is None else _stage(size)
        records.append(
            _record(round_index, stage, changes, registered, config, outliers, before, started)
        )
        bar.set_postfix(ncc=f"{records[-1].ncc:.3f}", excluded=records[-1].excluded)
    return records, None


def _adaptive_rounds(
    model: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: _Timer,
    progress: bool,
) -> tuple[list[RoundRecord], bool | None]:
    """Registration rounds while the slices move, then the final round (see ``schedule``).

    Round 0 reconstructs the volume at the initial poses. Each following round registers the
    slices (in groups of temporal neighbours first, then one by one; a slice that moved less than
    half the thresholds in ``QUIET_ROUNDS`` registered rounds in a row sits out the next round,
    and slices that fit badly get a wider search: :func:`recapture`), then updates the outlier
    weights and the volume. The rounds stop once at most ``config.converged_fraction`` of the
    registrable slices moved more than the thresholds, or one round before the cap
    ``config.rounds``. The final round registers
    every slice once more if they had not converged, and reconstructs the volume anew at the final
    poses with the last regularisation and CG iterations, so that the output does not carry the
    blur of the rough volumes of the first rounds.
    """
    records: list[RoundRecord] = []
    cap = config.rounds
    bar = tqdm(total=cap, desc="reconstruction", disable=not progress)
    started, before = time.perf_counter(), state.excluded
    settings = _alignment_settings(config, 0) if cap > 1 else _final_settings(config)
    outliers = _reconstruct_volume(model, state, config, timer, 0, settings)
    records.append(_record(0, "first", None, None, config, outliers, before, started))
    bar.update()
    if cap == 1:
        bar.close()
        return records, None
    single = _registrable(model, config, 1)
    active = single.clone()
    quiet = torch.zeros(len(single), dtype=torch.int64)
    tries = torch.zeros(len(single), dtype=torch.int64)
    start = state.poses.clone()
    converged, index = False, 1
    while index < cap - 1:
        started, before = time.perf_counter(), state.excluded
        size = _group_size(config, index)
        if config.recapture and size == 1 and _group_size(config, index - 1) == 1:
            low = _fits_badly(outliers.ncc.cpu(), single) & (tries < 2)
            if bool(low.any()):
                with timer.phase("recapture"):
                    new_poses, recaptured = recapture(
                        model, state.volume, state.poses, start, low.to(state.poses.device), config
                    )
                    recaptured = recaptured.cpu()
                    tries += low.long()
                    state.poses = new_poses
                    state.points = model.points(state.poses)
                    state.background_points = model.background_points(state.poses)
                log.info(
                    "recapture: %d slices fit badly, %d found a better pose from a wider search",
                    int(low.sum()),
                    int(recaptured.sum()),
                )
                active = active | low
        changes = _register(model, state, config, timer, size, active if size == 1 else None)
        registered = active if size == 1 else _registrable(model, config, size)
        outliers = _reconstruct_volume(
            model, state, config, timer, index, _alignment_settings(config, index)
        )
        record = _record(
            index, _stage(size), changes, registered, config, outliers, before, started
        )
        records.append(record)
        bar.update()
        bar.set_postfix(moving=record.moving, ncc=f"{record.ncc:.3f}")
        index += 1
        rotation, translation = changes
        if record.moving <= config.converged_fraction * int(single.sum()):
            converged = True
            break
        if size == 1:
            # A slice that moved less than half the thresholds in two rounds in a row sits out
            # the next round and is registered again after it: the volume keeps changing
            # around it (freezing it for good cost sb24-large 0.55 dB).
            still_deg, still_mm = config.convergence
            still = (rotation <= still_deg / 2) & (translation <= still_mm / 2)
            quiet = torch.where(still & registered, quiet + 1, torch.zeros_like(quiet))
            active = single & (quiet < QUIET_ROUNDS)
    verdict: bool | None = converged
    if index == 1:
        # A cap of 2: nothing ran between the first volume and the final round to judge by.
        verdict = None
        log.info(
            "--iterations %d leaves no registration round before the final one, which registers "
            "every slice once",
            cap,
        )
    elif converged:
        log.info(
            "converged after round %d: %d of %d slices still moved (at most %.0f%% allowed)",
            index - 1,
            records[-1].moving,
            int(single.sum()),
            100 * config.converged_fraction,
        )
    else:
        log.warning(
            "not converged: %d slices still moved in round %d, the last before the cap of %d "
            "rounds (--iterations); the final round registers them once more",
            records[-1].moving,
            index - 1,
            cap,
        )
    started, before = time.perf_counter(), state.excluded
    last = single & ~state.excluded.cpu()
    # Converged slices would not move: the final round only reconstructs the volume anew.
    final: tuple[Tensor, Tensor] | None = None
    if not converged:
        final = _register(model, state, config, timer, 1, single)
    with timer.phase("super-resolution"):
        state.volume = initial_volume(model, state.points)
    outliers = _reconstruct_volume(model, state, config, timer, index, _final_settings(config))
    simulated = model.projector.forward(state.volume, state.points)
    ncc = slice_ncc(model.projector, simulated, model.observed)
    records.append(_record(index, "final", final, last, config, outliers, before, started, ncc))
    bar.update()
    bar.close()
    return records, verdict


def _fits_badly(ncc: Tensor, registrable: Tensor) -> Tensor:
    """(N,) bool: registrable slices whose NCC is far below the others' (median - 3 MAD)."""
    values = ncc[registrable].double()
    if values.numel() < 4:
        return torch.zeros_like(registrable)
    median = float(values.median())
    spread = 1.4826 * float((values - median).abs().median())
    return registrable & (ncc.double() < median - 3 * max(spread, 0.01))


def _registrable(model: Acquisition, config: ReconstructionConfig, group_size: int) -> Tensor:
    """(N,) bool on the CPU: the slices a pass with ``group_size`` registers."""
    if group_size > 1:
        return torch.ones(len(model.slices), dtype=torch.bool)
    return (model.brain_pixels >= config.min_slice_pixels).cpu()


def _stage(group_size: int) -> str:
    return "slices" if group_size == 1 else f"groups of {group_size}"


def _alignment_settings(config: ReconstructionConfig, round_index: int) -> tuple[float, int]:
    """(regularisation, CG iterations) of an adaptive round before the final one."""
    regularization = config.regularization[:-1] or config.regularization
    iterations = config.sr_iterations[:-1] or config.sr_iterations
    return (_per_round(regularization, round_index), _per_round(iterations, round_index))


def _final_settings(config: ReconstructionConfig) -> tuple[float, int]:
    """(regularisation, CG iterations) of the adaptive schedule's final round."""
    return (config.regularization[-1], config.sr_iterations[-1])


def _rounds(
    slices: SliceSet,
    config: ReconstructionConfig,
    init: tuple[str, ...],
    timer: _Timer,
    progress: bool,
) -> ReconstructionResult:
    adaptive = config.schedule == "adaptive"
    with timer.phase("setup"):
        grid = output_grid(slices, config.output_resolution_mm)
        model = acquisition_model(slices, grid, config.background_mm if adaptive else (0.0, 0.0))
        poses = slices.poses
        points = model.points(poses)
        volume = initial_volume(model, points)
        state = _RoundState(
            poses=poses,
            points=points,
            background_points=model.background_points(poses),
            pixel_w=torch.ones_like(model.observed),
            slice_w=torch.ones(len(slices), device=model.observed.device),
            excluded=torch.zeros(len(slices), dtype=torch.bool, device=model.observed.device),
            volume=volume,
        )
        initial = volume.clone()
        log.info(
            "output grid %s at %.2f mm (%s frame), %s schedule",
            grid.shape,
            config.output_resolution_mm,
            slices.frame,
            config.schedule,
        )
    run = _adaptive_rounds if adaptive else _fixed_rounds
    records, converged = run(model, state, config, timer, progress)
    with timer.phase("finish"):
        final = finalise(model, state.volume, state.points, state.pixel_w)
    _report_exclusions(slices, state.excluded)
    return ReconstructionResult(
        volume=grid.image(final.volume.float()),
        mask=grid.image(final.mask),
        initial_volume=grid.image(initial.float()),
        slices=slices.with_poses(state.poses),
        slice_ncc=final.slice_ncc.detach().cpu(),
        slice_weights=state.slice_w.detach().cpu(),
        excluded=state.excluded.cpu(),
        initialisation=init,
        timings_s=timer.timings,
        rounds=tuple(records),
        converged=converged,
    )


def _anchored(poses: Tensor, previous: Tensor) -> Tensor:
    """Remove the common rigid motion of all slices from a registration's corrections.

    Slice-to-volume registration can move every slice (and with them the volume) together; the
    robust mean of the per-slice corrections ``poses_i o previous_i^-1`` is taken back out so the
    volume stays in the frame of the initialisation (the template stack, or canonical space).
    """
    drift = robust_mean_pose(poses @ torch.linalg.inv(previous))
    return torch.linalg.inv(drift).to(poses) @ poses


def _report_exclusions(slices: SliceSet, excluded: Tensor) -> None:
    for sid, name in enumerate(slices.stack_names):
        members = slices.stack_ids == sid
        total = int(members.sum())
        out = int((excluded & members).sum())
        if total and out == total:
            log.warning(
                "%s: all %d slices excluded (NCC below threshold); check its mask", name, total
            )
        elif out:
            log.info("%s: %d of %d slices excluded", name, out, total)
