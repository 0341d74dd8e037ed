"""Whether a reconstruction can be trusted, said plainly: its volume, and the frame it is in.

A reconstruction can end without a usable volume (slices that never settled, stacks that do not
agree) and a canonical output can be in a wrong frame (stacks whose estimates disagree, an atlas
of another anatomy or contrast that fits every frame about as well). :func:`assess` turns what the
run measured into a :class:`Verdict`: ``"ok"``, ``"warning"`` or ``"failed"`` for the volume, and
``"trusted"``, ``"uncertain"`` or ``"untrusted"`` for a canonical frame, each with its reasons. The
command line prints it as the last line of the log, the QA page shows it, and ``svr bids`` records
it in each participant's sidecar and counts the failed ones.

The evidence for a canonical frame:

* the learned start's *frame margin*: the stack-pose network's logits summed over the registered
  stacks at the chosen frame, minus the best sum at any frame more than 45 degrees away
  (:func:`~svr.reconstruction.initialisation.stack_pose.joint_frame`);
* the atlas fit's *margin*: the NCC of the volume with the atlas in the frame kept, minus the best
  NCC of a distinct frame (:func:`~svr.reconstruction.atlas_frame.align_to_atlas`).

A learned frame with a clear margin is not turned far by the atlas fit (the pipeline refuses a
turn over :data:`~svr.reconstruction.pipeline.ATLAS_MAX_TURN_DEG`); where the fit wanted such a
turn, the atlas does not confirm the frame, and the frame is at most uncertain.

A frame with neither margin above its threshold is uncertain (so is one whose evidence was not
measured: the slice-pose start without an atlas); with every measured margin at or below zero it
is untrusted, and the pipeline then writes the volume in the scanner frame instead.

The brain's own mirror plane (:mod:`svr.reconstruction.midplane`) checks both. A clear mirror
plane far from the canonical frame's mid-sagittal plane makes the frame untrusted whatever the
margins say. A volume with no clear mirror plane in any orientation is not a recognisable brain:
a warning alone, a failure with another sign (not converged, a poor fit, a stack apart), and its
frame cannot be more than uncertain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from svr.reconstruction.midplane import MIDPLANE_MAX_TILT_DEG, MIDPLANE_MIN_CORRELATION
from svr.reconstruction.result import ReconstructionResult, Verdict
from svr.validation import check_fraction, check_number

__all__ = ["Verdict", "VerdictConfig", "assess"]


@dataclass(frozen=True)
class VerdictConfig:
    """The thresholds of :func:`assess`.

    Attributes:
        min_mean_ncc: A volume whose slices' mean NCC with their simulation is below this fits
            its data poorly, in [-1, 1].
        min_stack_ncc: A stack whose slices' mean NCC is below this does not agree with the
            volume of the others, in [-1, 1].
        max_excluded: A volume that left out more than this fraction of its slices is failed.
        frame_margin: The learned frame margin (summed logits) at or above which the frame is
            trusted, >= 0.
        atlas_margin: The atlas fit's NCC margin at or above which the frame is trusted, >= 0.
        min_mirror_correlation: A volume whose best mirror plane correlates less than this has
            no clear mirror plane, in [-1, 1].
        max_mirror_tilt_deg: A clear mirror plane farther than this (degrees) from the canonical
            ``x = 0`` makes the frame untrusted, in [0, 90].

    Raises:
        ConfigFieldError: On construction, naming the field.
    """

    min_mean_ncc: float = 0.7
    min_stack_ncc: float = 0.5
    max_excluded: float = 0.5
    frame_margin: float = 4.0
    atlas_margin: float = 0.03
    min_mirror_correlation: float = MIDPLANE_MIN_CORRELATION
    max_mirror_tilt_deg: float = MIDPLANE_MAX_TILT_DEG

    def __post_init__(self) -> None:
        owner = "VerdictConfig"
        check_number(owner, "min_mean_ncc", self.min_mean_ncc, ge=-1, le=1)
        check_number(owner, "min_stack_ncc", self.min_stack_ncc, ge=-1, le=1)
        check_fraction(owner, "max_excluded", self.max_excluded)
        check_number(owner, "frame_margin", self.frame_margin, ge=0)
        check_number(owner, "atlas_margin", self.atlas_margin, ge=0)
        check_number(owner, "min_mirror_correlation", self.min_mirror_correlation, ge=-1, le=1)
        check_number(owner, "max_mirror_tilt_deg", self.max_mirror_tilt_deg, ge=0, le=90)


def _asymmetric(result: ReconstructionResult, config: VerdictConfig) -> bool:
    """Whether the volume has no clear mirror plane (as measured; ``False`` where not)."""
    mirror = result.mirror_correlation
    return mirror is not None and mirror < config.min_mirror_correlation


def _volume_reasons(result: ReconstructionResult, config: VerdictConfig) -> tuple[list[str], bool]:
    """The reasons to doubt the volume, and whether they make it a failure."""
    reasons: list[str] = []
    ncc = result.slice_ncc.double()
    kept = ~result.excluded.cpu()
    mean = float(ncc[kept].mean()) if bool(kept.any()) else float("nan")
    excluded = float((~kept).double().mean())
    poor = not mean >= config.min_mean_ncc
    if result.converged is False:
        reasons.append("not converged")
    if poor:
        reasons.append(f"slices fit the volume poorly (mean NCC {mean:.2f})")
    ids = result.slices.stack_ids.cpu()
    apart = []
    for sid, name in enumerate(result.slices.stack_names):
        members = ids == sid
        if bool(members.any()):
            stack_mean = float(ncc[members].mean())
            if stack_mean < config.min_stack_ncc:
                apart.append(f"{name.rsplit('/', 1)[-1]} ({stack_mean:.2f})")
    if apart:
        reasons.append("stacks disagree with the volume: " + ", ".join(apart))
    if excluded > config.max_excluded:
        reasons.append(f"{100 * excluded:.0f}% of slices excluded")
    asymmetric = _asymmetric(result, config)
    if asymmetric:
        reasons.append(
            "no clear mirror plane, not a recognisable brain "
            f"(mirror correlation {result.mirror_correlation:.2f})"
        )
    failed = (
        excluded > config.max_excluded
        or (poor and (result.converged is False or bool(apart)))
        or (asymmetric and (result.converged is False or poor or bool(apart)))
        or math.isnan(mean)  # nothing kept
    )
    return reasons, failed


def _frame(result: ReconstructionResult, config: VerdictConfig) -> tuple[str, list[str]]:
    """The canonical frame's trust and its reasons (``"scanner"`` for a scanner output)."""
    if result.slices.frame != "canonical":
        return "scanner", []
    tilt = result.mirror_tilt_deg
    if not _asymmetric(result, config) and tilt is not None and tilt > config.max_mirror_tilt_deg:
        return "untrusted", [f"the brain's mirror plane is {tilt:.0f} deg from the frame's x = 0"]
    learned, atlas = result.frame_margin, result.atlas_margin
    evidence = []
    if learned is not None:
        evidence.append(f"stack-pose margin {learned:.1f}")
    if atlas is not None:
        evidence.append(f"atlas-fit margin {atlas:.3f}")
    strong = (learned is not None and learned >= config.frame_margin) or (
        atlas is not None and atlas >= config.atlas_margin
    )
    if strong:
        doubts = []
        if _asymmetric(result, config):
            doubts.append("no mirror plane to check the frame by")
        if result.atlas_turn_applied is False and result.atlas_turn_deg is not None:
            doubts.append(
                f"the atlas fit disagrees: it would turn the frame by {result.atlas_turn_deg:.0f} "
                "deg (not applied)"
            )
        if doubts:
            return "uncertain", [*doubts[:-1], doubts[-1] + _listed(evidence)]
        return "trusted", []
    if not evidence:
        return "uncertain", ["the frame's evidence was not measured (give an atlas)"]
    none = (learned is None or learned <= 0) and (atlas is None or atlas <= 0)
    if none:
        return "untrusted", ["no evidence tells the frame apart" + _listed(evidence)]
    return "uncertain", ["thin evidence for the frame" + _listed(evidence)]


def _listed(evidence: list[str]) -> str:
    return f" ({', '.join(evidence)})" if evidence else ""


def assess(result: ReconstructionResult, config: VerdictConfig | None = None) -> Verdict:
    """The verdict on a finished reconstruction (see the module docstring).

    The volume is ``"failed"`` when more than ``max_excluded`` of its slices were left out, or
    its slices fit it poorly (mean NCC below ``min_mean_ncc``) and the rounds did not converge or
    a stack disagrees with it; any single sign alone is a ``"warning"``.

    Args:
        result: The reconstruction (its ``frame_margin`` and ``atlas_margin`` where measured).
        config: Thresholds (default :class:`VerdictConfig`).

    Returns:
        The verdict.
    """
    config = config or VerdictConfig()
    reasons, failed = _volume_reasons(result, config)
    frame, frame_reasons = _frame(result, config)
    status = "failed" if failed else "warning" if reasons or frame_reasons else "ok"
    return Verdict(status, frame, tuple(reasons + frame_reasons))
