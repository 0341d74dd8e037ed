"""Automatic fetal brain masks for thick-slice stacks: localise, then segment.

A clinical stack shows the whole maternal abdomen; the brain is a small part of it. A
:class:`~svr.masking.network.BrainMasker` holds two small 2D U-Nets
(:class:`~svr.models.segmentation.BrainUNet`) and :func:`segment_stack` runs them on each slice
of a stack:

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
   either side as channels (:func:`~svr.masking.canvas.neighbour_slices`), so that it knows
   where in the head a slice lies (the skull base, the vertex).
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

The canvases are :mod:`svr.masking.canvas`'s, the clean-up :mod:`svr.masking.morphology`'s, the
networks and their checkpoints :mod:`svr.masking.network`'s.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from svr.image import Image, largest_component
from svr.masking.canvas import (
    canvas_to_slices,
    neighbour_slices,
    normalise_stack,
    slices_to_canvas,
    tile_centres,
)
from svr.masking.config import BrainMaskConfig
from svr.masking.morphology import clean_up_mask
from svr.masking.network import BrainMasker
from svr.models.segmentation import BrainUNet

__all__ = ["BrainNotFoundError", "MaskResult", "segment_stack"]

log = logging.getLogger(__name__)


class BrainNotFoundError(ValueError):
    """No brain was found in a stack (the message names the stack)."""


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
    log.info("%s: automatic brain mask (network), %.1f ml", name, volume_ml)
    return MaskResult(torch.from_numpy(mask), probability, centre, volume_ml)
