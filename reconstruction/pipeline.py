"""The reconstruction pipeline: slices -> starting poses -> rounds -> (the atlas's frame).

Phases (each timed and logged):
    1. slices: every stack cut into slices, each its own rigid body
       (:func:`~svr.reconstruction.slices.extract_slices`);
    2. initialisation: the start that ``config.initialisation.kind`` names
       (:func:`svr.reconstruction.initialisation.initialise`);
    3. rounds: slice-to-volume registration, outlier weights and super-resolution, as the
       schedule runs them (:func:`svr.reconstruction.schedule.run_rounds`);
    4. atlas frame: for a start in canonical space with atlases given, the volume brought into
       the frame of the atlas it fits (:func:`svr.reconstruction.atlas_frame.align_to_atlas`);
    5. mid-sagittal plane: a canonical volume levelled onto the brain's own mirror plane
       (:func:`svr.reconstruction.midplane.level_to_midplane`), any volume's mirror plane
       measured (:func:`svr.reconstruction.midplane.measure_symmetry`);
    6. verdict: whether the volume and its frame can be trusted
       (:func:`svr.reconstruction.verdict.assess`); a canonical frame that nothing tells apart from
       another, or whose mid-sagittal plane is not the brain's, is not claimed: the volume is
       written in the scanner frame instead.

:func:`reconstruct` is the entry point; :func:`reconstruct_from_poses` runs the rounds from poses
found elsewhere (another tool's, or the truth of a simulation).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import torch
from torch import Tensor

from svr.frames import Frame
from svr.models.network import SlicePoseNet
from svr.models.stack_pose import StackPoseNet
from svr.reconstruction.atlas_frame import align_to_atlas
from svr.reconstruction.config import LEARNED_STARTS, ReconstructionConfig
from svr.reconstruction.initialisation import initialise
from svr.reconstruction.midplane import level_to_midplane, measure_symmetry
from svr.reconstruction.result import ReconstructionResult, relabelled
from svr.reconstruction.schedule import run_rounds
from svr.reconstruction.slices import SliceSet, Stack, extract_slices, moved_from_stack
from svr.reconstruction.verdict import Verdict, VerdictConfig, assess
from svr.sampling.volume import CanonicalVolume, as_atlases
from svr.timing import PhaseTimer

__all__ = ["ATLAS_MAX_TURN_DEG", "reconstruct", "reconstruct_from_poses"]

log = logging.getLogger(__name__)

ATLAS_MAX_TURN_DEG = 15.0
"""The largest turn an atlas fit may make of a learned frame that has a clear margin (degrees)."""


def reconstruct(
    stacks: list[Stack],
    config: ReconstructionConfig | None = None,
    model: SlicePoseNet | StackPoseNet | None = None,
    atlases: CanonicalVolume | Sequence[CanonicalVolume] = (),
    device: str | torch.device = "cpu",
    progress: bool = True,
) -> ReconstructionResult:
    """Reconstruct a volume from prepared stacks.

    Args:
        stacks: The stacks (:func:`svr.reconstruction.stacks.load_stacks`).
        config: Settings; ``config.initialisation.kind`` chooses the start
            (:meth:`~svr.reconstruction.config.ReconstructionConfig.preset` gives each start's
            defaults).
        model: The network of a learned start: a stack-pose network
            (:func:`svr.models.stack_pose.load_stack_pose_model`) for ``"learned"``, a slice-pose
            network (:func:`svr.models.predict.load_pose_model`) for ``"learned-slices"``.
        atlases: Brains of about the fetus's age in canonical space, the preferred first (for
            example the fetus's age, then the weeks either side). Needed by the ``"atlas"``
            start; with any start in canonical space the final volume is brought into the first
            atlas's frame unless another fits it clearly better
            (:func:`svr.reconstruction.atlas_frame.align_to_atlas`).
        device: Where to compute.
        progress: Show a progress bar.

    Returns:
        The result: the volume in the canonical frame for a start in canonical space, in the
        scanner frame otherwise.

    Raises:
        ValueError: If the start needs a model or atlases it was not given, or atlases come with
            a start in the scanner frame.
    """
    config = config or ReconstructionConfig()
    atlases = as_atlases(atlases, "reconstruct", "atlases") if atlases else ()
    kind = config.initialisation.kind
    if atlases and kind not in LEARNED_STARTS:
        raise ValueError(
            f"reconstruct(): 'atlases' are used by the starts {LEARNED_STARTS}, not {kind!r}"
        )
    timer = PhaseTimer(logger=log)
    with timer.phase("slices"):
        slices = _slices(stacks, device)
    with timer.phase("initialisation"):
        start = initialise(slices, stacks, config, model, atlases)
    result = run_rounds(start.slices, config, start.choice, timer, progress)
    result = dataclasses.replace(
        result,
        initialisation_notes=start.notes,
        from_scanner=start.from_scanner,
        frame_margin=start.frame_margin,
    )
    if atlases:
        # A learned frame with a clear margin is not turned far by an atlas fit (NCC with an
        # atlas of another anatomy or contrast has near-equal optima in many frames).
        learned = (
            start.frame_margin is not None and start.frame_margin >= VerdictConfig().frame_margin
        )
        with timer.phase("atlas frame"):
            result = align_to_atlas(
                result, atlases, max_turn_deg=ATLAS_MAX_TURN_DEG if learned else None
            )
    result = _mirror_plane(result, timer)
    _report_exclusions(result)
    return _judged(result)


def _judged(result: ReconstructionResult) -> ReconstructionResult:
    """The result with its verdict; an untrusted canonical frame falls back to the scanner's."""
    verdict = assess(result)
    if verdict.frame == "untrusted" and result.from_scanner is not None:
        back = torch.linalg.inv(result.from_scanner.to(torch.float64))
        result = relabelled(result, back, "scanner")
        result = dataclasses.replace(result, from_scanner=None)
        reasons = (*verdict.reasons, "written in the scanner frame instead")
        status = "failed" if assess(result).status == "failed" else "warning"
        verdict = Verdict(status, "scanner", reasons)
    (log.warning if verdict.status != "ok" else log.info)("verdict: %s", verdict.line())
    return dataclasses.replace(result, verdict=verdict)


def reconstruct_from_poses(
    stacks: list[Stack],
    poses: Tensor,
    frame: Frame = "scanner",
    config: ReconstructionConfig | None = None,
    device: str | torch.device = "cpu",
    progress: bool = True,
) -> ReconstructionResult:
    """Reconstruct from given starting poses of every slice (``config.initialisation`` unused).

    Args:
        stacks: The stacks (:func:`svr.reconstruction.stacks.load_stacks`).
        poses: (N, 4, 4) starting poses of the slices that
            :func:`~svr.reconstruction.slices.extract_slices` cuts from ``stacks``, in its order:
            slice-plane mm -> ``frame`` mm.
        frame: The frame of ``poses`` (and of the result).
        config: Settings.
        device: Where to compute.
        progress: Show a progress bar.

    Returns:
        The result in ``frame``; every stack's start is ``"given"``.

    Raises:
        ValueError: If ``poses`` is not (N, 4, 4) for the stacks' N slices.
    """
    config = config or ReconstructionConfig()
    timer = PhaseTimer(logger=log)
    with timer.phase("slices"):
        slices = _slices(stacks, device)
    if tuple(poses.shape) != (len(slices), 4, 4):
        raise ValueError(
            f"reconstruct_from_poses(): 'poses' must be ({len(slices)}, 4, 4) for the stacks' "
            f"slices, got {tuple(poses.shape)}"
        )
    slices = slices.with_poses(poses.to(device), frame)
    result = run_rounds(slices, config, ("given",) * len(stacks), timer, progress)
    result = _mirror_plane(result, timer, level=False)
    _report_exclusions(result)
    return _judged(result)


def _mirror_plane(
    result: ReconstructionResult, timer: PhaseTimer, level: bool = True
) -> ReconstructionResult:
    """The result's mirror plane recorded; a canonical one levelled onto it if ``level``.

    Given poses (:func:`reconstruct_from_poses`) keep their frame: the plane is only measured.
    """
    with timer.phase("mid-sagittal plane"):
        if level and result.slices.frame == "canonical":
            return level_to_midplane(result)[0]
        return measure_symmetry(result)


def _slices(stacks: list[Stack], device: str | torch.device) -> SliceSet:
    slices = extract_slices(stacks).to(device)
    log.info("%d slices from %d stacks", len(slices), len(stacks))
    return slices


def _report_exclusions(result: ReconstructionResult) -> None:
    slices, excluded = result.slices, result.excluded.to(result.slices.device)
    moved = moved_from_stack(slices)
    for sid, name in enumerate(slices.stack_names):
        mine = moved[slices.stack_ids.cpu() == sid]
        if len(mine):
            log.info(
                "%s: slices moved from the stack's rigid pose by %.1f deg (median), %.1f (max); "
                "%d beyond 10 deg",
                name,
                float(mine.median()),
                float(mine.max()),
                int((mine > 10).sum()),
            )
        members = slices.stack_ids == sid
        total = int(members.sum())
        out = int((excluded & members).sum())
        if total and out == total:
            log.warning(
                "%s: all %d slices excluded (NCC below threshold); check its mask", name, total
            )
        elif out:
            log.info("%s: %d of %d slices excluded", name, out, total)
