"""The reconstruction pipeline: slices -> initial poses -> (SVR, super-resolution) rounds.

Phases (each timed and logged):
    1. slices: every stack cut into slices, each its own rigid body (:func:`extract_slices`);
    2. initialisation: ``"none"`` keeps the scanner poses; ``"stack"`` registers every stack
       rigidly to a volume estimated from the template stack; ``"cnn"`` predicts every slice's
       canonical pose, replaces predictions that disagree with their stack's robust consensus
       by the consensus pose, and keeps per stack whichever of these poses and the stack
       registration (mapped to canonical space) makes the simulated slices match the observed
       ones better by NCC, as NeSVoR does (:func:`learned_initialisation`);
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
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NamedTuple, TypeVar

import torch
from torch import Tensor
from tqdm import tqdm

from svr.geometry import se3_compose, se3_inverse
from svr.geometry.averaging import robust_mean_pose
from svr.models.network import SlicePoseNet
from svr.reconstruction.cnn_init import CnnInitialisation, cnn_slice_poses
from svr.reconstruction.config import REGISTRATIONS, ReconstructionConfig, ReconstructionResult
from svr.reconstruction.operators import SliceProjector, VolumeGrid
from svr.reconstruction.registration import RegistrationConfig, register_rigid, slice_ncc
from svr.reconstruction.robust import robust_weights
from svr.reconstruction.slices import SliceSet, Stack, extract_slices
from svr.reconstruction.superres import (
    coverage,
    output_grid,
    scattered_data_approximation,
    slice_intensity_scales,
    super_resolution,
)

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

STACK_REGISTRATION = RegistrationConfig(levels=3, iterations=10)
SVR_PSF_SAMPLES = 3


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


def _sda(slices: SliceSet, grid: VolumeGrid, psf_samples: int = SVR_PSF_SAMPLES) -> Tensor:
    projector = SliceProjector(grid, slices, psf_samples=psf_samples)
    observed = projector.gather(slices.images)
    points = projector.grid_points(slices.poses)
    return scattered_data_approximation(projector, points, observed, torch.ones_like(observed))


def stack_registration(
    slices: SliceSet, resolution_mm: float, template: int | None = None
) -> tuple[Tensor, int]:
    """Rigid registration of every stack to a volume estimated from the template stack.

    Args:
        slices: All slices at their starting poses.
        resolution_mm: Voxel size of the template volume.
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
    grid = output_grid(slices, 2 * resolution_mm)
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


def _stack_ncc(slices: SliceSet, resolution_mm: float) -> Tensor:
    """(S,) mean NCC of each stack's slices with their simulation from the slices' SDA volume."""
    grid = output_grid(slices, 2 * resolution_mm)
    projector = SliceProjector(grid, slices, psf_samples=SVR_PSF_SAMPLES)
    observed = projector.gather(slices.images)
    points = projector.grid_points(slices.poses)
    volume = scattered_data_approximation(projector, points, observed, torch.ones_like(observed))
    ncc = slice_ncc(projector, projector.forward(volume, points), observed)
    num_stacks = len(slices.stack_names)
    total = torch.zeros(num_stacks, dtype=ncc.dtype, device=ncc.device)
    count = total.index_add(0, slices.stack_ids, torch.ones_like(ncc)).clamp_min(1)
    return total.index_add(0, slices.stack_ids, ncc) / count


class LearnedStart(NamedTuple):
    """What :func:`learned_initialisation` chose.

    Attributes:
        slices: The slices at their initial canonical poses.
        choice: Per stack, ``"cnn"`` or ``"stack"``.
        notes: Per stack, why (support, flipped slices, NCC), for the log and the QA figure.
    """

    slices: SliceSet
    choice: tuple[str, ...]
    notes: tuple[str, ...]


def _canonical_frame(
    learned: CnnInitialisation, registered: Tensor, slices: SliceSet, trusted: Tensor
) -> Tensor | None:
    """``G``: registered (template) frame -> canonical, from the trusted stacks' supporting slices.

    The robust mean of ``P_i o X_i^-1`` over the slices that support their stack's transform in
    the stacks with enough support, ``X_i`` their registered poses; ``None`` if there are none.
    """
    use = learned.supporting & trusted[slices.stack_ids]
    if not bool(use.any()):
        return None
    chosen = learned.predicted_poses[use].to(torch.float64).cpu()
    inverse = se3_inverse(registered[use].to(torch.float64).cpu())
    return robust_mean_pose(se3_compose(chosen, inverse)).to(registered)


def _mean_ncc(per_stack: Tensor, slices: SliceSet) -> float:
    """Slice-weighted mean of (S,) per-stack NCCs."""
    counts = torch.bincount(slices.stack_ids.cpu(), minlength=len(per_stack)).to(per_stack)
    return float((per_stack.cpu() * counts.cpu()).sum() / counts.sum().clamp_min(1))


def learned_initialisation(
    slices: SliceSet, learned: CnnInitialisation, config: ReconstructionConfig
) -> LearnedStart:
    """Learned slice poses or stack registration, per stack, chosen so as never to do harm.

    1. **Support.** A stack whose slices mostly disagree with their consensus (support below
       ``config.cnn_min_support``; :func:`svr.reconstruction.cnn_init.disambiguate_stack`) means the
       model is unsure of it: it keeps stack registration, and the log and QA say so.
    2. **Canonical frame.** Stack registration is moved into canonical space by ``G``, the robust
       mean over the trusted stacks' supporting slices of (chosen prediction) o (registered
       pose)^-1, so that the output is in atlas orientation whichever start each stack keeps. With
       no trusted stack the predictions' global transform is used, and the log warns that the
       orientation is unreliable.
    3. **NCC per stack.** A trusted stack keeps its learned poses (each slice its own prediction,
       or the consensus pose where that is an outlier: :meth:`CnnInitialisation.refined_poses`)
       when they match their simulation from their own scattered-data volume at least as well
       (mean NCC) as the registered poses do, as NeSVoR chooses between SVoRT and registration.
    4. **Joint check.** The mixed start is kept only if its slice-weighted mean NCC is not below
       that of stack registration alone; otherwise every stack starts from registration.

    Args:
        slices: All slices, at their scanner poses.
        learned: The slices' (disambiguated) predicted canonical poses and their consensus
            (:func:`svr.reconstruction.cnn_init.cnn_slice_poses`).
        config: Settings.

    Returns:
        The slices at their initial canonical poses, the choice per stack and notes per stack.
    """
    outliers = learned.outliers(config.cnn_max_deviation_deg, config.cnn_max_deviation_mm)
    log.info(
        "cnn: %d of %d slice predictions disagree with their stack's consensus (> %g deg or "
        "%g mm) and take the consensus pose",
        int(outliers.sum()),
        len(slices),
        config.cnn_max_deviation_deg,
        config.cnn_max_deviation_mm,
    )
    support = learned.stack_support.cpu()
    flipped = learned.flipped(slices.stack_ids).cpu()
    trusted = (support >= config.cnn_min_support).to(slices.device)
    registered, _ = stack_registration(slices, config.output_resolution_mm, config.template)
    frame = _canonical_frame(learned, registered, slices, trusted)
    if frame is None:
        log.warning(
            "cnn: no stack has enough support (>= %.0f%% of its slices); the learned "
            "initialisation is unsure and the output's atlas orientation is unreliable",
            100 * config.cnn_min_support,
        )
        frame = learned.global_transform.to(registered)
    candidates = {
        "cnn": learned.refined_poses(config.cnn_max_deviation_deg, config.cnn_max_deviation_mm),
        "stack": frame @ registered,
    }
    # The learned candidate is only scored when some stack may keep it.
    scores = {
        name: _stack_ncc(slices.with_poses(poses, "canonical"), config.output_resolution_mm)
        for name, poses in candidates.items()
        if name == "stack" or bool(trusted.any())
    }
    choice, notes = [], []
    poses = candidates["stack"].clone()
    for sid, name in enumerate(slices.stack_names):
        head = f"support {100 * float(support[sid]):.0f}%, {int(flipped[sid])} flipped"
        if not bool(trusted[sid]):
            best, why = "stack", f"cnn unsure ({head})"
        else:
            ncc_cnn, ncc_stack = float(scores["cnn"][sid]), float(scores["stack"][sid])
            best = "cnn" if ncc_cnn >= ncc_stack else "stack"
            why = f"{head}, NCC cnn {ncc_cnn:.3f} vs stack {ncc_stack:.3f}"
        members = slices.stack_ids == sid
        poses[members] = candidates[best][members]
        choice.append(best)
        notes.append(why)
        log.info("%s: initialisation %s (%s)", name, best, why)
    if "cnn" in choice:
        mixed = _mean_ncc(
            _stack_ncc(slices.with_poses(poses, "canonical"), config.output_resolution_mm), slices
        )
        alone = _mean_ncc(scores["stack"], slices)
        if mixed < alone:
            log.info(
                "cnn: the mixed start (mean NCC %.3f) fits worse than stack registration alone "
                "(%.3f); every stack starts from registration",
                mixed,
                alone,
            )
            poses = candidates["stack"]
            notes = [f"{n}; joint check failed ({mixed:.3f} < {alone:.3f})" for n in notes]
            choice = ["stack"] * len(choice)
    return LearnedStart(slices.with_poses(poses, "canonical"), tuple(choice), tuple(notes))


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
    key = (slices.stack_ids * packets + k % packets) * (int(k.max()) + 1) + (k // packets) // size
    return torch.unique(key, return_inverse=True)[1]


def _group_size(config: ReconstructionConfig, round_index: int) -> int:
    sizes = config.group_sizes
    return sizes[round_index - 1] if round_index - 1 < len(sizes) else 1


def _per_round(values: tuple[_T, ...], round_index: int) -> _T:
    """The value for round ``round_index``; the last one repeats."""
    return values[min(round_index, len(values) - 1)]


def reconstruct(
    stacks: list[Stack],
    config: ReconstructionConfig | None = None,
    model: SlicePoseNet | None = None,
    initial_poses: Tensor | None = None,
    frame: str = "scanner",
    initialisation: tuple[str, ...] | None = None,
    device: str | torch.device = "cpu",
    progress: bool = True,
) -> ReconstructionResult:
    """Reconstruct a volume from prepared stacks.

    Args:
        stacks: The stacks (:func:`svr.reconstruction.stacks.load_stacks`).
        config: Settings.
        model: The slice-pose network, with its configuration ``model.config``
            (:func:`svr.models.predict.load_pose_model`), needed by ``registration="cnn"``.
        initial_poses: (N, 4, 4) starting poses of :func:`extract_slices`'s slices in ``frame``;
            when given, ``config.registration`` is not run.
        frame: The frame of ``initial_poses``.
        initialisation: Per stack, how ``initial_poses`` were obtained (for the report).
        device: Where to compute.
        progress: Show a progress bar.

    Returns:
        The result: volume in the canonical frame for ``"cnn"``, in ``frame`` for given poses,
        in the scanner frame otherwise.

    Raises:
        ValueError: If ``registration="cnn"`` comes without a model, or the registration is
            unknown.
    """
    config = config or ReconstructionConfig()
    timer = _Timer()
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(config.seed)
    notes: tuple[str, ...] = ()
    try:
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
            elif config.registration == "cnn":
                if model is None:
                    raise ValueError("reconstruct(): registration 'cnn' needs a model")
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
        return dataclasses.replace(result, initialisation_notes=notes) if notes else result
    finally:
        torch.random.set_rng_state(generator_state)


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
    """

    slices: SliceSet
    grid: VolumeGrid
    projector: SliceProjector
    svr_projector: SliceProjector
    observed: Tensor
    brain_pixels: Tensor

    def points(self, poses: Tensor) -> Tensor:
        """(K, P, 3) float32 ``grid_sample`` coordinates of every PSF node of every modelled pixel.

        Args:
            poses: (N, 4, 4) slice poses: slice-plane mm -> the grid's frame (mm).
        """
        return self.projector.grid_points(poses)


def acquisition_model(slices: SliceSet, grid: VolumeGrid) -> Acquisition:
    """The acquisition model of ``slices`` on ``grid`` (the setup of :func:`reconstruct`'s rounds).

    Args:
        slices: The slices; their poses' frame must be ``grid``'s frame.
        grid: The volume grid (:func:`svr.reconstruction.superres.output_grid` in
            :func:`reconstruct`).

    Returns:
        The projectors, the observed pixel values and the slices' brain pixel counts.
    """
    projector = SliceProjector(grid, slices)
    return Acquisition(
        slices=slices,
        grid=grid,
        projector=projector,
        svr_projector=SliceProjector(grid, slices, psf_samples=SVR_PSF_SAMPLES),
        observed=projector.gather(slices.images),
        brain_pixels=slices.masks.flatten(1).sum(1),
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

    Returns:
        (N, 4, 4) float64 registered poses in the same frame.
    """
    slices = acquisition.slices
    groups = slice_groups(slices, config.packets, group_size)
    # Slices with little brain carry too little signal to be registered alone.
    small = (acquisition.brain_pixels < config.min_slice_pixels) if group_size == 1 else None
    registered = register_rigid(
        acquisition.svr_projector,
        volume,
        slices.images,
        poses,
        groups,
        RegistrationConfig(levels=config.svr_levels, iterations=config.svr_iterations),
        fixed=small,
        slice_weights=slice_weights,
    )
    return _anchored(registered, poses) if anchor else registered


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
    """

    scales: Tensor
    ncc: Tensor
    excluded: Tensor
    pixel_weights: Tensor
    slice_weights: Tensor
    weights: Tensor


def reject_outliers(
    acquisition: Acquisition,
    volume: Tensor,
    points: Tensor,
    config: ReconstructionConfig,
    pixel_weights: Tensor | None = None,
    slice_weights: Tensor | None = None,
) -> OutlierWeights:
    """Per-slice intensity scales, EM outlier weights and NCC exclusion at the current volume.

    Slices are simulated from ``volume`` at ``points``; the per-slice scales are fitted with the
    previous ``pixel_weights``; slices whose NCC with their simulation is below
    ``config.ncc_threshold`` are excluded unless they have fewer than
    ``config.min_slice_pixels`` brain pixels (their NCC is noise: they rely on the EM weights
    alone); with ``config.robust`` the EM pixel and slice weights are recomputed from the scaled
    residuals (:func:`svr.reconstruction.robust.robust_weights`).

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) volume on ``acquisition.grid``.
        points: (K, P, 3) grid points of the current poses (:meth:`Acquisition.points`).
        config: Settings (``ncc_threshold``, ``min_slice_pixels``, ``robust``).
        pixel_weights: (P,) previous pixel weights, or ``None`` for all 1 (the first round).
        slice_weights: (N,) previous slice weights, or ``None`` for all 1 (the first round).

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
    if config.robust:
        robust = robust_weights(
            observed - scales[projector.slice_of] * simulated, projector.slice_of, num_slices
        )
        pixel_weights, slice_weights = robust.pixel, robust.slice
    weights = pixel_weights * (slice_weights * (~excluded))[projector.slice_of]
    return OutlierWeights(scales, ncc, excluded, pixel_weights, slice_weights, weights)


def super_resolve(
    acquisition: Acquisition,
    volume: Tensor,
    points: Tensor,
    outliers: OutlierWeights,
    config: ReconstructionConfig,
    round_index: int,
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

    Returns:
        (I, J, K) non-negative volume on ``acquisition.grid``.
    """
    return super_resolution(
        acquisition.projector,
        points,
        acquisition.observed,
        outliers.weights,
        outliers.scales,
        volume,
        _per_round(config.sr_iterations, round_index),
        _per_round(config.regularization, round_index),
        config.edge_delta,
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


def _rounds(
    slices: SliceSet,
    config: ReconstructionConfig,
    init: tuple[str, ...],
    timer: _Timer,
    progress: bool,
) -> ReconstructionResult:
    with timer.phase("setup"):
        grid = output_grid(slices, config.output_resolution_mm)
        model = acquisition_model(slices, grid)
        poses = slices.poses
        points = model.points(poses)
        pixel_w = torch.ones_like(model.observed)
        slice_w = torch.ones(len(slices), device=model.observed.device)
        excluded = torch.zeros(len(slices), dtype=torch.bool, device=model.observed.device)
        volume = initial_volume(model, points)
        initial = volume.clone()
        log.info(
            "output grid %s at %.2f mm (%s frame)",
            grid.shape,
            config.output_resolution_mm,
            slices.frame,
        )
    bar = tqdm(range(config.outer_iterations), desc="reconstruction", disable=not progress)
    for round_index in bar:
        if round_index > 0:
            with timer.phase("slice-to-volume registration"):
                poses = svr_pass(
                    model,
                    volume,
                    poses,
                    config,
                    _group_size(config, round_index),
                    slice_weights=slice_w * (~excluded),
                )
                points = model.points(poses)
        with timer.phase("outlier rejection"):
            outliers = reject_outliers(model, volume, points, config, pixel_w, slice_w)
            pixel_w, slice_w = outliers.pixel_weights, outliers.slice_weights
            excluded = outliers.excluded
        with timer.phase("super-resolution"):
            volume = super_resolve(model, volume, points, outliers, config, round_index)
        bar.set_postfix(ncc=f"{float(outliers.ncc.mean()):.3f}", excluded=int(excluded.sum()))
    with timer.phase("finish"):
        final = finalise(model, volume, points, pixel_w)
    _report_exclusions(slices, excluded)
    return ReconstructionResult(
        volume=grid.image(final.volume.float()),
        mask=grid.image(final.mask),
        initial_volume=grid.image(initial.float()),
        slices=slices.with_poses(poses),
        slice_ncc=final.slice_ncc.detach().cpu(),
        slice_weights=slice_w.detach().cpu(),
        excluded=excluded.cpu(),
        initialisation=init,
        timings_s=timer.timings,
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
