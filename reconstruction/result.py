"""What a reconstruction produced (:func:`svr.reconstruction.pipeline.reconstruct`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

from svr.image import Image
from svr.reconstruction.convergence import RoundRecord
from svr.reconstruction.slices import SliceSet

__all__ = ["ReconstructionResult"]


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
