"""Shared core of the fetal SVR toolkit: SE(3) geometry, pose losses and metrics.

Conventions (see the conventions page of the documentation, ``docs/conventions.md``):
millimetres and radians, poses as ``(r_x, r_y, r_z, t_x, t_y, t_z)`` 6-vectors (rotation vector
first) or ``(..., 4, 4)`` matrices acting as ``x -> R x + t``, quaternions ``(w, x, y, z)`` with
``w >= 0``.
"""

__version__ = "0.2.0"
