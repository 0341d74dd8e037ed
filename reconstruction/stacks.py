"""Acquired stacks from NIfTI files, prepared for reconstruction: masked, normalised, cropped.

A stack is an ``(I, J, K)`` image whose slices are its k-planes (in-plane axes along array axes 0
and 1), in any orientation, posed in the scanner's world frame by its affine. Preparation
(:func:`load_stacks` for files, :func:`prepare_stacks` for images in memory), per stack:

1. **Mask.** A given mask on another grid is resampled onto the stack's (nearest neighbour, by
   world position, as :mod:`svr.models.predict` does); it must overlap the stack. Without masks, an
   automatic one, by ``StackConfig.auto_mask``: ``"network"`` runs the shipped brain-mask
   networks (:func:`svr.models.brain_mask.segment_stack`, meant for whole-uterus and cropped
   stacks; the shipped model is accurate on cropped ones, looser than manual masks on
   whole-uterus ones; a stack where no brain is found is an error naming it); ``"otsu"`` keeps
   voxels above the stack's Otsu threshold inside the region that every stack's field of view
   covers (each stack covering the boxes of its voxels), then the largest 3D connected component
   with its holes filled, which suits only stacks already cropped around the brain (the brain is
   the largest bright object seen by all stacks). With ``StackConfig.fuse_masks`` the network's
   masks of 3 or more stacks are then made to agree in 3D
   (:func:`svr.reconstruction.mask_fusion.fuse_stack_masks`).
2. **Crop.** In-plane (axes 0 and 1) to the mask's bounding box over all planes plus
   ``crop_margin_mm``, clipped to the array; along k to the planes from the first to the last
   with mask (a contiguous range; planes with an empty mask inside it are kept and dropped later
   by :func:`svr.reconstruction.slices.extract_slices`). The cropped affine maps crop voxel
   ``(0, 0, k')`` to the file's voxel ``(i0, j0, k_indices[k'])``.
3. **Bias field** (optional): N4 (SimpleITK) fitted on the in-mask voxels of the cropped stack,
   downsampled in-plane by ``n4_shrink_factor``, then divided out at full resolution.
4. **Intensities.** Divided by the 99th percentile of the in-mask voxels (the rule of
   :mod:`svr.sampling.volume`); voxels outside the mask are set to 0 and the unmasked intensities
   are not kept.

The slice thickness (FWHM of the through-plane PSF) defaults to the slice spacing (the norm of
the affine's third column), with a warning, as in NeSVoR.
"""

from __future__ import annotations

import logging
import math
import numbers
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
import SimpleITK as sitk  # noqa: N813 (the usual alias)
import torch
from scipy import ndimage
from skimage.filters import threshold_otsu
from torch import Tensor

from svr.image import (
    Image,
    ImageError,
    intensity_scale,
    largest_component,
    load_nifti,
    mask_on_grid,
)
from svr.reconstruction.slices import Stack

if TYPE_CHECKING:
    from svr.models.brain_mask import BrainMasker

__all__ = ["AUTO_MASKS", "AutoMask", "StackConfig", "load_stacks", "prepare_stacks"]

log = logging.getLogger(__name__)

AutoMask = Literal["otsu", "network"]
AUTO_MASKS: tuple[str, ...] = ("network", "otsu")
"""The automatic masks of stacks given without one (``StackConfig.auto_mask``)."""

_SHEAR_TOLERANCE = 1e-3  # |cos| of the angle between the in-plane axes treated as orthogonal


@dataclass(frozen=True)
class StackConfig:
    """How stacks are prepared (see the module docstring).

    Attributes:
        crop_margin_mm: In-plane margin kept around the mask's bounding box (mm, >= 0). The
            default 5 mm (a few voxels at fetal in-plane resolutions) keeps the mask's edge away
            from the array border, so that interpolation, the PSF and in-plane motion at the edge
            of the brain stay inside the array; the margin holds zeros (outside the mask).
        bias_correction: Whether to correct each stack's bias field with N4 before normalising.
        n4_shrink_factor: In-plane downsampling factor of the image N4 fits the field on (>= 1;
            the slices are already thick, so k is not downsampled).
        n4_iterations: Maximum iterations per N4 fitting level; its length is the number of
            levels (SimpleITK's default).
        auto_mask: How stacks without a mask get one: ``"otsu"`` or ``"network"`` (module
            docstring). The ``svr`` commands default to ``"network"``.
        fuse_masks: Whether the network's automatic masks are fused across the stacks (all of
            one fetus, at least 3; :mod:`svr.reconstruction.mask_fusion`). Needs
            ``auto_mask="network"``.
    """

    crop_margin_mm: float = 5.0
    bias_correction: bool = False
    n4_shrink_factor: int = 2
    n4_iterations: tuple[int, ...] = (50, 50, 50, 50)
    auto_mask: AutoMask = "otsu"
    fuse_masks: bool = False

    def __post_init__(self) -> None:
        if self.auto_mask not in AUTO_MASKS:
            raise ValueError(
                f"StackConfig: 'auto_mask' must be one of {', '.join(AUTO_MASKS)}, "
                f"got {self.auto_mask!r}"
            )
        if self.fuse_masks and self.auto_mask != "network":
            raise ValueError("StackConfig: 'fuse_masks' needs auto_mask='network'")
        if not (math.isfinite(self.crop_margin_mm) and self.crop_margin_mm >= 0):
            raise ValueError(
                f"StackConfig: 'crop_margin_mm' must be >= 0, got {self.crop_margin_mm}"
            )
        if self.n4_shrink_factor < 1:
            raise ValueError(
                f"StackConfig: 'n4_shrink_factor' must be >= 1, got {self.n4_shrink_factor}"
            )
        if not self.n4_iterations or min(self.n4_iterations) < 1:
            raise ValueError(
                "StackConfig: 'n4_iterations' must be a nonempty tuple of positive counts, "
                f"got {self.n4_iterations}"
            )


def load_stacks(
    stack_paths: Sequence[str | os.PathLike[str]],
    mask_paths: Sequence[str | os.PathLike[str]] | None = None,
    thicknesses: float | Sequence[float] | None = None,
    config: StackConfig | None = None,
    masker: BrainMasker | str | os.PathLike[str] | None = None,
    device: torch.device | str = "cpu",
) -> list[Stack]:
    """Read NIfTI stacks (and their masks) and prepare them for reconstruction.

    Args:
        stack_paths: The stacks, ``.nii`` or ``.nii.gz`` files (3D, or 4D with one volume).
        mask_paths: One brain mask per stack (voxels > 0.5 are brain; any grid that overlaps the
            stack), or ``None`` for the automatic masks of the module docstring.
        thicknesses: Slice thicknesses in mm: ``None`` (each stack's slice spacing, with a
            warning), one value for all stacks, or one per stack.
        config: Preparation settings; default :class:`StackConfig`'s.
        masker: The brain-mask networks for ``config.auto_mask == "network"``, or the model to
            load (:func:`svr.models.brain_mask.load_brain_masker`: ``"default"``, a folder),
            loaded after the stacks are checked; ``None`` for ``"default"``.
        device: Where those networks run.

    Returns:
        One :class:`~svr.reconstruction.slices.Stack` per file, in order, on the CPU: float32
        intensities and a bool mask on the cropped grid; ``name`` is the file path as given.

    Raises:
        ImageError: Beginning with the file's path, for a missing or unreadable file, one that is
            not NIfTI, not 3D, empty or has NaN/Inf voxels; a stack whose in-plane axes are not
            orthogonal or whose in-mask intensities are not positive; an empty mask, one that
            does not overlap its stack, or an empty automatic mask; a failed bias correction.
        ValueError: If there are no stacks, the number of masks or thicknesses does not match
            the number of stacks, or a thickness is not a positive number.
    """
    if mask_paths is not None and len(mask_paths) != len(stack_paths):
        raise ValueError(_count_mismatch("masks", len(mask_paths), len(stack_paths)))
    images = [load_nifti(path) for path in stack_paths]
    masks = None if mask_paths is None else [load_nifti(path) for path in mask_paths]
    return prepare_stacks(
        images,
        masks,
        thicknesses,
        config,
        names=[str(path) for path in stack_paths],
        mask_names=None if mask_paths is None else [str(path) for path in mask_paths],
        masker=masker,
        device=device,
    )


def prepare_stacks(
    images: Sequence[Image],
    masks: Sequence[Image] | None = None,
    thicknesses: float | Sequence[float] | None = None,
    config: StackConfig | None = None,
    names: Sequence[str] | None = None,
    mask_names: Sequence[str] | None = None,
    masker: BrainMasker | str | os.PathLike[str] | None = None,
    device: torch.device | str = "cpu",
) -> list[Stack]:
    """Prepare stacks held in memory (e.g. simulated ones); :func:`load_stacks` for files.

    Args:
        images: The ``(I, J, K)`` stacks (any device; the results are on the CPU).
        masks: One mask per stack (any grid), or ``None`` for automatic masks.
        thicknesses: As in :func:`load_stacks`.
        config: Preparation settings; default :class:`StackConfig`'s.
        names: The stacks' names for the results and messages; default ``"stack 0"``, ...
        mask_names: The masks' names for messages; default ``"mask of <stack name>"``.
        masker: As in :func:`load_stacks`.
        device: As in :func:`load_stacks`.

    Returns:
        One prepared :class:`~svr.reconstruction.slices.Stack` per image.

    Raises:
        ImageError: Beginning with the stack's or mask's name (see :func:`load_stacks`).
        ValueError: For no stacks or a count mismatch of masks, names or thicknesses, a
            thickness that is not a positive number, or ``config.fuse_masks`` with fewer than 3
            stacks.
    """
    config = StackConfig() if config is None else config
    count = len(images)
    if count == 0:
        raise ValueError("no stacks given")
    names = [f"stack {n}" for n in range(count)] if names is None else list(names)
    for what, given in (("masks", masks), ("names", names), ("mask names", mask_names)):
        if given is not None and len(given) != count:
            raise ValueError(_count_mismatch(what, len(given), count))
    if mask_names is None:
        mask_names = [f"mask of {name}" for name in names]
    images = [image.to("cpu", torch.float32) for image in images]
    for image, name in zip(images, names, strict=True):
        _check_stack(image, name)
    widths = _thicknesses(thicknesses, images, names)
    if masks is None and config.auto_mask == "network":
        from svr.models.brain_mask import BrainMasker, load_brain_masker, segment_stack

        networks = (
            masker
            if isinstance(masker, BrainMasker)
            else load_brain_masker("default" if masker is None else masker, device)
        )
        brains, probabilities = [], []
        for image, name in zip(images, names, strict=True):
            result = segment_stack(image, networks, name=name, device=device)
            log.info("%s: automatic brain mask (network), %.0f ml", name, result.volume_ml)
            brains.append(result.mask)
            probabilities.append(result.probability)
        if config.fuse_masks:
            from svr.reconstruction.mask_fusion import fuse_stack_masks

            fused = fuse_stack_masks(
                images, brains, widths, names, device=device, probabilities=probabilities
            )
            brains = fused.masks
            log.info(
                "automatic brain masks fused across %d stacks (Dice with their own: %s)",
                count,
                ", ".join(f"{value:.3f}" for value in fused.agreement),
            )
    elif masks is None:
        brains = [
            _automatic_mask(image, images[:n] + images[n + 1 :], name)
            for n, (image, name) in enumerate(zip(images, names, strict=True))
        ]
    else:
        brains = [
            _given_mask(image, mask.to("cpu"), name, mask_name)
            for image, mask, name, mask_name in zip(images, masks, names, mask_names, strict=True)
        ]
    return [
        _prepare(image, brain, name, width, config)
        for image, brain, name, width in zip(images, brains, names, widths, strict=True)
    ]


def _count_mismatch(what: str, given: int, count: int) -> str:
    return f"got {given} {what} for {count} stacks; give one per stack"


def _check_stack(image: Image, name: str) -> None:
    """Reject non-finite intensities and non-rectangular slices (sheared in-plane axes)."""
    if not bool(torch.isfinite(image.data).all()):
        raise ImageError(
            f"{name}: {int((~torch.isfinite(image.data)).sum())} voxels are NaN or Inf"
        )
    u, v = image.affine[:3, 0], image.affine[:3, 1]
    cosine = float((u @ v).abs() / (u.norm() * v.norm()))
    if cosine > _SHEAR_TOLERANCE:
        raise ImageError(
            f"{name}: the affine's in-plane axes (columns 0 and 1) are not orthogonal "
            f"({math.degrees(math.acos(min(cosine, 1.0))):.3f} deg between them); slices must be "
            "rectangular"
        )


def _thicknesses(
    thicknesses: float | Sequence[float] | None, images: Sequence[Image], names: Sequence[str]
) -> list[float]:
    """One thickness (mm) per stack: given, or the slice spacing with a warning."""
    if thicknesses is None:
        widths = [float(image.spacing[2]) for image in images]
        for name, width in zip(names, widths, strict=True):
            log.warning(
                "%s: no slice thickness given; using the slice spacing, %.4g mm", name, width
            )
        return widths
    values = (
        [float(thicknesses)]
        if isinstance(thicknesses, numbers.Real | float)  # float: for the type checker
        else [float(t) for t in thicknesses]
    )
    if len(values) == 1:
        values = values * len(images)
    if len(values) != len(images):
        raise ValueError(
            f"got {len(values)} thicknesses for {len(images)} stacks; give one for all stacks "
            "or one per stack"
        )
    for name, value in zip(names, values, strict=True):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(
                f"{name}: the slice thickness must be a positive number of mm, got {value}"
            )
    return values


def _given_mask(image: Image, mask: Image, name: str, mask_name: str) -> Tensor:
    """The mask as an (I, J, K) bool tensor on the stack's grid, checked to be nonempty there."""
    if not bool((mask.data > 0.5).any()):
        raise ImageError(f"{mask_name}: the mask is empty")
    brain = mask_on_grid(mask, image)
    if not bool(brain.any()):
        raise ImageError(
            f"{mask_name}: the mask does not overlap its stack {name} (mask shape {mask.shape}, "
            f"stack shape {image.shape}; their affines place them apart)"
        )
    return brain


def _inside_fields_of_view(image: Image, others: Sequence[Image]) -> Tensor:
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


def _automatic_mask(image: Image, others: Sequence[Image], name: str) -> Tensor:
    """Otsu foreground inside all fields of view, largest 3D component, holes filled."""
    data = image.data.numpy()
    foreground = (data > threshold_otsu(data.ravel())) & _inside_fields_of_view(
        image, others
    ).numpy()
    if not foreground.any():
        raise ImageError(
            f"{name}: the automatic mask is empty (no voxel above the Otsu threshold inside the "
            "region all stacks cover); give a brain mask"
        )
    log.info("%s: automatic brain mask (otsu)", name)
    return torch.from_numpy(ndimage.binary_fill_holes(largest_component(foreground)))


def _span(present: Tensor, margin: int) -> tuple[int, int]:
    """``[first - margin, last + margin + 1)`` of the true entries of a 1D bool tensor, clipped."""
    where = torch.nonzero(present).flatten()
    return max(int(where[0]) - margin, 0), min(int(where[-1]) + margin + 1, len(present))


def _n4_correct(
    data: Tensor, mask: Tensor, spacing: Tensor, config: StackConfig, name: str
) -> Tensor:
    """Divide out the N4 bias field fitted on the positive in-mask voxels.

    Args:
        data: (I, J, K) float32 intensities.
        mask: (I, J, K) bool mask.
        spacing: (3,) voxel sizes (mm).
        config: The shrink factor and iterations.
        name: The stack's name for errors.

    Returns:
        (I, J, K) float32 corrected intensities.
    """
    # SimpleITK arrays are (z, y, x): NIfTI's (i, j, k) reversed.
    image = sitk.GetImageFromArray(data.numpy().T.copy())
    image.SetSpacing([float(s) for s in spacing])
    fit_mask = sitk.GetImageFromArray((mask & (data > 0)).numpy().T.astype(np.uint8))
    fit_mask.CopyInformation(image)
    shrink = [min(config.n4_shrink_factor, n) for n in data.shape[:2]] + [1]
    corrector = sitk.N4BiasFieldCorrectionImageFilter()
    corrector.SetMaximumNumberOfIterations(list(config.n4_iterations))
    try:
        corrector.Execute(sitk.Shrink(image, shrink), sitk.Shrink(fit_mask, shrink))
        log_field = sitk.GetArrayFromImage(corrector.GetLogBiasFieldAsImage(image)).T
    except RuntimeError as err:
        message = " ".join(str(err).split())
        raise ImageError(f"{name}: N4 bias-field correction failed: {message[:300]}") from err
    return data / torch.from_numpy(np.exp(log_field)).float()


def _prepare(
    image: Image, brain: Tensor, name: str, thickness: float, config: StackConfig
) -> Stack:
    """Crop, optionally bias-correct and normalise one stack (see the module docstring).

    Args:
        image: The (I, J, K) stack on the CPU.
        brain: (I, J, K) bool nonempty mask on its grid.
        name: The stack's name.
        thickness: Slice thickness (mm).
        config: Preparation settings.

    Returns:
        The prepared stack.
    """
    margins = [math.ceil(config.crop_margin_mm / float(s) - 1e-9) for s in image.spacing[:2]]
    i0, i1 = _span(brain.any(dim=2).any(dim=1), margins[0])
    j0, j1 = _span(brain.any(dim=2).any(dim=0), margins[1])
    k0, k1 = _span(brain.any(dim=1).any(dim=0), 0)
    data = image.data[i0:i1, j0:j1, k0:k1]
    mask = brain[i0:i1, j0:j1, k0:k1].clone()
    if config.bias_correction:
        data = _n4_correct(data, mask, image.spacing, config, name)
    try:
        scale = intensity_scale(data[mask], name)
    except ValueError as err:
        raise ImageError(str(err)) from err
    data = torch.where(mask, data / scale, torch.zeros_like(data)).float()
    shift = torch.eye(4, dtype=torch.float64)
    shift[:3, 3] = torch.tensor([i0, j0, k0], dtype=torch.float64)
    affine = image.affine.double() @ shift
    return Stack(
        name=name,
        image=Image(data, affine),
        mask=Image(mask, affine.clone()),
        thickness_mm=thickness,
        k_indices=torch.arange(k0, k1, dtype=torch.int64),
        full_shape=(image.shape[0], image.shape[1]),
        crop_origin=(i0, j0),
    )
