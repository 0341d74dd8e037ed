"""The masking stage: a brain mask for every stack given without one, before preparation.

A reconstruction reads its stacks, masks them, then prepares them::

    from svr.image import load_nifti
    from svr.masking import MaskingConfig, auto_masks
    from svr.reconstruction.stacks import prepare_stacks

    images = [load_nifti(path) for path in paths]
    masks = auto_masks(images, MaskingConfig(fuse=True), names=paths, thicknesses=3.0)
    stacks = prepare_stacks(images, masks, 3.0, names=paths)

Homes:

* :mod:`svr.masking.config`: :class:`MaskingConfig` (which method, whether to fuse),
  :class:`BrainMaskConfig` (the networks' canvases and thresholds), :class:`MaskFusionConfig`;
* :mod:`svr.masking.stage`: :func:`auto_masks`, the stage;
* :mod:`svr.masking.segment`: :func:`segment_stack`, one stack through the networks (localise,
  segment, clean up);
* :mod:`svr.masking.network`: the two U-Nets (:class:`BrainMasker`) and their checkpoints;
* :mod:`svr.masking.canvas`: the canvases the networks see;
* :mod:`svr.masking.morphology`: the clean-up (one body, opening, holes filled);
* :mod:`svr.masking.otsu`: the Otsu mask, for stacks cropped around the brain;
* :mod:`svr.masking.fuse`: the masks of one fetus's stacks made to agree in 3D;
* :mod:`svr.masking.train`: training the networks on simulated scenes.
* :mod:`svr.masking.recipe`: a training run of both networks, and the model folder it makes
  (``svr train-brain-mask``).

The stage sits above stack preparation and registration (:mod:`svr.reconstruction`), which the
fusion uses, and below the command line; nothing in :mod:`svr.reconstruction` imports it.
"""

from __future__ import annotations

from svr.masking.config import AUTO_MASKS, BrainMaskConfig, MaskFusionConfig, MaskingConfig
from svr.masking.fuse import MIN_FUSED_STACKS, FusedMasks, fuse_masks, fuse_stack_masks
from svr.masking.morphology import clean_up_mask, open_mask
from svr.masking.network import BrainMasker, load_brain_masker, save_brain_masker
from svr.masking.otsu import otsu_mask
from svr.masking.segment import BrainNotFoundError, MaskResult, segment_stack
from svr.masking.stage import auto_masks

__all__ = [
    "AUTO_MASKS",
    "MIN_FUSED_STACKS",
    "BrainMaskConfig",
    "BrainMasker",
    "BrainNotFoundError",
    "FusedMasks",
    "MaskFusionConfig",
    "MaskResult",
    "MaskingConfig",
    "auto_masks",
    "clean_up_mask",
    "fuse_masks",
    "fuse_stack_masks",
    "load_brain_masker",
    "open_mask",
    "otsu_mask",
    "save_brain_masker",
    "segment_stack",
]
