"""What each reconstruction round did, and when the slices have stopped moving.

The adaptive schedule (:func:`svr.reconstruction.pipeline.reconstruct` with
``schedule="adaptive"``) registers the slices round after round while they still move: after each
slice-to-volume registration pass, every registered slice's pose change is measured (the angle of
its rotation change in degrees and the displacement of its centre in mm, the same measures as
:func:`svr.metrics.rotation_error_rad` and :func:`svr.metrics.translation_error_mm`), and the
slices have converged once at most ``converged_fraction`` of the registrable slices moved more
than ``converged_deg`` or ``converged_mm``; the rounds stop there, or with ``polish`` < 1 once
they also settle at those thresholds times ``polish``. Each round leaves a :class:`RoundRecord`
for the log, the QA figure and the ``--output-log`` summary, so that a user sees whether a run
converged.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from svr.geometry import se3_to_vector
from svr.metrics import rotation_error_rad, translation_error_mm

__all__ = ["RoundRecord", "pose_change", "round_summary", "verdict"]


@dataclass(frozen=True)
class RoundRecord:
    """One round of a reconstruction.

    Attributes:
        index: The round, from 0.
        stage: ``"first"`` (super-resolution only), ``"groups of N"`` (temporal neighbours
            registered together), ``"slices"`` (one by one) or ``"final"`` (the adaptive
            schedule's last registration, if any, and the volume restarted at the final poses).
        registered: Slices registered in this round (0 in the first round).
        moving: Registered slices that moved more than the convergence thresholds.
        rotation_deg: Median rotation change of the registered slices (degrees; 0 if none).
        rotation_p90_deg: Their 90th percentile (degrees).
        translation_mm: Median displacement of the registered slices' centres (mm).
        translation_p90_mm: Their 90th percentile (mm).
        ncc: Mean NCC of the slices with their simulation from the volume the round started
            from, at the round's poses (before its super-resolution); for the final round, from
            the final volume.
        excluded: Slices excluded after the round (NCC below the threshold).
        newly_excluded: Of those, slices that were not excluded after the previous round.
        seconds: Wall time of the round.
    """

    index: int
    stage: str
    registered: int
    moving: int
    rotation_deg: float
    rotation_p90_deg: float
    translation_mm: float
    translation_p90_mm: float
    ncc: float
    excluded: int
    newly_excluded: int
    seconds: float

    def line(self) -> str:
        """The round as one line of the log."""
        head = f"round {self.index} ({self.stage})"
        if self.registered:
            head += (
                f": {self.registered} slices registered, change median "
                f"{self.rotation_deg:.2f} deg / {self.translation_mm:.2f} mm (90th percentile "
                f"{self.rotation_p90_deg:.2f} deg / {self.translation_p90_mm:.2f} mm), "
                f"{self.moving} still moving"
            )
        return (
            f"{head}; mean NCC {self.ncc:.3f}, {self.excluded} excluded "
            f"({self.newly_excluded:+d}), {self.seconds:.1f} s"
        )


def pose_change(before: Tensor, after: Tensor) -> tuple[Tensor, Tensor]:
    """How far each slice moved between two sets of poses.

    Args:
        before: (N, 4, 4) poses (slice plane -> frame, mm).
        after: (N, 4, 4) poses in the same frame.

    Returns:
        (N,) rotation change in degrees (the angle of ``R_before^T R_after``) and (N,)
        displacement of the slice centre (the poses' origin) in mm, float64 on the CPU.
    """
    if before.shape != after.shape or before.shape[-2:] != (4, 4) or before.dim() != 3:
        raise ValueError(
            "pose_change(): 'before' and 'after' must both be (N, 4, 4), got "
            f"{tuple(before.shape)} and {tuple(after.shape)}"
        )
    a = se3_to_vector(before.detach().to("cpu", torch.float64))
    b = se3_to_vector(after.detach().to("cpu", torch.float64))
    return rotation_error_rad(a, b).rad2deg(), translation_error_mm(a, b)


def round_summary(
    rotation_deg: Tensor, translation_mm: Tensor
) -> tuple[float, float, float, float]:
    """(median, 90th percentile) of rotation changes, then of translation changes.

    Args:
        rotation_deg: (M,) rotation changes of the registered slices (degrees).
        translation_mm: (M,) their centre displacements (mm).

    Returns:
        ``(rotation median, rotation p90, translation median, translation p90)``; zeros for
        ``M = 0``.
    """
    if rotation_deg.numel() == 0:
        return (0.0, 0.0, 0.0, 0.0)
    q = torch.tensor([0.5, 0.9], dtype=torch.float64)
    r = torch.quantile(rotation_deg.double(), q)
    t = torch.quantile(translation_mm.double(), q)
    return (float(r[0]), float(r[1]), float(t[0]), float(t[1]))


def verdict(converged: bool | None) -> str:
    """How the rounds ended, in words: ``""`` when there is no verdict (``converged`` is ``None``).

    A run that did not converge ran up to its cap, so its number of rounds is the cap.
    """
    if converged is None:
        return ""
    if converged:
        return "converged"
    return "NOT converged: slices still moved at the cap on rounds (--iterations)"
