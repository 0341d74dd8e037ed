"""NIfTI-style images (array + RAS affine) to and from SimpleITK images (LPS geometry).

The toolkit holds an image as an (I, J, K) array and its voxel-to-world RAS+ affine (nibabel).
SimpleITK holds an (x, y, z)-indexed image with spacing, origin and direction in LPS. Index
(x, y, z) here is array index (i, j, k), so the array is transposed on the way in and out; the
world point is the same, with x and y negated (RAS -> LPS). This is the one place that converts.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk  # noqa: N813 (the usual alias)

__all__ = ["from_sitk", "sitk_affine", "to_sitk"]

_LPS = np.diag([-1.0, -1.0, 1.0])


def to_sitk(array: np.ndarray, affine: np.ndarray) -> sitk.Image:
    """An (I, J, K) array with its RAS voxel-to-world affine as a SimpleITK image.

    Args:
        array: (I, J, K) voxels.
        affine: (4, 4) voxel-to-world (RAS+, mm); its 3x3 part must have orthogonal columns
            (no shear: SimpleITK cannot represent one).

    Returns:
        The image, index (x, y, z) = array index (i, j, k), geometry in LPS.

    Raises:
        ValueError: If ``array`` is not 3D or ``affine`` is not a 4x4 affine without shear.
    """
    if array.ndim != 3:
        raise ValueError(f"to_sitk(): 'array' must be 3D (I, J, K), got shape {array.shape}")
    affine = np.asarray(affine, dtype=np.float64)
    if affine.shape != (4, 4):
        raise ValueError(f"to_sitk(): 'affine' must be 4x4, got shape {affine.shape}")
    linear = affine[:3, :3]
    spacing = np.linalg.norm(linear, axis=0)
    direction = linear / spacing
    if not np.allclose(direction.T @ direction, np.eye(3), atol=1e-4):
        raise ValueError("to_sitk(): 'affine' has shear (its columns are not orthogonal)")
    image = sitk.GetImageFromArray(np.ascontiguousarray(np.transpose(array, (2, 1, 0))))
    image.SetSpacing(tuple(float(s) for s in spacing))
    image.SetOrigin(tuple(float(v) for v in _LPS @ affine[:3, 3]))
    image.SetDirection(tuple(float(v) for v in (_LPS @ direction).ravel()))
    return image


def sitk_affine(image: sitk.Image) -> np.ndarray:
    """The (4, 4) RAS voxel-to-world affine of a SimpleITK image (index (x, y, z) = (i, j, k))."""
    direction = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    affine = np.eye(4)
    affine[:3, :3] = _LPS @ direction @ np.diag(image.GetSpacing())
    affine[:3, 3] = _LPS @ np.asarray(image.GetOrigin(), dtype=np.float64)
    return affine


def from_sitk(image: sitk.Image) -> np.ndarray:
    """The (I, J, K) array of a SimpleITK image (its affine: :func:`sitk_affine`)."""
    return np.transpose(sitk.GetArrayFromImage(image), (2, 1, 0))
