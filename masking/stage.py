"""The masking stage: masks for stacks given without one, before they are prepared.

``masks = auto_masks(images, config)`` then
``prepare_stacks(images, masks, ...)`` (:func:`svr.reconstruction.stacks.prepare_stacks`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence

import torch

from svr.image import Image
from svr.masking.config import MaskingConfig
from svr.masking.fuse import fuse_stack_masks
from svr.masking.network import BrainMasker, load_brain_masker
from svr.masking.otsu import otsu_mask
from svr.masking.segment import segment_stack
from svr.reconstruction.stacks import check_stack

__all__ = ["auto_masks"]

log = logging.getLogger(__name__)


def auto_masks(
    images: Sequence[Image],
    config: MaskingConfig | None = None,
    names: Sequence[str] | None = None,
    thicknesses: float | Sequence[float] | None = None,
    masker: BrainMasker | str | os.PathLike[str] | None = None,
    device: torch.device | str = "cpu",
) -> list[Image]:
    """A brain mask for each stack of one fetus (:class:`~svr.masking.config.MaskingConfig`).

    Args:
        images: The ``(I, J, K)`` stacks as read (any device).
        config: How; default :class:`~svr.masking.config.MaskingConfig`'s (the networks).
        names: The stacks' names for messages and logs; default ``"stack 0"``, ...
        thicknesses: Slice thickness (mm) for the fusion: one for all stacks, one per stack, or
            ``None`` for each stack's slice spacing (with a warning), as
            :func:`~svr.reconstruction.stacks.prepare_stacks` takes it.
        masker: The brain-mask networks, or the model to load
            (:func:`~svr.masking.network.load_brain_masker`: ``"default"``, a folder), loaded
            after the stacks are checked; ``None`` for ``"default"``.
        device: Where the networks run.

    Returns:
        One mask per stack on its grid: an :class:`~svr.image.Image` of bool voxels with the
        stack's affine, on the CPU.

    Raises:
        ImageError: Naming the stack, for non-finite voxels, sheared slices or an empty Otsu mask.
        BrainNotFoundError: Naming the stack, where the networks find no brain.
        ValueError: For no stacks, a count mismatch of names or thicknesses, or fusion of fewer
            than 3 stacks.
    """
    config = MaskingConfig() if config is None else config
    count = len(images)
    if count == 0:
        raise ValueError("no stacks given")
    names = [f"stack {n}" for n in range(count)] if names is None else list(names)
    if len(names) != count:
        raise ValueError(f"got {len(names)} names for {count} stacks; give one per stack")
    images = [image.to("cpu", torch.float32) for image in images]
    for image, name in zip(images, names, strict=True):
        check_stack(image, name)
    if config.method == "otsu":
        brains = [
            otsu_mask(image, images[:n] + images[n + 1 :], name)
            for n, (image, name) in enumerate(zip(images, names, strict=True))
        ]
    else:
        networks = (
            masker
            if isinstance(masker, BrainMasker)
            else load_brain_masker("default" if masker is None else masker, device)
        )
        brains, probabilities = [], []
        for image, name in zip(images, names, strict=True):
            result = segment_stack(image, networks, name=name, device=device)
            brains.append(result.mask)
            probabilities.append(result.probability)
        if config.fuse:
            fused = fuse_stack_masks(
                images,
                brains,
                thicknesses,
                names,
                config.fusion,
                device=device,
                probabilities=probabilities,
            )
            brains = fused.masks
            log.info(
                "automatic brain masks fused across %d stacks (Dice with their own: %s)",
                count,
                ", ".join(f"{value:.3f}" for value in fused.agreement),
            )
    return [Image(brain, image.affine) for brain, image in zip(brains, images, strict=True)]
