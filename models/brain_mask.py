"""Automatic fetal brain masks for thick-slice stacks: localise, then segment (issue 14).

A clinical stack shows the whole maternal abdomen; the brain is a small part of it. A
:class:`BrainMasker` holds two small 2D U-Nets (:class:`~svr.models.segmentation.BrainUNet`) and
:func:`segment_stack` runs them on each slice of a stack:

1. **Localise.** Every slice is resampled in-plane onto a square canvas of
   ``localiser_size`` pixels of ``localiser_mm`` (the whole field of view, coarse), the localiser
   predicts a brain probability, the probabilities go back onto the stack grid and the largest 3D
   connected component above ``threshold`` is the brain's rough extent. With
   ``localiser_tiles`` the canvases are tiles overlapping by half that cover the field of view
   (finer pixels than one canvas could hold) and their probabilities are blended with weights
   falling towards each tile's edge. None (or one smaller than
   ``min_volume_ml``) is a :class:`BrainNotFoundError` naming the stack, never an empty mask.
2. **Segment.** Every slice the brain may touch (``slice_margin`` beyond the localised extent,
   or every slice of the stack)
   is resampled onto a finer canvas (``segmenter_size`` pixels of ``segmenter_mm``) centred on
   the brain, the segmenter predicts the brain there (averaged with its prediction on the
   left-right flipped canvas) and the probabilities go back onto the stack grid. A 2.5D
   segmenter (``segmenter.in_channels`` = 1 + 2 c) sees each slice with its c neighbours on
   either side as channels (:func:`neighbour_slices`), so that it knows where in the head a
   slice lies (the skull base, the vertex).
3. **Clean up.** The largest 3D component is kept and holes are filled slice by slice; a piece
   of a slice stays only if it joins the brain through the neighbouring slices (per-slice
   consistency: the brain is one body through the stack). With ``opening_mm`` the mask is
   first opened in 3D by a ball of that radius (in mm, on the stack's anisotropic grid): parts
   thinner than the ball, such as a leak along the fluid beside the head or a piece of the body
   joined to the brain by a narrow bridge, are cut, while the brain's bulk is kept; the mask
   within ``regrow_mm`` of the opened one is then given back (the ragged edge that slice motion
   leaves, which the ball cannot reach into, but not the bulk of a leak). A mask under
   ``min_volume_ml``, over ``max_volume_ml`` or over ``max_stack_fraction`` of the stack (the
   segmenter taking the whole field of view) is a :class:`BrainNotFoundError` too.

Canvases are cut with the same function (:func:`slices_to_canvas`) at inference and when the
training examples are made (:mod:`svr.models.brain_mask_train`), so both see the same pixels.
Intensities are divided by the stack's 99th percentile of its positive voxels
(:func:`normalise_stack`). Frames: the canvas axes are the stack's array axes 0 and 1
(voxel i, j); its centre is a point of the stack's voxel grid.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor, nn
from torch.nn import functional

from svr.image import Image, intensity_scale, largest_component
from svr.models.checkpoint import (
    CheckpointError,
    load_checkpoint,
    resolve_model_path,
    save_checkpoint,
)
from svr.models.pretrained import DEFAULT_MODEL, brain_mask_model_path
from svr.models.segmentation import BrainUNet, SegmentationConfig
from svr.sampling._validation import is_finite_number

__all__ = [
    "BrainMaskConfig",
    "BrainMasker",
    "BrainNotFoundError",
    "MaskResult",
    "canvas_to_slices",
    "clean_up_mask",
    "load_brain_masker",
    "neighbour_slices",
    "normalise_stack",
    "open_mask",
    "save_brain_masker",
    "segment_stack",
    "slices_to_canvas",
    "tile_centres",
]

_ARCHITECTURE = "brain_masker"
log = logging.getLogger(__name__)


class BrainNotFoundError(ValueError):
    """No brain was found in a stack (the message names the stack)."""


@dataclass(frozen=True)
class BrainMaskConfig:
    """Canvases and thresholds of :func:`segment_stack` and the two networks' shapes.

    Attributes:
        localiser_mm: Pixel size of the localiser's canvas, mm, > 0.
        localiser_size: Side of the localiser's canvas, pixels (a multiple of 16).
        localiser_tiles: Whether the localiser's canvases are tiles covering the field of view
            (overlapping by half) rather than one canvas centred on it.
        segmenter_mm: Pixel size of the segmenter's canvas, mm, > 0.
        segmenter_size: Side of the segmenter's canvas, pixels (a multiple of 16).
        localiser: The localiser U-Net's shape (one input channel).
        segmenter: The segmenter U-Net's shape; ``in_channels`` = 1 + 2 c (odd) makes it 2.5D:
            each slice comes with its c neighbours on either side (:attr:`segmenter_context`).
        threshold: Probability above which a voxel is brain, in (0, 1).
        min_volume_ml: Smallest brain accepted by the localiser, millilitres (cm^3), >= 0.
        max_volume_ml: Largest mask accepted, millilitres, > ``min_volume_ml`` (a term fetal
            head holds about 500 ml).
        max_stack_fraction: Largest fraction of the stack's voxels a mask may cover, in (0, 1]
            (a brain fills at most about half of a box cropped tightly around it; a mask over
            most of the field of view is the segmenter failing, not a brain).
        slice_margin: Slices beyond the localised brain's first and last that are segmented
            too, >= 0; ``None`` segments every slice (then the 3D clean-up alone decides where
            the brain ends, so pieces of other anatomy the segmenter takes for brain in slices
            beyond it may stay when they touch it).
        percentile: Percentile of a stack's positive voxels that is mapped to 1, in (0, 100].
        opening_mm: Radius of the ball by which the clean-up opens the mask (erodes, then
            dilates), mm, > 0; ``None`` for no opening. Where the opening would leave less than
            half of the mask (a brain thinner than the ball, e.g. a stack with few slices
            through it), the mask is kept unopened.
        regrow_mm: After the opening, the voxels of the mask within this distance of the
            opened mask (mm, >= 0) are kept too.

    Raises:
        ValueError: On construction, naming the field, for an invalid value.
    """

    localiser_mm: float = 3.0
    localiser_size: int = 128
    segmenter_mm: float = 1.25
    segmenter_size: int = 128
    localiser: SegmentationConfig = field(default_factory=lambda: SegmentationConfig(8, 4))
    segmenter: SegmentationConfig = field(default_factory=lambda: SegmentationConfig(8, 4))
    threshold: float = 0.5
    min_volume_ml: float = 5.0
    max_volume_ml: float = 1000.0
    max_stack_fraction: float = 0.8
    slice_margin: int | None = 2
    percentile: float = 99.0
    localiser_tiles: bool = False
    opening_mm: float | None = None
    regrow_mm: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.localiser_tiles, bool):
            raise ValueError(
                "BrainMaskConfig: 'localiser_tiles' must be true or false, "
                f"got {self.localiser_tiles!r}"
            )
        for name in ("localiser_mm", "segmenter_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and value > 0):
                raise ValueError(f"BrainMaskConfig: '{name}' must be a number > 0, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"BrainMaskConfig: '{name}' must be finite, got {value!r}")
        if self.localiser.in_channels != 1:
            raise ValueError(
                "BrainMaskConfig: 'localiser.in_channels' must be 1, "
                f"got {self.localiser.in_channels!r}"
            )
        if self.segmenter.in_channels % 2 != 1:
            raise ValueError(
                "BrainMaskConfig: 'segmenter.in_channels' must be odd (a slice and as many "
                f"neighbours on either side), got {self.segmenter.in_channels!r}"
            )
        for name, net in (("localiser", self.localiser), ("segmenter", self.segmenter)):
            size = getattr(self, f"{name}_size")
            step = 2**net.depth
            if isinstance(size, bool) or not isinstance(size, int) or size < step or size % step:
                raise ValueError(
                    f"BrainMaskConfig: '{name}_size' must be a positive multiple of {step} "
                    f"(2 ** {name}.depth), got {size!r}"
                )
        if not 0 < self.threshold < 1:
            raise ValueError(
                f"BrainMaskConfig: 'threshold' must be in (0, 1), got {self.threshold!r}"
            )
        if self.slice_margin is not None and (
            isinstance(self.slice_margin, bool)
            or not (isinstance(self.slice_margin, int) and self.slice_margin >= 0)
        ):
            raise ValueError(
                "BrainMaskConfig: 'slice_margin' must be an integer >= 0 or null, "
                f"got {self.slice_margin!r}"
            )
        radius, regrow = self.opening_mm, self.regrow_mm
        if radius is not None and not (is_finite_number(radius) and radius > 0):
            raise ValueError(
                f"BrainMaskConfig: 'opening_mm' must be a finite number > 0 or null, got {radius!r}"
            )
        if not (is_finite_number(regrow) and regrow >= 0):
            raise ValueError(
                f"BrainMaskConfig: 'regrow_mm' must be a finite number >= 0, got {regrow!r}"
            )
        if not self.min_volume_ml >= 0:
            raise ValueError(
                f"BrainMaskConfig: 'min_volume_ml' must be >= 0, got {self.min_volume_ml!r}"
            )
        if not (is_finite_number(self.max_volume_ml) and self.max_volume_ml > self.min_volume_ml):
            raise ValueError(
                "BrainMaskConfig: 'max_volume_ml' must be a finite number > 'min_volume_ml' "
                f"({self.min_volume_ml!r}), got {self.max_volume_ml!r}"
            )
        if not (is_finite_number(self.max_stack_fraction) and 0 < self.max_stack_fraction <= 1):
            raise ValueError(
                "BrainMaskConfig: 'max_stack_fraction' must be in (0, 1], "
                f"got {self.max_stack_fraction!r}"
            )
        if not 0 < self.percentile <= 100:
            raise ValueError(
                f"BrainMaskConfig: 'percentile' must be in (0, 100], got {self.percentile!r}"
            )

    @property
    def segmenter_context(self) -> int:
        """Neighbouring slices on either side that the segmenter sees (0: 2D)."""
        return (self.segmenter.in_channels - 1) // 2

    def to_dict(self) -> dict[str, Any]:
        """The config as JSON-serialisable data."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BrainMaskConfig:
        """The config written by :meth:`to_dict`.

        Raises:
            ValueError: For unknown or invalid fields.
        """
        values = dict(data)
        for name in ("localiser", "segmenter"):
            if name in values:
                values[name] = SegmentationConfig(**values[name])
        try:
            return cls(**values)
        except TypeError as exc:
            raise ValueError(f"BrainMaskConfig: {exc}") from exc


class BrainMasker(nn.Module):
    """The localiser and the segmenter U-Nets with their :class:`BrainMaskConfig`.

    Args:
        config: Canvases and network shapes; ``None`` for ``BrainMaskConfig()``.

    Attributes:
        config: The configuration.
        localiser: Brain logits on the coarse whole-slice canvas (or its tiles).
        segmenter: Brain logits on the fine canvas centred on the brain.
    """

    def __init__(self, config: BrainMaskConfig | None = None) -> None:
        super().__init__()
        self.config = BrainMaskConfig() if config is None else config
        self.localiser = BrainUNet(self.config.localiser)
        self.segmenter = BrainUNet(self.config.segmenter)


@dataclass(frozen=True)
class MaskResult:
    """A stack's automatic brain mask.

    Attributes:
        mask: (I, J, K) bool brain mask on the stack's grid.
        probability: (I, J, K) float32 segmenter probability on the stack's grid.
        centre_voxel: (2,) float64 in-plane centre (voxel i, j) of the segmenter's canvases.
        volume_ml: The mask's volume, millilitres.
    """

    mask: Tensor
    probability: Tensor
    centre_voxel: Tensor
    volume_ml: float


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


@torch.no_grad()
def _predict(net: BrainUNet, canvases: Tensor, flip: bool, batch: int = 32) -> Tensor:
    """(K, 1, S, S) probabilities of (K, C, S, S) canvases.

    With ``flip``, averaged with the left-right flipped canvases' probabilities, flipped back.
    """
    out = []
    for start in range(0, canvases.shape[0], batch):
        x = canvases[start : start + batch]
        p = torch.sigmoid(net(x))
        if flip:
            p = 0.5 * (p + torch.sigmoid(net(x.flip(-1))).flip(-1))
        out.append(p)
    return torch.cat(out) if out else canvases.new_zeros((0, 1, *canvases.shape[2:]))


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


def _localise(net: BrainUNet, slices: Tensor, spacing: Tensor, cfg: BrainMaskConfig) -> Tensor:
    """(K, 1, I, J) localiser probabilities of (K, 1, I, J) normalised slices."""
    shape = (slices.shape[2], slices.shape[3])
    size, pixel = cfg.localiser_size, cfg.localiser_mm
    if not cfg.localiser_tiles:
        middle = torch.tensor([(shape[0] - 1) / 2, (shape[1] - 1) / 2], dtype=torch.float64)
        canvas = slices_to_canvas(slices, spacing, middle, size, pixel)
        return canvas_to_slices(_predict(net, canvas, flip=False), spacing, middle, pixel, shape)
    # Blending weights: a tent falling from 1 at a tile's centre to a small floor at its edge.
    ramp = 1.0 - (torch.arange(size, dtype=torch.float32) - (size - 1) / 2).abs() / (size / 2)
    ramp = ramp.clamp(min=0.05).to(slices.device)
    weight = (ramp[:, None] * ramp[None, :])[None, None]
    total = slices.new_zeros(slices.shape)
    norm = slices.new_zeros((1, 1, *shape))
    for centre in tile_centres(shape, spacing, size * pixel):
        canvas = slices_to_canvas(slices, spacing, centre, size, pixel)
        p = _predict(net, canvas, flip=False)
        total += canvas_to_slices(p * weight, spacing, centre, pixel, shape)
        norm += canvas_to_slices(weight, spacing, centre, pixel, shape)
    return total / norm.clamp(min=1e-6)


def segment_stack(
    stack: Image,
    masker: BrainMasker,
    name: str = "stack",
    device: torch.device | str | None = None,
) -> MaskResult:
    """The brain mask of one stack (module docstring: localise, segment, clean up).

    Args:
        stack: The stack (I, J, K), I, J >= 2; any intensity scale.
        masker: The networks and their config (moved to ``device`` for the call).
        name: The stack's name (its file), for errors and logs.
        device: Where the networks run; ``None`` for the masker's device.

    Returns:
        The mask on the stack's grid and the probabilities behind it.

    Raises:
        ValueError: Naming ``name``, if the stack has non-finite voxels, no positive voxel or an
            in-plane side below 2.
        BrainNotFoundError: Naming ``name``, if the localiser finds no brain of at least
            ``config.min_volume_ml``, the segmenter finds nothing where it was localised, or
            the mask is larger than ``config.max_volume_ml`` or ``config.max_stack_fraction``
            of the stack.
    """
    cfg = masker.config
    data = stack.data
    if data.dim() != 3 or data.shape[0] < 2 or data.shape[1] < 2:
        raise ValueError(f"{name}: expected a 3D stack with in-plane sides >= 2, got {data.shape}")
    if not bool(torch.isfinite(data).all()):
        raise ValueError(f"{name}: the stack has non-finite voxels (NaN or Inf)")
    if device is None:
        device = next(masker.parameters()).device
    masker = masker.to(device).eval()
    normalised = normalise_stack(data.cpu(), name, cfg.percentile)
    spacing = stack.spacing[:2].cpu().double()
    voxel_ml = float(stack.spacing.prod()) / 1000.0
    shape = (data.shape[0], data.shape[1])
    slices = normalised.permute(2, 0, 1)[:, None].to(device)  # (K, 1, I, J)

    # 1. Localise on the whole field of view.
    coarse = _localise(masker.localiser, slices, spacing, cfg)
    found = largest_component(coarse[:, 0].permute(1, 2, 0).cpu().numpy() > cfg.threshold)
    if found.sum() * voxel_ml < max(cfg.min_volume_ml, voxel_ml):
        raise BrainNotFoundError(
            f"{name}: no fetal brain found (the localiser's largest region is "
            f"{found.sum() * voxel_ml:.1f} ml, expected at least {cfg.min_volume_ml:g} ml); "
            "pass a mask with --stack-masks"
        )
    where = np.argwhere(found)
    centre = torch.from_numpy(where[:, :2].mean(axis=0)).double()
    margin = data.shape[2] if cfg.slice_margin is None else cfg.slice_margin
    first = max(int(where[:, 2].min()) - margin, 0)
    last = min(int(where[:, 2].max()) + margin, data.shape[2] - 1)

    # 2. Segment on fine canvases centred on the brain.
    chosen = neighbour_slices(slices, cfg.segmenter_context)[first : last + 1]
    canvas = slices_to_canvas(chosen, spacing, centre, cfg.segmenter_size, cfg.segmenter_mm)
    fine = _predict(masker.segmenter, canvas, flip=True)
    fine = canvas_to_slices(fine, spacing, centre, cfg.segmenter_mm, shape)
    probability = torch.zeros(data.shape, dtype=torch.float32)
    probability[:, :, first : last + 1] = fine[:, 0].permute(1, 2, 0).float().cpu()

    # 3. Clean up.
    mask = clean_up_mask(
        probability.numpy() > cfg.threshold,
        stack.spacing.cpu().double().numpy(),
        cfg.opening_mm,
        cfg.regrow_mm,
    )
    volume_ml = float(mask.sum()) * voxel_ml
    if volume_ml < max(cfg.min_volume_ml, voxel_ml):
        raise BrainNotFoundError(
            f"{name}: no fetal brain found (the segmented brain is {volume_ml:.1f} ml, expected "
            f"at least {cfg.min_volume_ml:g} ml); pass a mask with --stack-masks"
        )
    fraction = float(mask.mean())
    if volume_ml > cfg.max_volume_ml or fraction > cfg.max_stack_fraction:
        raise BrainNotFoundError(
            f"{name}: no fetal brain found (the segmented region is {volume_ml:.0f} ml and "
            f"{100 * fraction:.0f} % of the stack, expected at most {cfg.max_volume_ml:g} ml and "
            f"{100 * cfg.max_stack_fraction:g} %); pass a mask with --stack-masks"
        )
    log.info("%s: automatic brain mask of %.1f ml", name, volume_ml)
    return MaskResult(torch.from_numpy(mask), probability, centre, volume_ml)


def save_brain_masker(
    masker: BrainMasker,
    path: str | os.PathLike[str],
    provenance: dict[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a masker as a checkpoint folder (float16 safetensors + JSON config).

    Args:
        masker: The networks.
        path: The checkpoint folder to create.
        provenance: JSON data recorded beside the config (training command, data, figures).
        overwrite: Whether an existing folder may be replaced.

    Returns:
        The folder.
    """
    config = {"architecture": _ARCHITECTURE, "brain_mask": masker.config.to_dict()}
    if provenance is not None:
        config["provenance"] = provenance
    state = {k: v.detach().cpu() for k, v in masker.state_dict().items()}
    return save_checkpoint(path, state, config, half_precision=True, overwrite=overwrite)


def load_brain_masker(
    path_or_name: str | os.PathLike[str] = "default", device: torch.device | str = "cpu"
) -> BrainMasker:
    """Load a masker: ``"default"`` (the shipped one), a checkpoint folder or a run folder.

    Loading reads safetensors and JSON only; no code runs.

    Raises:
        CheckpointError: If the folder is missing, modified, or not a brain-mask model.
    """
    if str(path_or_name) == DEFAULT_MODEL:
        folder = brain_mask_model_path()
    else:
        folder = resolve_model_path(path_or_name)
    checkpoint = load_checkpoint(folder, device)
    if checkpoint.config.get("architecture") != _ARCHITECTURE:
        raise CheckpointError(
            folder,
            f"not a brain-mask model (architecture {checkpoint.config.get('architecture')!r}, "
            f"expected {_ARCHITECTURE!r})",
        )
    try:
        masker = BrainMasker(BrainMaskConfig.from_dict(checkpoint.config["brain_mask"]))
        masker.load_state_dict(checkpoint.state_dict)
    except (KeyError, ValueError, RuntimeError) as exc:
        raise CheckpointError(folder, f"invalid brain-mask model: {exc}") from exc
    return masker.to(device).eval()
