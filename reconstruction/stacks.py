"""Acquired stacks from NIfTI files, prepared for reconstruction: masked, normalised, cropped.

A stack is an ``(I, J, K)`` image whose slices are its k-planes (in-plane axes along array axes 0
and 1), in any orientation, posed in the scanner's world frame by its affine. Preparation
(:func:`load_stacks` for files, :func:`prepare_stacks` for images in memory), per stack:

1. **Mask.** Each stack's mask, on any grid, is resampled onto the stack's (nearest neighbour,
   by world position, as :mod:`svr.models.predict` does); it must overlap the stack. Stacks
   given without masks get them from the masking stage first
   (:func:`svr.masking.auto_masks`: the brain-mask networks, or an Otsu threshold, optionally
   fused across the stacks).
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

import numpy as np
import torch
from torch import Tensor

from svr.image import (
    Image,
    ImageError,
    intensity_scale,
    load_nifti,
    mask_on_grid,
)
from svr.reconstruction.slices import Stack
from svr.validation import check_bool, check_int, check_int_tuple, check_number

__all__ = [
    "StackConfig",
    "check_stack",
    "load_stacks",
    "prepare_stacks",
    "slice_thicknesses",
]

log = logging.getLogger(__name__)

_NO_MASKS = (
    "'{what}' is None: give one mask per stack; stacks without masks get them from the masking "
    "stage first (svr.masking.auto_masks)"
)
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
    """

    crop_margin_mm: float = 5.0
    bias_correction: bool = False
    n4_shrink_factor: int = 2
    n4_iterations: tuple[int, ...] = (50, 50, 50, 50)

    def __post_init__(self) -> None:
        owner = "StackConfig"
        check_number(owner, "crop_margin_mm", self.crop_margin_mm, ge=0)
        check_bool(owner, "bias_correction", self.bias_correction)
        check_int(owner, "n4_shrink_factor", self.n4_shrink_factor, minimum=1)
        iterations = check_int_tuple(
            owner,
            "n4_iterations",
            self.n4_iterations,
            minimum=1,
            allow_empty=False,
            allow_list=True,
        )
        object.__setattr__(self, "n4_iterations", iterations)


def load_stacks(
    stack_paths: Sequence[str | os.PathLike[str]],
    mask_paths: Sequence[str | os.PathLike[str]],
    thicknesses: float | Sequence[float] | None = None,
    config: StackConfig | None = None,
) -> list[Stack]:
    """Read NIfTI stacks and their masks and prepare them for reconstruction.

    Stacks without masks: read them (:func:`svr.image.load_nifti`), make masks with
    :func:`svr.masking.auto_masks`, and call :func:`prepare_stacks`.

    Args:
        stack_paths: The stacks, ``.nii`` or ``.nii.gz`` files (3D, or 4D with one volume).
        mask_paths: One brain mask per stack (voxels > 0.5 are brain; any grid that overlaps the
            stack).
        thicknesses: Slice thicknesses in mm: ``None`` (each stack's slice spacing, with a
            warning), one value for all stacks, or one per stack.
        config: Preparation settings; default :class:`StackConfig`'s.

    Returns:
        One :class:`~svr.reconstruction.slices.Stack` per file, in order, on the CPU: float32
        intensities and a bool mask on the cropped grid; ``name`` is the file path as given.

    Raises:
        ImageError: Beginning with the file's path, for a missing or unreadable file, one that is
            not NIfTI, not 3D, empty or has NaN/Inf voxels; a stack whose in-plane axes are not
            orthogonal or whose in-mask intensities are not positive; an empty mask, or one that
            does not overlap its stack; a failed bias correction.
        ValueError: If there are no stacks, the number of masks or thicknesses does not match
            the number of stacks, or a thickness is not a positive number.
    """
    if mask_paths is None:
        raise ValueError(_NO_MASKS.format(what="mask_paths"))
    if len(mask_paths) != len(stack_paths):
        raise ValueError(_count_mismatch("masks", len(mask_paths), len(stack_paths)))
    images = [load_nifti(path) for path in stack_paths]
    masks = [load_nifti(path) for path in mask_paths]
    return prepare_stacks(
        images,
        masks,
        thicknesses,
        config,
        names=[str(path) for path in stack_paths],
        mask_names=[str(path) for path in mask_paths],
    )


def prepare_stacks(
    images: Sequence[Image],
    masks: Sequence[Image],
    thicknesses: float | Sequence[float] | None = None,
    config: StackConfig | None = None,
    names: Sequence[str] | None = None,
    mask_names: Sequence[str] | None = None,
) -> list[Stack]:
    """Prepare stacks held in memory (e.g. simulated ones); :func:`load_stacks` for files.

    Args:
        images: The ``(I, J, K)`` stacks (any device; the results are on the CPU).
        masks: One mask per stack (any grid; from :func:`svr.masking.auto_masks` for stacks
            without one).
        thicknesses: As in :func:`load_stacks`.
        config: Preparation settings; default :class:`StackConfig`'s.
        names: The stacks' names for the results and messages; default ``"stack 0"``, ...
        mask_names: The masks' names for messages; default ``"mask of <stack name>"``.

    Returns:
        One prepared :class:`~svr.reconstruction.slices.Stack` per image.

    Raises:
        ImageError: Beginning with the stack's or mask's name (see :func:`load_stacks`).
        ValueError: For no stacks, a count mismatch of masks, names or thicknesses, or a
            thickness that is not a positive number.
    """
    config = StackConfig() if config is None else config
    if masks is None:
        raise ValueError(_NO_MASKS.format(what="masks"))
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
        check_stack(image, name)
    widths = slice_thicknesses(thicknesses, images, names)
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


def check_stack(image: Image, name: str) -> None:
    """Reject non-finite intensities and non-rectangular slices (sheared in-plane axes).

    Raises:
        ImageError: Beginning with ``name``.
    """
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


def slice_thicknesses(
    thicknesses: float | Sequence[float] | None, images: Sequence[Image], names: Sequence[str]
) -> list[float]:
    """One slice thickness (mm) per stack: given, or the slice spacing with a warning.

    Args:
        thicknesses: ``None``, one value for all stacks, or one per stack.
        images: The stacks.
        names: Their names, for messages.

    Raises:
        ValueError: For a count mismatch or a thickness that is not a positive number.
    """
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
    import SimpleITK as sitk  # noqa: N813 (the usual alias; imported only where N4 runs)

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
