"""The slices' acquisition model on a volume grid, and which slices were acquired together.

:func:`acquisition_model` builds, once per reconstruction, what every step of a round shares: the
projectors that simulate the slices from a volume (the PSF along each slice's normal), the
observed pixel values, each slice's brain pixels and the band of background pixels around its
mask. :func:`slice_groups` and :func:`packet_neighbours` say which slices were acquired one after
another (interleaved packets), so that they can be registered together.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from svr.reconstruction.operators import SliceProjector, VolumeGrid
from svr.reconstruction.registration import SVR_PSF_SAMPLES
from svr.reconstruction.slices import SliceSet

__all__ = [
    "BACKGROUND_STRIDE",
    "Acquisition",
    "acquisition_model",
    "background_pixels",
    "packet_key",
    "packet_neighbours",
    "slice_groups",
]

# Background pixels are taken on a lattice of this step (pixels) in each slice.
BACKGROUND_STRIDE = 2


class Acquisition(NamedTuple):
    """The slices' acquisition model on a volume grid: what every step of a round shares.

    Built once per reconstruction by :func:`acquisition_model`. The slices' poses are not part of
    it: every step takes the current poses (or their grid points) as an argument.

    Attributes:
        slices: The slices (images, masks, spacing and thickness).
        grid: The volume grid; its affine maps voxel indices to the frame of the poses (mm).
        projector: The acquisition model with the default PSF (5 Gauss-Hermite nodes along the
            normal), for simulation, outlier rejection and super-resolution.
        svr_projector: The same with :data:`SVR_PSF_SAMPLES` nodes, for slice-to-volume
            registration.
        observed: (P,) observed values of the P modelled (masked) pixels, in ``projector``'s
            pixel order.
        brain_pixels: (N,) int64 number of masked pixels of each slice.
        background: The acquisition model of the background pixels
            (:func:`background_pixels`), or ``None`` for none.
    """

    slices: SliceSet
    grid: VolumeGrid
    projector: SliceProjector
    svr_projector: SliceProjector
    observed: Tensor
    brain_pixels: Tensor
    background: SliceProjector | None = None

    def points(self, poses: Tensor) -> Tensor:
        """(K, P, 3) float32 ``grid_sample`` coordinates of every PSF node of every modelled pixel.

        Args:
            poses: (N, 4, 4) slice poses: slice-plane mm -> the grid's frame (mm).
        """
        return self.projector.grid_points(poses)

    def background_points(self, poses: Tensor) -> Tensor | None:
        """(K, B, 3) grid coordinates of the background pixels, or ``None`` without them.

        Args:
            poses: (N, 4, 4) slice poses: slice-plane mm -> the grid's frame (mm).
        """
        return None if self.background is None else self.background.grid_points(poses)


def background_pixels(
    slices: SliceSet, inner_mm: float, outer_mm: float, stride: int = 1
) -> Tensor:
    """The pixels between ``inner_mm`` and ``outer_mm`` from each slice's mask, in its plane.

    A brain mask cuts the slice where the (blurred) brain fades out; the pixels just outside it
    still hold some brain (partial volume), those a little farther out hold none. The distance is
    the chessboard distance in pixels of the slices' smallest in-plane spacing.

    Args:
        slices: The slices.
        inner_mm: Pixels nearer to the mask than this are left out (mm, >= 0).
        outer_mm: Pixels up to this distance are kept (mm, >= ``inner_mm``).
        stride: Keep only the pixels whose array indices are both multiples of this (>= 1): the
            background is smooth, so a sparser band says as much for less work.

    Returns:
        (N, H, W) bool, none of them inside a mask; all false for ``outer_mm = 0``.
    """
    if stride < 1:
        raise ValueError(f"background_pixels(): 'stride' must be >= 1, got {stride}")
    if not 0 <= inner_mm <= outer_mm:
        raise ValueError(
            "background_pixels(): need 0 <= 'inner_mm' <= 'outer_mm', got "
            f"{inner_mm} and {outer_mm}"
        )
    pixel = float(slices.spacing_mm.min())

    def grown(mm: float) -> Tensor:
        width = round(mm / pixel)
        if width <= 0:
            return slices.masks
        return (
            torch.nn.functional.max_pool2d(
                slices.masks[:, None].float(), 2 * width + 1, stride=1, padding=width
            )[:, 0]
            > 0.5
        )

    band = grown(outer_mm) & ~grown(inner_mm)
    if stride > 1:
        lattice = torch.zeros_like(band[0])
        lattice[::stride, ::stride] = True
        band = band & lattice
    return band


def acquisition_model(
    slices: SliceSet, grid: VolumeGrid, background_mm: tuple[float, float] = (0.0, 0.0)
) -> Acquisition:
    """The acquisition model of ``slices`` on ``grid`` (the setup of the rounds).

    Args:
        slices: The slices; their poses' frame must be ``grid``'s frame.
        grid: The volume grid (:func:`svr.reconstruction.superres.output_grid` in
            :func:`svr.reconstruction.pipeline.reconstruct`).
        background_mm: ``(inner, outer)`` band of background pixels around the masks
            (:func:`background_pixels`); ``(0, 0)`` for none.

    Returns:
        The projectors, the observed pixel values and the slices' brain pixel counts.
    """
    projector = SliceProjector(grid, slices)
    band = background_pixels(slices, *background_mm, stride=BACKGROUND_STRIDE)
    return Acquisition(
        slices=slices,
        grid=grid,
        projector=projector,
        svr_projector=SliceProjector(grid, slices, psf_samples=SVR_PSF_SAMPLES),
        observed=projector.gather(slices.images),
        brain_pixels=slices.masks.flatten(1).sum(1),
        background=SliceProjector(grid, slices, pixels=band) if bool(band.any()) else None,
    )


def slice_groups(slices: SliceSet, packets: int, size: int) -> Tensor:
    """Groups of up to ``size`` slices acquired one after another, for hierarchical SVR.

    With ``packets`` interleaved packets per stack (slices ``k = p, p + packets, p + 2 packets,
    ...`` acquired in turn), slices of one packet that are neighbours in that order are
    neighbours in time, so under smooth fetal motion they moved alike. ``size = 1`` gives one
    group per slice.

    Args:
        slices: The slices.
        packets: Interleaved packets per stack (>= 1; 1 for sequential acquisition).
        size: Slices per group (>= 1).

    Returns:
        (N,) int64 group ids, consecutive from 0.
    """
    if size <= 1:
        return torch.arange(len(slices), device=slices.device)
    k = slices.slice_indices
    key = packet_key(slices, packets) * (int(k.max()) + 1) + (k // packets) // size
    return torch.unique(key, return_inverse=True)[1]


def packet_key(slices: SliceSet, packets: int) -> Tensor:
    """(N,) int64 the same for slices of one interleaved packet of one stack."""
    return slices.stack_ids * packets + slices.slice_indices % packets


def packet_neighbours(slices: SliceSet, packets: int) -> list[list[int]]:
    """Per slice, the slices acquired just before and after it in its stack's packet."""
    key = packet_key(slices, packets)
    order = torch.argsort(key * (int(slices.slice_indices.max()) + 1) + slices.slice_indices)
    out: list[list[int]] = [[] for _ in range(len(slices))]
    sorted_key = key[order].tolist()
    ranked = order.tolist()
    for a in range(len(ranked)):
        for b in (a - 1, a + 1):
            if 0 <= b < len(ranked) and sorted_key[b] == sorted_key[a]:
                out[ranked[a]].append(ranked[b])
    return out
