"""The names of the coordinate frames that poses and volumes are given in.

A *frame* is a coordinate system in mm; a (4, 4) matrix between two frames is a *transform*
(``to_canonical``: scanner mm -> canonical mm), never a frame (``docs/conventions.md``).
"""

from __future__ import annotations

from typing import Literal, get_args

__all__ = ["FRAMES", "Frame"]

Frame = Literal["canonical", "scanner", "atlas"]
"""``"canonical"``: an atlas's world frame shifted so that the origin is the centre of its brain
mask. ``"scanner"``: the world frame of the acquired stacks (NIfTI RAS+ mm). ``"atlas"``: an
atlas volume's own world frame (as a simulation's truth tables give it)."""

FRAMES: tuple[str, ...] = get_args(Frame)
