"""An atlas registered to a reconstruction: affine, then deformable (SimpleITK).

The reconstruction is the fixed image and the atlas the moving one, so that the atlas's labels are
pulled onto the reconstruction's grid. Both are brains already cut out (0 outside the brain) and
both are in the atlas frame up to a few degrees and millimetres (``svr reconstruct
--registration cnn`` writes its volume there). The steps, all SimpleITK (no registration code of
our own):

1. **Affine** (12 parameters), started from the identity rotation with the brains' centres of
   mass matched, Pearson correlation over the fixed brain, three levels; a rigid fit first.
2. **Deformable**: the atlas resampled through the affine, its histogram matched to the
   reconstruction's, then symmetric-forces demons with a smoothed displacement field on a
   coarse and a fine level (``AtlasRegistrationConfig.demons_levels_mm``).

The result maps a point of the reconstruction to the atlas: ``atlas(A(p + d(p)))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import SimpleITK as sitk  # noqa: N813 (the usual alias)
import torch

from svr.geometry import rotation_angle
from svr.image_metrics import ncc as image_ncc
from svr.validation import (
    check_bool,
    check_int,
    check_int_tuple,
    check_number,
    check_number_tuple,
)

__all__ = [
    "AtlasRegistrationConfig",
    "AtlasWarp",
    "affine_register",
    "correlation_method",
    "deformable_register",
    "register_atlas",
    "resample_like",
    "rotation_degrees",
]


@dataclass(frozen=True)
class AtlasRegistrationConfig:
    """How an atlas is registered to a reconstruction.

    Attributes:
        grid_mm: Spacing of the grid the registration runs on (mm, > 0).
        affine_iterations: Optimiser iterations per level of the rigid and of the affine fit.
        demons_levels_mm: Grid spacing of each demons level, coarse to fine (mm, > 0).
        demons_iterations: Demons iterations per level (one per entry of ``demons_levels_mm``).
        field_sigma_mm: Standard deviation of the Gaussian smoothing of the displacement field
            after each demons iteration (mm, > 0).
        deformable: Whether to run the deformable step (``False``: affine only).

    Raises:
        ConfigFieldError: On construction, naming the field, for a value out of range.
    """

    grid_mm: float = 1.6
    affine_iterations: int = 60
    demons_levels_mm: tuple[float, ...] = (3.2, 1.6)
    demons_iterations: tuple[int, ...] = (40, 30)
    field_sigma_mm: float = 2.4
    deformable: bool = True

    def __post_init__(self) -> None:
        owner = "AtlasRegistrationConfig"
        check_number(owner, "grid_mm", self.grid_mm, gt=0)
        check_number(owner, "field_sigma_mm", self.field_sigma_mm, gt=0)
        check_int(owner, "affine_iterations", self.affine_iterations, minimum=1)
        levels = check_number_tuple(
            owner, "demons_levels_mm", self.demons_levels_mm, gt=0, allow_empty=False
        )
        counts = check_int_tuple(
            owner, "demons_iterations", self.demons_iterations, length=len(levels), minimum=0
        )
        check_bool(owner, "deformable", self.deformable)
        object.__setattr__(self, "demons_levels_mm", levels)
        object.__setattr__(self, "demons_iterations", counts)


class AtlasWarp(NamedTuple):
    """An atlas registered to a reconstruction.

    Attributes:
        transform: Maps a point of the reconstruction (LPS mm, SimpleITK's convention) to the
            atlas: the affine after the displacement.
        affine: The affine part alone.
        rotation: (3, 3) the affine's rotation (its polar factor) in RAS: it turns the
            reconstruction's world directions into the atlas's.
        scale: The affine's mean scale (cube root of its determinant): the atlas's size over
            the reconstruction's brain.
        ncc_affine: Correlation of the two brains after the affine, over the fixed brain.
        ncc: Correlation after the deformable step (``ncc_affine`` without one).
    """

    transform: sitk.Transform
    affine: sitk.AffineTransform
    rotation: np.ndarray
    scale: float
    ncc_affine: float
    ncc: float

    @property
    def rotation_deg(self) -> float:
        """The rotation's angle (degrees): the reconstruction's frame against the atlas's."""
        return rotation_degrees(self.rotation)


def _grid_like(image: sitk.Image, spacing_mm: float) -> sitk.Image:
    """An empty image over ``image``'s extent, same direction, isotropic ``spacing_mm``."""
    old_size = np.asarray(image.GetSize(), dtype=np.float64)
    old_spacing = np.asarray(image.GetSpacing(), dtype=np.float64)
    size = [max(1, math.ceil(n)) for n in old_size * old_spacing / spacing_mm]
    reference = sitk.Image(size, sitk.sitkFloat32)
    reference.SetDirection(image.GetDirection())
    reference.SetSpacing((spacing_mm,) * 3)
    # the same physical corner: voxel centres shift by half the change of spacing
    shift = 0.5 * (spacing_mm - old_spacing)
    direction = np.asarray(image.GetDirection()).reshape(3, 3)
    reference.SetOrigin(tuple(np.asarray(image.GetOrigin()) + direction @ shift))
    return reference


def resample_like(
    image: sitk.Image,
    reference: sitk.Image,
    transform: sitk.Transform | None = None,
    interpolator: int = sitk.sitkLinear,
) -> sitk.Image:
    """``image`` on ``reference``'s grid through ``transform`` (reference -> image), 0 outside."""
    return sitk.Resample(
        image,
        reference,
        transform if transform is not None else sitk.Transform(),
        interpolator,
        0.0,
        sitk.sitkFloat32,
    )


def _down(image: sitk.Image, spacing_mm: float) -> sitk.Image:
    """``image`` smoothed (Gaussian, half the new spacing) and resampled at ``spacing_mm``."""
    smooth = sitk.SmoothingRecursiveGaussian(sitk.Cast(image, sitk.sitkFloat32), 0.5 * spacing_mm)
    return resample_like(smooth, _grid_like(image, spacing_mm))


def ncc(a: sitk.Image, b: sitk.Image, mask: sitk.Image) -> float:
    """Pearson correlation of two images on one grid over ``mask`` (> 0).

    The images are flattened into one "slice" for :func:`svr.image_metrics.ncc`.
    """
    flat = [torch.from_numpy(sitk.GetArrayFromImage(image)).reshape(1, -1, 1) for image in (a, b)]
    inside = torch.from_numpy(sitk.GetArrayFromImage(mask) > 0).reshape(1, -1, 1)
    return float(image_ncc(flat[0].double(), flat[1].double(), inside)[0])


def correlation_method(fixed_mask: sitk.Image) -> sitk.ImageRegistrationMethod:
    """A registration method by Pearson correlation over ``fixed_mask``.

    A quarter of the mask's voxels on a regular grid, linear interpolation; the optimiser, levels
    and transform are the caller's.
    """
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsCorrelation()
    method.SetMetricFixedMask(fixed_mask)
    method.SetMetricSamplingStrategy(method.REGULAR)
    method.SetMetricSamplingPercentage(0.25, seed=1)
    method.SetInterpolator(sitk.sitkLinear)
    return method


def _fit(
    fixed: sitk.Image,
    moving: sitk.Image,
    fixed_mask: sitk.Image,
    transform: sitk.Transform,
    iterations: int,
) -> sitk.Transform:
    """One intensity-based fit of ``transform`` (Pearson correlation, three levels)."""
    method = correlation_method(fixed_mask)
    method.SetOptimizerAsRegularStepGradientDescent(
        learningRate=1.0,
        minStep=1e-3,
        numberOfIterations=iterations,
        relaxationFactor=0.6,
        gradientMagnitudeTolerance=1e-6,
    )
    method.SetOptimizerScalesFromPhysicalShift()
    method.SetShrinkFactorsPerLevel([4, 2, 1])
    method.SetSmoothingSigmasPerLevel([2.0, 1.0, 0.0])
    method.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    method.SetInitialTransform(transform, inPlace=True)
    method.Execute(fixed, moving)
    return transform


def affine_register(
    fixed: sitk.Image,
    moving: sitk.Image,
    fixed_mask: sitk.Image,
    moving_mask: sitk.Image,
    iterations: int = 60,
    rigid_only: bool = False,
) -> sitk.AffineTransform:
    """Fit a similarity (or rigid), then (unless ``rigid_only``) an affine map ``fixed -> moving``.

    Started from the identity rotation with the masks' centres of mass matched and (similarity)
    the scale their volumes suggest: the two images must already be in one frame up to a
    moderate rotation.

    Args:
        fixed: The image whose points are mapped (float32).
        moving: The image they are mapped into (float32).
        fixed_mask: Where the metric is measured (uint8, ``fixed``'s grid).
        moving_mask: ``moving``'s brain (uint8), for the centre of mass.
        iterations: Optimiser iterations per level.
        rigid_only: Stop after the rigid fit.

    Returns:
        The fitted map as an affine transform (fixed -> moving, LPS mm).
    """
    similarity = sitk.CenteredTransformInitializer(
        fixed_mask,
        moving_mask,
        sitk.Similarity3DTransform(),
        sitk.CenteredTransformInitializerFilter.MOMENTS,
    )
    similarity = sitk.Similarity3DTransform(similarity)
    # the brains' sizes differ (neighbouring ages of an atlas by up to 15 % in length): start
    # from the ratio of their volumes, so that the rotation is not used to make up for it
    fixed_volume = _mask_volume(fixed_mask)
    if fixed_volume > 0 and not rigid_only:
        similarity.SetScale((_mask_volume(moving_mask) / fixed_volume) ** (1.0 / 3.0))
    fitted: sitk.Euler3DTransform | sitk.Similarity3DTransform = similarity
    if rigid_only:
        fitted = sitk.Euler3DTransform()
        fitted.SetCenter(similarity.GetCenter())
        fitted.SetTranslation(similarity.GetTranslation())
    _fit(fixed, moving, fixed_mask, fitted, iterations)  # in place
    affine = sitk.AffineTransform(3)
    affine.SetCenter(fitted.GetCenter())
    affine.SetMatrix(fitted.GetMatrix())
    affine.SetTranslation(fitted.GetTranslation())
    if not rigid_only:
        affine = sitk.AffineTransform(_fit(fixed, moving, fixed_mask, affine, iterations))
    return affine


def _mask_volume(mask: sitk.Image) -> float:
    """The volume (mm^3) of a mask's nonzero voxels."""
    return float((sitk.GetArrayViewFromImage(mask) > 0).sum() * np.prod(mask.GetSpacing()))


def deformable_register(
    fixed: sitk.Image,
    moved: sitk.Image,
    fixed_mask: sitk.Image,
    config: AtlasRegistrationConfig,
) -> sitk.DisplacementFieldTransform:
    """Symmetric-forces demons from ``fixed`` to ``moved`` (affinely aligned), coarse to fine.

    Args:
        fixed: The reconstruction on the registration grid (float32).
        moved: The atlas resampled through the affine on the same grid (float32).
        fixed_mask: The reconstruction's brain on that grid (uint8).
        config: Levels, iterations and field smoothing.

    Returns:
        The displacement field transform ``p -> p + d(p)`` on the finest level's grid.
    """
    matched = sitk.HistogramMatching(
        moved, fixed, numberOfHistogramLevels=128, numberOfMatchPoints=15
    )
    field: sitk.Image | None = None
    for spacing, count in zip(config.demons_levels_mm, config.demons_iterations, strict=True):
        level_fixed = _down(fixed, spacing)
        level_moved = _down(matched, spacing)
        if field is not None:
            field = sitk.Resample(
                field, level_fixed, sitk.Transform(), sitk.sitkLinear, 0.0, field.GetPixelID()
            )
        demons = sitk.FastSymmetricForcesDemonsRegistrationFilter()
        demons.SetNumberOfIterations(int(count))
        demons.SetSmoothDisplacementField(True)
        demons.SetStandardDeviations(config.field_sigma_mm / spacing)
        if field is None:
            field = demons.Execute(level_fixed, level_moved)
        else:
            field = demons.Execute(level_fixed, level_moved, field)
    assert field is not None
    del fixed_mask  # the demons forces vanish where both images are 0 outside the brains
    return sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64))


def rotation_degrees(rotation: np.ndarray) -> float:
    """The angle (degrees) of a (3, 3) rotation matrix (:func:`svr.geometry.rotation_angle`)."""
    turn = torch.as_tensor(rotation, dtype=torch.float64)
    return math.degrees(float(rotation_angle(torch.eye(3, dtype=torch.float64), turn)))


def _rotation_and_scale(affine: sitk.AffineTransform) -> tuple[np.ndarray, float]:
    """The affine matrix's polar rotation (RAS) and its mean scale."""
    matrix = np.asarray(affine.GetMatrix(), dtype=np.float64).reshape(3, 3)
    u, _, vt = np.linalg.svd(matrix)
    lps = np.diag([-1.0, -1.0, 1.0])
    return lps @ (u @ vt) @ lps, float(abs(np.linalg.det(matrix)) ** (1.0 / 3.0))


def register_atlas(
    volume: sitk.Image,
    volume_mask: sitk.Image,
    atlas: sitk.Image,
    atlas_mask: sitk.Image,
    config: AtlasRegistrationConfig | None = None,
) -> AtlasWarp:
    """Register an atlas (moving) to a reconstruction (fixed): affine, then demons.

    Args:
        volume: The reconstruction, 0 outside its brain (float32).
        volume_mask: Its brain (uint8, same grid).
        atlas: The atlas's brain (``srr`` times its mask, float32).
        atlas_mask: The atlas's brain mask (uint8).
        config: The registration's settings (defaults: :class:`AtlasRegistrationConfig`).

    Returns:
        The warp and how well it fits.
    """
    config = config or AtlasRegistrationConfig()
    fixed = _down(volume, config.grid_mm)
    mask = resample_like(volume_mask, fixed, interpolator=sitk.sitkNearestNeighbor) > 0.5
    moving = _down(atlas, config.grid_mm)
    moving_mask = resample_like(atlas_mask, moving, interpolator=sitk.sitkNearestNeighbor) > 0.5
    affine = affine_register(fixed, moving, mask, moving_mask, config.affine_iterations)
    moved = resample_like(moving, fixed, affine)
    ncc_affine = ncc(fixed, moved, mask)
    transform: sitk.Transform = affine
    score = ncc_affine
    if config.deformable:
        displacement = deformable_register(fixed, moved, mask, config)
        transform = sitk.CompositeTransform([affine, displacement])
        score = ncc(fixed, resample_like(moving, fixed, transform), mask)
    rotation, scale = _rotation_and_scale(affine)
    return AtlasWarp(transform, affine, rotation, scale, ncc_affine, score)
