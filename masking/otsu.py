"""The Otsu automatic mask, for stacks already cropped around the brain."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from scipy import ndimage
from skimage.filters import threshold_otsu
from torch import Tensor

from svr.image import Image, ImageError, largest_component

__all__ = ["inside_fields_of_view", "otsu_mask"]

log = logging.getLogger(__name__)


def inside_fields_of_view(image: Image, others: Sequence[Image]) -> Tensor:
    """(I, J, K) bool: voxels of ``image`` whose centres lie inside every image of ``others``.

    An image covers the boxes of its voxels: continuous indices in [-0.5, n - 0.5] on each axis.
    """
    axes = [torch.arange(n, dtype=torch.float64) for n in image.shape]
    inside = torch.ones(image.shape, dtype=torch.bool)
    for other in others:
        to_other = torch.linalg.solve(other.affine.double(), image.affine.double())  # voxel map
        for row, n in zip(to_other[:3], other.shape, strict=True):
            index = (
                row[0] * axes[0][:, None, None]
                + row[1] * axes[1][None, :, None]
                + row[2] * axes[2][None, None, :]
                + row[3]
            )
            inside &= (index >= -0.5) & (index <= n - 0.5)
    return inside


def otsu_mask(image: Image, others: Sequence[Image], name: str) -> Tensor:
    """Otsu foreground inside all fields of view, largest 3D component, holes filled.

    Args:
        image: The (I, J, K) stack, on the CPU.
        others: The other stacks of the fetus (their fields of view bound the mask).
        name: The stack's name, for messages.

    Returns:
        (I, J, K) bool mask on the stack's grid.

    Raises:
        ImageError: Naming ``name``, if no voxel is above the threshold inside the region.
    """
    data = image.data.numpy()
    foreground = (data > threshold_otsu(data.ravel())) & inside_fields_of_view(
        image, others
    ).numpy()
    if not foreground.any():
        raise ImageError(
            f"{name}: the automatic mask is empty (no voxel above the Otsu threshold inside the "
            "region all stacks cover); give a brain mask"
        )
    log.info("%s: automatic brain mask (otsu)", name)
    return torch.from_numpy(ndimage.binary_fill_holes(largest_component(foreground)))
