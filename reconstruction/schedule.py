"""The schedules that chain a round's steps, from the slices' starting poses to the result.

``"fixed"`` runs ``config.schedule.rounds`` rounds with the per-round settings; ``"adaptive"``
runs registration rounds while the slices still move, then a final round that reconstructs the
volume anew at the final poses (:func:`run_rounds`). The steps themselves are
:mod:`svr.reconstruction.rounds`; what each round did is a
:class:`~svr.reconstruction.convergence.RoundRecord`.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import torch
from torch import Tensor
from tqdm import tqdm

from svr.reconstruction.acquisition import Acquisition, acquisition_model
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.convergence import RoundRecord, pose_change, round_summary
from svr.reconstruction.recapture import recapture
from svr.reconstruction.registration import slice_ncc
from svr.reconstruction.result import ReconstructionResult
from svr.reconstruction.rounds import (
    OutlierWeights,
    finalise,
    initial_volume,
    per_round,
    reject_outliers,
    super_resolve,
    svr_pass,
    volume_without,
)
from svr.reconstruction.slices import SliceSet
from svr.reconstruction.superres import output_grid
from svr.reconstruction.trajectory import fit_slice_trajectory
from svr.timing import PhaseTimer

__all__ = ["QUIET_ROUNDS", "run_rounds"]

log = logging.getLogger(__name__)

# The adaptive schedule lets a slice sit out one round once it has moved less than half the
# convergence thresholds in this many registered one-by-one rounds in a row.
QUIET_ROUNDS = 2


def _thresholds(config: ReconstructionConfig, polished: bool = False) -> tuple[float, float]:
    """The (degrees, mm) change above which a slice still moves (``polished``: is unsettled)."""
    factor = config.schedule.polish if polished else 1.0
    return factor * config.schedule.converged_deg, factor * config.schedule.converged_mm


def _few(count: int, activity: _Activity, config: ReconstructionConfig) -> bool:
    """At most ``converged_fraction`` of the slices registered one by one: ``count`` is few."""
    return count <= config.schedule.converged_fraction * int(activity.single.sum())


def _group_size(config: ReconstructionConfig, round_index: int) -> int:
    sizes = config.schedule.group_sizes
    return sizes[round_index - 1] if round_index - 1 < len(sizes) else 1


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
    acquisition: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: PhaseTimer,
    group_size: int,
    active: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """One slice-to-volume registration pass on ``state``; returns each slice's pose change."""
    with timer.phase("slice-to-volume registration"):
        before = state.poses
        state.poses = svr_pass(
            acquisition,
            state.volume,
            before,
            config,
            group_size,
            slice_weights=state.slice_w * (~state.excluded),
            active=active,
        )
        state.points = acquisition.points(state.poses)
        state.background_points = acquisition.background_points(state.poses)
    return pose_change(before, state.poses)


def _reconstruct_volume(
    acquisition: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: PhaseTimer,
    round_index: int,
    settings: tuple[float, int] | None = None,
) -> OutlierWeights:
    """Outlier weights then super-resolution on ``state``; returns the weights."""
    with timer.phase("outlier rejection"):
        outliers = reject_outliers(
            acquisition,
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
            acquisition,
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
    still_deg, still_mm = _thresholds(config)
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
    acquisition: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: PhaseTimer,
    progress: bool,
) -> tuple[list[RoundRecord], bool | None]:
    """``config.schedule.rounds`` rounds with the per-round settings (release 0.1.0's)."""
    records = []
    bar = tqdm(range(config.schedule.rounds), desc="reconstruction", disable=not progress)
    for round_index in bar:
        started, before = time.perf_counter(), state.excluded
        changes = None
        size = _group_size(config, round_index)
        if round_index > 0:
            changes = _register(acquisition, state, config, timer, size)
        outliers = _reconstruct_volume(acquisition, state, config, timer, round_index)
        registered = _registrable(acquisition, config, size) & ~before.cpu()
        stage = "first" if changes is None else _stage(size)
        records.append(
            _record(round_index, stage, changes, registered, config, outliers, before, started)
        )
        bar.set_postfix(ncc=f"{records[-1].ncc:.3f}", excluded=records[-1].excluded)
    return records, None


@dataclasses.dataclass
class _Activity:
    """Which slices the adaptive schedule registers: all, active now, quiet counts, searches."""

    single: Tensor
    active: Tensor
    quiet: Tensor
    tries: Tensor
    start: Tensor

    @classmethod
    def of(cls, single: Tensor, start: Tensor) -> _Activity:
        zeros = torch.zeros(len(single), dtype=torch.int64)
        return cls(single, single.clone(), zeros, zeros.clone(), start.clone())


def _recapture_round(
    acquisition: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: PhaseTimer,
    activity: _Activity,
    ncc: Tensor,
) -> None:
    """A wider search for the slices that fit badly (at most twice each); they become active."""
    low = _fits_badly(ncc.cpu(), activity.single) & (activity.tries < 2)
    if not bool(low.any()):
        return
    with timer.phase("recapture"):
        # The slices that fit badly are left out of the fit: their packet's other slices say
        # where the motion put them.
        known = ~low.to(state.poses.device)
        along = fit_slice_trajectory(
            acquisition.slices.with_poses(state.poses), config.packets, known=known
        )
        # ... and out of the reference: the volume there is theirs where they sit wrong together.
        reference = volume_without(acquisition, state.points, low.to(state.poses.device))
        new_poses, recaptured = recapture(
            acquisition,
            reference,
            state.poses,
            activity.start,
            low.to(state.poses.device),
            config,
            trajectory=along.poses,
        )
        activity.tries += low.long()
        state.poses = new_poses
        state.points = acquisition.points(state.poses)
        state.background_points = acquisition.background_points(state.poses)
    log.info(
        "recapture: %d slices fit badly, %d found a better pose from a wider search",
        int(low.sum()),
        int(recaptured.cpu().sum()),
    )
    activity.active = activity.active | low


def _alignment_round(
    acquisition: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: PhaseTimer,
    activity: _Activity,
    index: int,
    outliers: OutlierWeights,
) -> tuple[RoundRecord, OutlierWeights, bool]:
    """Adaptive round ``index``: (recapture,) registration, weights, volume; settled?

    The slices have settled when few of them moved more than the thresholds times
    ``config.schedule.polish`` (the rounds stop); the record counts those that moved more than the
    thresholds themselves (the verdict).
    """
    started, before = time.perf_counter(), state.excluded
    size = _group_size(config, index)
    if config.schedule.recapture and size == 1 and _group_size(config, index - 1) == 1:
        _recapture_round(acquisition, state, config, timer, activity, outliers.ncc)
    changes = _register(
        acquisition, state, config, timer, size, activity.active if size == 1 else None
    )
    registered = activity.active if size == 1 else _registrable(acquisition, config, size)
    outliers = _reconstruct_volume(
        acquisition, state, config, timer, index, _alignment_settings(config, index)
    )
    record = _record(index, _stage(size), changes, registered, config, outliers, before, started)
    settle_deg, settle_mm = _thresholds(config, polished=True)
    rotation, translation = changes
    unsettled = ((rotation > settle_deg) | (translation > settle_mm)) & registered
    if _few(int(unsettled.sum()), activity, config):
        return record, outliers, True
    if size == 1:
        # A slice that moved less than half the thresholds in two rounds in a row sits out the
        # next round and is registered again after it: the volume keeps changing around it.
        still = (rotation <= settle_deg / 2) & (translation <= settle_mm / 2)
        quiet = activity.quiet
        activity.quiet = torch.where(still & registered, quiet + 1, torch.zeros_like(quiet))
        activity.active = activity.single & (activity.quiet < QUIET_ROUNDS)
    return record, outliers, False


def _log_verdict(
    records: list[RoundRecord],
    index: int,
    settled: bool,
    activity: _Activity,
    config: ReconstructionConfig,
) -> bool | None:
    """Log how the registration rounds ended; the verdict (``None``: nothing ran to judge by).

    The slices converged when few of them still moved more than the thresholds in the last
    registration round, whether or not the polish after it settled before the cap.
    """
    cap = config.schedule.rounds
    if index == 1:
        log.info(
            "--iterations %d leaves no registration round before the final one, which registers "
            "every slice once",
            cap,
        )
        return None
    converged = _few(records[-1].moving, activity, config)
    if converged:
        log.info(
            "converged after round %d: %d of %d slices still moved (at most %.0f%% allowed)",
            index - 1,
            records[-1].moving,
            int(activity.single.sum()),
            100 * config.schedule.converged_fraction,
        )
        polish = config.schedule.polish
        if polish < 1 and settled:
            log.info("the slices also settled at %g times the thresholds (--polish)", polish)
        elif polish < 1:
            log.info(
                "the polish (%g times the thresholds, --polish) reached the cap of %d rounds "
                "(--iterations); the final round registers every slice once more",
                polish,
                cap,
            )
    else:
        log.warning(
            "not converged: %d slices still moved in round %d, the last before the cap of %d "
            "rounds (--iterations); the final round registers them once more",
            records[-1].moving,
            index - 1,
            cap,
        )
    return converged


def _final_round(
    acquisition: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: PhaseTimer,
    single: Tensor,
    index: int,
    settled: bool,
) -> RoundRecord:
    """Register every slice once more unless settled; reconstruct the volume anew."""
    started, before = time.perf_counter(), state.excluded
    last = single & ~state.excluded.cpu()
    # Settled slices would not move: the final round only reconstructs the volume anew.
    final: tuple[Tensor, Tensor] | None = None
    if not settled:
        final = _register(acquisition, state, config, timer, 1, single)
    with timer.phase("super-resolution"):
        state.volume = initial_volume(acquisition, state.points)
    outliers = _reconstruct_volume(
        acquisition, state, config, timer, index, _final_settings(config)
    )
    simulated = acquisition.projector.forward(state.volume, state.points)
    ncc = slice_ncc(acquisition.projector, simulated, acquisition.observed)
    return _record(index, "final", final, last, config, outliers, before, started, ncc)


def _adaptive_rounds(
    acquisition: Acquisition,
    state: _RoundState,
    config: ReconstructionConfig,
    timer: PhaseTimer,
    progress: bool,
) -> tuple[list[RoundRecord], bool | None]:
    """Registration rounds while the slices move, then the final round.

    Round 0 reconstructs the volume at the initial poses. Each following round registers the
    slices (in groups of temporal neighbours first, then one by one; a slice that moved less than
    half the thresholds in ``QUIET_ROUNDS`` registered rounds in a row sits out the next round,
    and slices that fit badly get a wider search: :func:`~svr.reconstruction.recapture.recapture`),
    then updates the outlier weights and the volume. The rounds stop once at most
    ``config.schedule.converged_fraction`` of the registrable slices moved more than the
    thresholds times ``config.schedule.polish`` (the slices have settled), or one round before the
    cap ``config.schedule.rounds``; the verdict is whether few moved more than the thresholds
    themselves in the last of them. The final round registers
    every slice once more if they had not settled, and reconstructs the volume anew at the
    final poses with the last regularisation and CG iterations, so that the output does not carry
    the blur of the rough volumes of the first rounds. The progress bar ends full at the round the
    schedule stopped, whether it converged or reached the cap.
    """
    cap = config.schedule.rounds
    bar = tqdm(total=cap, desc="reconstruction", unit="round", disable=not progress)
    started, before = time.perf_counter(), state.excluded
    settings = _alignment_settings(config, 0) if cap > 1 else _final_settings(config)
    outliers = _reconstruct_volume(acquisition, state, config, timer, 0, settings)
    records = [_record(0, "first", None, None, config, outliers, before, started)]
    bar.update()
    if cap == 1:
        bar.close()
        return records, None
    activity = _Activity.of(_registrable(acquisition, config, 1), state.poses)
    settled, index = False, 1
    while index < cap - 1:
        record, outliers, settled = _alignment_round(
            acquisition, state, config, timer, activity, index, outliers
        )
        records.append(record)
        bar.update()
        bar.set_postfix(moving=record.moving, ncc=f"{record.ncc:.3f}")
        index += 1
        if settled:
            break
    verdict = _log_verdict(records, index, settled, activity, config)
    # The final round is the last: a bar that stopped early ends full, not at a fraction.
    bar.total = index + 1
    records.append(_final_round(acquisition, state, config, timer, activity.single, index, settled))
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


def _registrable(acquisition: Acquisition, config: ReconstructionConfig, group_size: int) -> Tensor:
    """(N,) bool on the CPU: the slices a pass with ``group_size`` registers."""
    if group_size > 1:
        return torch.ones(len(acquisition.slices), dtype=torch.bool)
    return (acquisition.brain_pixels >= config.schedule.min_slice_pixels).cpu()


def _stage(group_size: int) -> str:
    return "slices" if group_size == 1 else f"groups of {group_size}"


def _alignment_settings(config: ReconstructionConfig, round_index: int) -> tuple[float, int]:
    """(regularisation, CG iterations) of an adaptive round before the final one."""
    regularization = config.superres.regularization[:-1] or config.superres.regularization
    iterations = config.superres.iterations[:-1] or config.superres.iterations
    return (per_round(regularization, round_index), per_round(iterations, round_index))


def _final_settings(config: ReconstructionConfig) -> tuple[float, int]:
    """(regularisation, CG iterations) of the adaptive schedule's final round."""
    return (config.superres.regularization[-1], config.superres.iterations[-1])


def run_rounds(
    slices: SliceSet,
    config: ReconstructionConfig,
    init: tuple[str, ...],
    timer: PhaseTimer,
    progress: bool,
) -> ReconstructionResult:
    """The rounds from the slices' starting poses to the result (the schedule ``config`` names).

    Args:
        slices: The slices at their starting poses (and the frame of those poses).
        config: Settings.
        init: Per stack, the start it kept (for the result).
        timer: The run's phase timer (the rounds add their phases).
        progress: Show a progress bar.

    Returns:
        The result, in the frame of the starting poses.
    """
    adaptive = config.schedule.kind == "adaptive"
    with timer.phase("setup"):
        grid = output_grid(slices, config.grid.resolution_mm)
        band = config.superres.background_mm if adaptive else (0.0, 0.0)
        acquisition = acquisition_model(slices, grid, band)
        poses = slices.poses
        points = acquisition.points(poses)
        volume = initial_volume(acquisition, points)
        state = _RoundState(
            poses=poses,
            points=points,
            background_points=acquisition.background_points(poses),
            pixel_w=torch.ones_like(acquisition.observed),
            slice_w=torch.ones(len(slices), device=acquisition.observed.device),
            excluded=torch.zeros(len(slices), dtype=torch.bool, device=acquisition.observed.device),
            volume=volume,
        )
        initial = volume.clone()
        log.info(
            "output grid %s at %.2f mm (%s frame), %s schedule",
            grid.shape,
            config.grid.resolution_mm,
            slices.frame,
            config.schedule.kind,
        )
    run = _adaptive_rounds if adaptive else _fixed_rounds
    records, converged = run(acquisition, state, config, timer, progress)
    with timer.phase("finish"):
        final = finalise(acquisition, state.volume, state.points, state.pixel_w)
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
