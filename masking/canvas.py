"""Canvases of the brain-mask networks: a stack's slices resampled onto square pixel grids.

Canvases are cut with the same function (:func:`slices_to_canvas`) at inference
(:func:`svr.masking.segment.segment_stack`) and when the training examples are made
(:mod:`svr.masking.train`), so both see the same pixels. Intensities are divided by the stack's
99th percentile of its positive voxels (:func:`normalise_stack`). Frames: the canvas axes are the
stack's array axes 0 and 1 (voxel i, j); its centre is a point of the stack's voxel grid.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.nn import functional

from svr.image import intensity_scale

__all__ = [
    "canvas_to_slices",
    "neighbour_slices",
    "normalise_stack",
    "slices_to_canvas",
    "tile_centres",
]


def normalise_stack(data: Tensor, name: str, percentile: float = 99.0) -> Tensor:
    """A stack's intensities divided by the ``percentile``-th percentile of its positive voxels.

    Args:
        data: (I, J, K) intensities.
        name: The stack's name, for errors.
        percentile: In (0, 100].

    Returns:
        (I, J, K) float32.

    Raises:
        ValueError: Naming ``name``, if no voxel is positive.
    """
    values = data[data > 0]
    if values.numel() > 1_000_000:  # a fixed subsample: the same value every run
        values = values[:: values.numel() // 1_000_000 + 1]
    return (data / intensity_scale(values, name, percentile)).float()


def _canvas_axis(centre: Tensor, size: int, pixel_mm: float, spacing: Tensor) -> Tensor:
    """(2, size) stack voxel coordinates (i, j) of a canvas's pixel rows and columns."""
    offsets = (torch.arange(size, dtype=torch.float64) - (size - 1) / 2) * pixel_mm
    return centre.to(torch.float64)[:, None] + offsets[None] / spacing.to(torch.float64)[:, None]


def neighbour_slices(slices: Tensor, context: int) -> Tensor:
    """Each slice with its ``context`` neighbours on either side as channels (2.5D input).

    Args:
        slices: (K, 1, I, J) slices in stack order (array axis 2).
        context: Neighbours on either side, >= 0.

    Returns:
        (K, 1 + 2 context, I, J): channel c of slice k is slice ``k - context + c``, the first
        and last slices repeated beyond the stack's ends; ``slices`` itself for ``context`` 0.

    Raises:
        ValueError: If ``slices`` is not (K, 1, I, J) with K >= 1 or ``context`` is negative.
    """
    if slices.dim() != 4 or slices.shape[1] != 1 or slices.shape[0] < 1:
        raise ValueError(
            f"neighbour_slices(): 'slices' must be (K, 1, I, J) with K >= 1, "
            f"got {tuple(slices.shape)}"
        )
    if isinstance(context, bool) or not isinstance(context, int) or context < 0:
        raise ValueError(f"neighbour_slices(): 'context' must be an integer >= 0, got {context!r}")
    if context == 0:
        return slices
    k = slices.shape[0]
    offsets = torch.arange(-context, context + 1, device=slices.device)
    index = (torch.arange(k, device=slices.device)[:, None] + offsets[None]).clamp(0, k - 1)
    return slices[:, 0][index]


def slices_to_canvas(
    slices: Tensor,
    spacing: Tensor,
    centre: Tensor,
    size: int,
    pixel_mm: float,
    mode: str = "bilinear",
) -> Tensor:
    """Resample stack slices in-plane onto square canvases of ``size`` pixels of ``pixel_mm``.

    Shrinking by a factor f >= 1.5 first averages f x f neighbourhoods (anti-aliasing).

    Args:
        slices: (K, C, I, J) slices (array axes 0 and 1 of the stack), I, J >= 2.
        spacing: (2,) in-plane voxel size of the stack (axes 0 and 1), mm.
        centre: (2,) or (K, 2) canvas centre in stack voxel coordinates (i, j).
        size: Canvas side, pixels.
        pixel_mm: Canvas pixel size, mm.
        mode: ``"bilinear"`` or ``"nearest"``.

    Returns:
        (K, C, size, size); zeros outside the stack. Canvas row a, column b is stack voxel
        ``(i, j) = centre + ((a, b) - (size - 1) / 2) * pixel_mm / spacing``.

    Raises:
        ValueError: If ``slices`` is not (K, C, I, J) with I, J >= 2.
    """
    if slices.dim() != 4 or slices.shape[2] < 2 or slices.shape[3] < 2:
        raise ValueError(
            f"slices_to_canvas(): 'slices' must be (K, C, I, J) with I, J >= 2, "
            f"got {tuple(slices.shape)}"
        )
    k, _, rows, cols = slices.shape
    factor = pixel_mm / float(spacing.min())
    if factor >= 1.5 and mode == "bilinear":
        kernel = int(factor)
        slices = functional.avg_pool2d(
            slices, kernel, stride=1, padding=kernel // 2, count_include_pad=False
        )[..., :rows, :cols]
    grids = []
    for c in centre.reshape(-1, 2):
        i, j = _canvas_axis(c, size, pixel_mm, spacing)
        y = (2 * i / (rows - 1) - 1)[:, None].expand(size, size)
        x = (2 * j / (cols - 1) - 1)[None, :].expand(size, size)
        grids.append(torch.stack([x, y], dim=-1))
    grid = torch.stack(grids).to(slices.dtype).to(slices.device).expand(k, size, size, 2)
    return functional.grid_sample(slices, grid, mode=mode, padding_mode="zeros", align_corners=True)


def canvas_to_slices(
    canvas: Tensor,
    spacing: Tensor,
    centre: Tensor,
    pixel_mm: float,
    shape: tuple[int, int],
) -> Tensor:
    """Map canvases made by :func:`slices_to_canvas` back onto the stack's in-plane grid.

    Args:
        canvas: (K, C, S, S) values on the canvases (bilinear interpolation; zeros outside).
        spacing: (2,) in-plane voxel size of the stack, mm.
        centre: (2,) or (K, 2) canvas centre in stack voxel coordinates (i, j).
        pixel_mm: Canvas pixel size, mm.
        shape: (I, J) of the stack.

    Returns:
        (K, C, I, J).
    """
    k, _, size, _ = canvas.shape
    rows, cols = shape
    centres = centre.reshape(-1, 2).to(torch.float64).expand(k, 2)
    spacing = spacing.to(torch.float64)
    i = torch.arange(rows, dtype=torch.float64)
    j = torch.arange(cols, dtype=torch.float64)
    a = (i[None] - centres[:, :1]) * spacing[0] / pixel_mm + (size - 1) / 2  # (K, I)
    b = (j[None] - centres[:, 1:]) * spacing[1] / pixel_mm + (size - 1) / 2  # (K, J)
    y = (2 * a / (size - 1) - 1)[:, :, None].expand(k, rows, cols)
    x = (2 * b / (size - 1) - 1)[:, None, :].expand(k, rows, cols)
    grid = torch.stack([x, y], dim=-1).to(canvas.dtype).to(canvas.device)
    return functional.grid_sample(
        canvas, grid, mode="bilinear", padding_mode="zeros", align_corners=True
    )


def tile_centres(shape: tuple[int, int], spacing: Tensor, tile_mm: float) -> Tensor:
    """Centres of square tiles overlapping by half that cover a slice's field of view.

    Args:
        shape: (I, J) of the stack.
        spacing: (2,) in-plane voxel size, mm.
        tile_mm: Side of a tile, mm, > 0.

    Returns:
        (T, 2) float64 centres in stack voxel coordinates (i, j): along each axis, the fewest
        centres spaced at most ``tile_mm / 2`` apart whose tiles reach both edges (one centre,
        the middle, where a tile covers the axis).
    """
    axes = []
    for n, step in zip(shape, spacing.tolist(), strict=True):
        extent = n * step  # voxel edges at -0.5 and n - 0.5
        count = max(math.ceil(2 * (extent - tile_mm) / tile_mm), 0) + 1
        if count == 1:
            axes.append(torch.tensor([(n - 1) / 2], dtype=torch.float64))
        else:
            first = tile_mm / 2 / step - 0.5
            axes.append(torch.linspace(first, n - 1 - first, count, dtype=torch.float64))
    return torch.cartesian_prod(*axes).reshape(-1, 2)
