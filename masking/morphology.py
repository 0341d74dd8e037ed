"""Mask morphology of the automatic brain masks: one body, opened by a ball, holes filled."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from svr.image import largest_component

__all__ = ["clean_up_mask", "open_mask"]


def open_mask(mask: np.ndarray, spacing: np.ndarray, radius_mm: float) -> np.ndarray:
    """A bool mask opened by a ball: the union of all balls of ``radius_mm`` inside it.

    Erosion and dilation are thresholds of Euclidean distance transforms in mm, so the ball is
    round on an anisotropic grid (e.g. 1.1 mm pixels, 3.3 mm slices). Outside the array counts
    as background.

    Args:
        mask: (I, J, K) bool.
        spacing: (3,) voxel size, mm (orthogonal axes).
        radius_mm: The ball's radius, mm, > 0.

    Returns:
        (I, J, K) bool, a subset of ``mask``.
    """
    sampling = np.asarray(spacing, dtype=np.float64)
    pad = [(math.ceil(radius_mm / step) + 1,) * 2 for step in sampling]
    padded = np.pad(mask.astype(bool), pad)
    core = ndimage.distance_transform_edt(padded, sampling=sampling) > radius_mm
    if not core.any():
        return np.zeros_like(mask, dtype=bool)
    opened = ndimage.distance_transform_edt(~core, sampling=sampling) <= radius_mm
    inner = tuple(slice(before, before + n) for (before, _), n in zip(pad, mask.shape, strict=True))
    return opened[inner] & mask


def clean_up_mask(
    brain: np.ndarray,
    spacing: np.ndarray,
    opening_mm: float | None = None,
    regrow_mm: float = 0.0,
) -> np.ndarray:
    """The clean-up of :func:`segment_stack`: one body, optionally opened, holes filled.

    Keeping one face-connected body is the per-slice consistency: a piece of a slice stays only
    if it joins the brain through the neighbouring slices. With ``opening_mm`` the component is
    first opened (:func:`open_mask`), the largest component of the result kept with the
    component's voxels within ``regrow_mm`` of it, unless the opened part is less than half of
    the component.

    Args:
        brain: (I, J, K) bool, the thresholded probabilities on a stack's grid.
        spacing: (3,) voxel size, mm.
        opening_mm: Radius of the opening's ball, mm; ``None`` for no opening.
        regrow_mm: Distance from the opened mask within which voxels are given back, mm.

    Returns:
        (I, J, K) bool mask (empty only if ``brain`` is).
    """
    body = largest_component(brain)
    if opening_mm is not None and body.any():
        box = ndimage.find_objects(body.astype(np.uint8))[0]  # (all of it; distances stay exact)
        part = body[box]
        opened = largest_component(open_mask(part, spacing, opening_mm))
        if opened.sum() >= 0.5 * part.sum():
            if regrow_mm > 0:
                near = ndimage.distance_transform_edt(~opened, sampling=spacing) <= regrow_mm
                opened = largest_component(part & near)
            body = np.zeros_like(body)
            body[box] = opened
    for k in range(body.shape[2]):
        body[:, :, k] = ndimage.binary_fill_holes(body[:, :, k])
    return body
