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
from scipy.ndimage import binary_erosion

__all__ = ["MidplaneEstimate", "affine_rotation", "midplane_of_array", "midplane_of_file"]

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


def _mask(inside: np.ndarray, spacing: np.ndarray) -> sitk.Image:
    image = sitk.GetImageFromArray(np.ascontiguousarray(np.transpose(inside, (2, 1, 0)), np.uint8))
    image.SetSpacing(tuple(float(s) for s in spacing))
    return image


def _image(data: np.ndarray, spacing: np.ndarray) -> sitk.Image:
    image = sitk.GetImageFromArray(np.ascontiguousarray(np.transpose(data, (2, 1, 0)), np.float32))
    image.SetSpacing(tuple(float(s) for s in spacing))
    return image


def midplane_of_array(
    data: np.ndarray, spacing_mm: np.ndarray, threads: int = 1, erode_mm: float = 0.0
) -> MidplaneEstimate:
    """The mid-sagittal plane of a volume whose first array axis is roughly left-right.

    Args:
        data: (X, Y, Z) intensities, the brain (background 0).
        spacing_mm: (3,) voxel spacing (mm).
        threads: SimpleITK's threads.
        erode_mm: If > 0, the correlation is taken inside the brain's support eroded by this
            much (the brain's inside alone, not its outline).

    Returns:
        The plane's normal in the array axes and the mirror registration's correlation.
    """
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)
    spacing = np.asarray(spacing_mm, dtype=np.float64)
    fixed = _image(data, spacing)
    moving = _image(data[::-1], spacing)
    masks = None
    if erode_mm > 0:
        inside = binary_erosion(data > 0, iterations=max(1, round(erode_mm / float(spacing.min()))))
        masks = (_mask(inside, spacing), _mask(inside[::-1], spacing))
    centre = (np.array(data.shape) - 1) / 2 * spacing
    best: tuple[float, sitk.Euler3DTransform] | None = None
    starts = []
    for about_y, about_z in STARTS_DEG:
        start = sitk.Euler3DTransform()
        start.SetCenter(tuple(float(c) for c in centre))
        start.SetRotation(0.0, math.radians(about_y), math.radians(about_z))
        starts.append(start)
    for index in range(len(starts) + 1):
        if index == len(starts):  # polish: from the reflection the best estimate implies
            assert best is not None
            start = sitk.Euler3DTransform(best[1])
            reflection = np.eye(3) - 2.0 * np.outer(*(_normal(best[1]),) * 2)
            start.SetMatrix(tuple((FLIP @ reflection).ravel()))
        else:
            start = starts[index]
        metric, found = _register(fixed, moving, start, masks)
        if best is None or metric < best[0]:
            best = (metric, found)
    assert best is not None
    return MidplaneEstimate(_normal(best[1]), -float(best[0]))


FLIP = np.diag([-1.0, 1.0, 1.0])
"""The reflection of the array's first axis (the mirror image's)."""


def _register(
    fixed: sitk.Image,
    moving: sitk.Image,
    start: sitk.Euler3DTransform,
    masks: tuple[sitk.Image, sitk.Image] | None = None,
) -> tuple[float, sitk.Euler3DTransform]:
    """SimpleITK's rigid registration of the mirror image from ``start``: (metric, transform)."""
    method = sitk.ImageRegistrationMethod()
    if masks is not None:
        method.SetMetricFixedMask(masks[0])
        method.SetMetricMovingMask(masks[1])
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


def affine_rotation(affine: np.ndarray) -> np.ndarray:
    """The (3, 3) rotation of a voxel-to-world affine: its columns divided by the spacing."""
    return affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0)


def midplane_of_file(path: Path, threads: int = 1) -> tuple[MidplaneEstimate, np.ndarray]:
    """The mid-sagittal plane of a NIfTI reconstruction, and its normal in world coordinates.

    Args:
        path: A canonical output of ``svr reconstruct`` (array axes = its frame's x, y, z).
        threads: SimpleITK's threads.

    Returns:
        The estimate in the volume's own frame, and (3,) the normal in the file's world frame.
    """
    image = nib.load(str(path))
    data = np.asarray(image.dataobj, dtype=np.float32)
    spacing = np.linalg.norm(image.affine[:3, :3], axis=0)
    estimate = midplane_of_array(np.clip(data, 0, None), spacing, threads)
    return estimate, affine_rotation(image.affine) @ estimate.normal
