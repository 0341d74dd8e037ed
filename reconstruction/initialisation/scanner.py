"""The ``"scanner"`` start: every slice where the scanner put it (``--registration none``)."""

from __future__ import annotations

from svr.reconstruction.initialisation.choice import Start
from svr.reconstruction.slices import SliceSet

__all__ = ["scanner_start"]


def scanner_start(slices: SliceSet) -> Start:
    """The slices at their acquisition poses, in the scanner frame.

    Args:
        slices: All slices, at their scanner poses.

    Returns:
        The slices unchanged; every stack's choice ``"none"``.
    """
    return Start(slices, ("none",) * len(slices.stack_names))
