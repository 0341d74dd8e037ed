"""What a reconstruction produced (:func:`svr.reconstruction.pipeline.reconstruct`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from torch import Tensor

from svr.frames import Frame
from svr.geometry import se3_compose
from svr.image import Image
from svr.reconstruction.convergence import RoundRecord
from svr.reconstruction.slices import SliceSet
from svr.stamp import VerdictStamp

__all__ = ["ReconstructionResult", "Verdict", "relabelled"]


@dataclass(frozen=True)
class Verdict:
    """What :func:`svr.reconstruction.verdict.assess` found.

    Attributes:
        status: ``"ok"``, ``"warning"`` (something to look at) or ``"failed"`` (no usable volume).
        frame: ``"scanner"``, or for a canonical output ``"trusted"``, ``"uncertain"`` or
            ``"untrusted"``.
        reasons: Why, one phrase each (empty for ``"ok"`` and a trusted or scanner frame).
    """

    status: str
    frame: str
    reasons: tuple[str, ...] = ()

    def line(self) -> str:
        """One line for a log, a QA page or a table, e.g. ``"failed: not converged; ..."``."""
        head = VerdictStamp(self.status, self.frame).line()
        return head + (": " + "; ".join(self.reasons) if self.reasons else "")


@dataclass(frozen=True)
class ReconstructionResult:
    """What a reconstruction produced.

    Attributes:
        volume: The reconstructed float32 volume (world frame ``slices.frame``).
        mask: Its float32 brain mask (0/1) on the same grid.
        initial_volume: The first estimate (scattered-data approximation at the initial poses).
        slices: The slices with their final poses.
        slice_ncc: (N,) NCC of each observed slice with the slice simulated from ``volume``.
        slice_weights: (N,) EM slice-level inlier probability (1 without robust statistics).
        excluded: (N,) bool, slices left out of the final volume.
        initialisation: Per stack, the start it kept (``"stack"``, ``"scanner"``, ``"cnn"``,
            ``"packets"``, ``"given"``).
        timings_s: Wall time of each phase in seconds, in order.
        initialisation_notes: Per stack, why a learned or atlas start kept what it kept (support,
            NCC of each candidate); empty for the scanner and stack starts.
        rounds: What each round did (:class:`~svr.reconstruction.convergence.RoundRecord`).
        converged: ``"adaptive"``: whether the slices stopped moving before the cap on rounds
            (``None`` for the fixed schedule, or when no registration round ran before the final
            one: ``schedule.rounds`` 1 or 2).
        atlas_ncc: With atlases: the NCC of the output with each atlas given, in order, after its
            fit (empty without an atlas).
        atlas_chosen: The index of the atlas whose frame the output is in (``None`` without).
        from_scanner: (4, 4) float64, for a canonical output: the transform from the scanner frame
            (the template stack's world frame, which stack registration keeps) to the output's
            frame; ``None`` where the start gave none.
        frame_margin: The learned start's evidence for its frame (the stack-pose network's
            pooled logits over the runner-up frame's), or ``None``.
        atlas_margin: The atlas fit's NCC margin of the frame kept over the best distinct
            other, or ``None`` without an atlas.
        atlas_turn_deg: The turn (degrees) by which the atlas fit moved the frame, or would have
            moved it where the turn was refused, or ``None`` without an atlas.
        atlas_turn_applied: Whether that turn was applied (``False``: it went farther than a frame
            the learned stack poses support may be turned, and only the centring was kept), or
            ``None`` without an atlas.
        midplane_tilt_deg: The tilt (degrees) by which a canonical output was levelled onto the
            brain's own mid-sagittal plane (:mod:`svr.reconstruction.midplane`), or ``None``.
        mirror_correlation: The correlation of the volume with its mirror image about the
            brain's best mirror plane (:mod:`svr.reconstruction.midplane`; 1 for a perfectly
            symmetric volume), or ``None`` where not measured.
        mirror_tilt_deg: For a canonical output, that plane's angle (degrees) from the frame's
            mid-sagittal plane ``x = 0`` as it was measured (before any levelling), or ``None``.
        verdict: Whether the volume and its frame can be trusted
            (:class:`Verdict`), ``None`` until assessed.
    """

    volume: Image
    mask: Image
    initial_volume: Image
    slices: SliceSet
    slice_ncc: Tensor
    slice_weights: Tensor
    excluded: Tensor
    initialisation: tuple[str, ...]
    timings_s: dict[str, float] = field(default_factory=dict)
    initialisation_notes: tuple[str, ...] = ()
    rounds: tuple[RoundRecord, ...] = ()
    converged: bool | None = None
    atlas_ncc: tuple[float, ...] = ()
    atlas_chosen: int | None = None
    from_scanner: Tensor | None = None
    frame_margin: float | None = None
    atlas_margin: float | None = None
    atlas_turn_deg: float | None = None
    atlas_turn_applied: bool | None = None
    midplane_tilt_deg: float | None = None
    mirror_correlation: float | None = None
    mirror_tilt_deg: float | None = None
    verdict: Verdict | None = None


def relabelled(
    result: ReconstructionResult, transform: Tensor, frame: Frame | None = None
) -> ReconstructionResult:
    """The same reconstruction in another frame: every affine and slice pose moved by ``transform``.

    Nothing is resampled, so the volumes' values are unchanged.

    Args:
        result: The reconstruction.
        transform: (4, 4) rigid transform from the result's frame to the new one (mm).
        frame: The new frame's name (default: the result's).

    Returns:
        The result with the volume's, mask's and initial volume's affines, every slice pose and
        ``from_scanner`` premultiplied by ``transform``.
    """

    def moved(image: Image) -> Image:
        return Image(image.data, transform.to(image.affine) @ image.affine)

    slices = result.slices
    poses = se3_compose(transform.to(slices.poses)[None], slices.poses)
    from_scanner = result.from_scanner
    if from_scanner is not None:
        from_scanner = se3_compose(transform.to(from_scanner), from_scanner)
    return replace(
        result,
        volume=moved(result.volume),
        mask=moved(result.mask),
        initial_volume=moved(result.initial_volume),
        slices=slices.with_poses(poses, frame),
        from_scanner=from_scanner,
    )
