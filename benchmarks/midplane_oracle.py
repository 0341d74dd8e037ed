"""An independent measure of a reconstruction's mid-sagittal plane, for the benchmarks.

The pipeline levels its canonical output on the brain's mirror symmetry with its own estimator
(:func:`svr.sampling.mirror_planes.measure_reflection_plane`). To check an output's frame on a real
scan, where no truth exists, the benchmarks need a measure that shares no code with it: here the
volume is registered to its own left-right mirror image with SimpleITK (rigid, correlation,
two resolutions, several starts, the best kept). If ``V(p) ~ V_mirror(T p)`` with ``V_mirror(p)
= V(F p)`` (``F`` the reflection of the array's first axis), then ``S = F o T`` is the brain's
reflection symmetry, and the eigenvector of its linear part with eigenvalue ``-1`` is the normal
of the mid-sagittal plane. Nothing in the library imports this.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import nibabel as nib
import numpy as np
import SimpleITK as sitk  # noqa: N813 (the usual alias)
from bench_real_frame import rotation_part
from scipy.ndimage import affine_transform

__all__ = [
    "MidplaneEstimate",
    "midplane_in_world",
    "midplane_of_array",
    "midplane_of_file",
    "on_world_axes",
    "world_image",
]

STARTS_DEG = ((0.0, 0.0), (30.0, 0.0), (-30.0, 0.0), (0.0, 30.0), (0.0, -30.0))
"""Starting turns (about the second and third axes, degrees) of the mirror registration.

The registration turns by about twice the plane's tilt, so these reach tilts up to about 25 deg.
"""


@dataclass(frozen=True)
class MidplaneEstimate:
    """The mid-sagittal plane of a volume.

    Attributes:
        normal: (3,) unit normal in the volume's array axes (first component >= 0).
        correlation: The best mirror registration's correlation (1: perfectly symmetric).
        tilt_deg: Angle between the normal and the array's first axis (degrees).
    """

    normal: np.ndarray
    correlation: float

    @property
    def tilt_deg(self) -> float:
        """Angle (degrees) between the normal and the array's first axis."""
        return math.degrees(math.acos(min(1.0, abs(float(self.normal[0])))))


def _image(data: np.ndarray, spacing: np.ndarray, origin: np.ndarray | None = None) -> sitk.Image:
    image = sitk.GetImageFromArray(np.ascontiguousarray(np.transpose(data, (2, 1, 0)), np.float32))
    image.SetSpacing(tuple(float(s) for s in spacing))
    if origin is not None:
        image.SetOrigin(tuple(float(v) for v in origin))
    return image


def on_world_axes(
    data: np.ndarray,
    affine: np.ndarray,
    support: np.ndarray,
    spacing_mm: float,
    margin_mm: float,
    order: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """An array resampled onto a grid of its world's axes around ``support``.

    Args:
        data: (I, J, K) values on the grid of ``affine``.
        affine: (4, 4) voxel -> world (mm).
        support: (I, J, K) bool: the voxels the new grid must cover.
        spacing_mm: The new grid's spacing (mm).
        margin_mm: How far past the support's extent the grid reaches (mm).
        order: Spline order of the resampling (1: trilinear, 0: nearest).

    Returns:
        The resampled array and (3,) the world point of its first voxel (mm); its voxel ``v``
        lies at ``low + spacing_mm * v``.
    """
    world = np.argwhere(support) @ affine[:3, :3].T + affine[:3, 3]
    low = world.min(axis=0) - margin_mm
    shape = tuple(int(n) + 1 for n in np.ceil((world.max(axis=0) + margin_mm - low) / spacing_mm))
    inverse = np.linalg.inv(affine)
    # grid voxel v -> world low + spacing v -> the source's voxel
    matrix = inverse[:3, :3] * spacing_mm
    offset = inverse[:3, :3] @ low + inverse[:3, 3]
    resampled = affine_transform(data, matrix, offset=offset, output_shape=shape, order=order)
    return resampled, low


def midplane_of_array(
    data: np.ndarray, spacing_mm: np.ndarray, threads: int = 1
) -> MidplaneEstimate:
    """The mid-sagittal plane of a volume whose first array axis is roughly left-right.

    Args:
        data: (X, Y, Z) intensities, the brain (background 0).
        spacing_mm: (3,) voxel spacing (mm).
        threads: SimpleITK's threads.

    Returns:
        The plane's normal in the array axes and the mirror registration's correlation.
    """
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)
    spacing = np.asarray(spacing_mm, dtype=np.float64)
    fixed = _image(data, spacing)
    moving = _image(data[::-1], spacing)
    centre = tuple(float(c) for c in (np.array(data.shape) - 1) / 2 * spacing)
    found = []
    for about_y, about_z in STARTS_DEG:
        start = sitk.Euler3DTransform()
        start.SetCenter(centre)
        start.SetRotation(0.0, math.radians(about_y), math.radians(about_z))
        found.append(_register(fixed, moving, start))
    # polish: once more from the exact reflection about the best start's plane
    best = min(found, key=lambda pair: pair[0])
    start = sitk.Euler3DTransform(best[1])
    normal = _normal(best[1])
    start.SetMatrix(tuple((FLIP @ (np.eye(3) - 2.0 * np.outer(normal, normal))).ravel()))
    best = min([best, _register(fixed, moving, start)], key=lambda pair: pair[0])
    return MidplaneEstimate(_normal(best[1]), -float(best[0]))


FLIP = np.diag([-1.0, 1.0, 1.0])
"""The reflection of the array's first axis (the mirror image's)."""


def _register(
    fixed: sitk.Image, moving: sitk.Image, start: sitk.Euler3DTransform
) -> tuple[float, sitk.Euler3DTransform]:
    """SimpleITK's rigid registration of the mirror image from ``start``: (metric, transform)."""
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsCorrelation()
    method.SetInterpolator(sitk.sitkLinear)
    method.SetOptimizerAsRegularStepGradientDescent(1.0, 1e-4, 300)
    method.SetOptimizerScalesFromPhysicalShift()
    method.SetShrinkFactorsPerLevel([4, 2])
    method.SetSmoothingSigmasPerLevel([2.0, 1.0])
    method.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    method.SetMetricSamplingStrategy(method.RANDOM)
    method.SetMetricSamplingPercentage(0.2, 1)
    method.SetInitialTransform(start, inPlace=False)
    found = method.Execute(fixed, moving)
    rigid = sitk.Euler3DTransform(sitk.CompositeTransform(found).GetNthTransform(0))
    return float(method.GetMetricValue()), rigid


def _normal(transform: sitk.Euler3DTransform) -> np.ndarray:
    """(3,) the mid-sagittal normal a mirror registration implies (first component >= 0)."""
    symmetry = FLIP @ np.array(transform.GetMatrix()).reshape(3, 3)
    values, vectors = np.linalg.eig(symmetry)
    normal = np.real(vectors[:, int(np.argmin(np.real(values)))])
    normal = normal / np.linalg.norm(normal)
    return normal if normal[0] >= 0 else -normal


def midplane_of_file(path: Path, threads: int = 1) -> tuple[MidplaneEstimate, np.ndarray]:
    """The mid-sagittal plane of a NIfTI reconstruction, and its normal in world coordinates.

    Args:
        path: A canonical output of ``svr reconstruct``: its world is the canonical frame, its
            array axes those of the grid it was reconstructed on (before its last turns).
        threads: SimpleITK's threads.

    Returns:
        The estimate in the array's axes, and (3,) the normal in the file's world frame.
    """
    image = nib.load(str(path))
    data = np.asarray(image.dataobj, dtype=np.float32)
    spacing = np.linalg.norm(image.affine[:3, :3], axis=0)
    estimate = midplane_of_array(np.clip(data, 0, None), spacing, threads)
    return estimate, rotation_part(image.affine) @ estimate.normal


def midplane_in_world(
    image_path: Path, mask_path: Path, spacing_mm: float = 1.1, threads: int = 1
) -> MidplaneEstimate:
    """The mid-sagittal plane of the brain in a stack, in the file's own world frame.

    The brain-masked stack is resampled (trilinear) onto a grid of the world's axes at
    ``spacing_mm`` and measured there, so the normal is in world coordinates: for files whose
    world is the brain's anatomical frame (simulated stacks), how far that frame's ``x = 0``
    lies from the brain's own symmetry plane.

    Args:
        image_path: A stack (NIfTI).
        mask_path: Its brain mask, on the same grid.
        spacing_mm: The resampling grid's spacing (mm).
        threads: SimpleITK's threads.

    Returns:
        The estimate; its ``normal`` and ``tilt_deg`` are in the world's axes.
    """
    image = nib.load(str(image_path))
    data = np.asarray(image.dataobj, dtype=np.float32)
    data = data * (np.asarray(nib.load(str(mask_path)).dataobj) > 0.5)
    resampled, _ = on_world_axes(data, image.affine, data > 0, spacing_mm, 5.0)
    return midplane_of_array(resampled, np.full(3, spacing_mm), threads)


def world_image(path: Path, spacing_mm: float = 1.0, mask: Path | None = None) -> sitk.Image:
    """A NIfTI image resampled onto a grid of its world axes, as a SimpleITK image.

    SimpleITK's physical points are then the file's RAS world coordinates (mm), with no LPS
    conversion. The grid covers the image's nonzero voxels and 8 mm more.

    Args:
        path: The image (NIfTI).
        spacing_mm: The grid's spacing (mm).
        mask: A mask on the same grid, returned instead of the image (nearest neighbour).

    Returns:
        The image (or mask) on the new grid.
    """
    image = nib.load(str(path))
    source = image if mask is None else nib.load(str(mask))
    data = np.asarray(source.dataobj, dtype=np.float32)
    support = np.asarray(image.dataobj) != 0
    order = 1 if mask is None else 0
    resampled, low = on_world_axes(data, image.affine, support, spacing_mm, 8.0, order)
    return _image(resampled, np.full(3, spacing_mm), low)
