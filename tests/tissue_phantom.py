"""A labelled brain phantom and an atlas folder of it, for the tissue tests (no shared data)."""

from __future__ import annotations

from pathlib import Path

import nibabel as nib
import numpy as np
from scipy import ndimage

# T2-like level per label (CSF bright, grey matter dark)
LEVELS = {0: 0.0, 1: 0.6, 2: 0.95, 3: 0.5, 4: 1.0, 5: 0.35, 6: 0.45, 7: 0.42, 8: 0.3}


def _inside(points: np.ndarray, centre, radii) -> np.ndarray:
    return (((points - np.asarray(centre)) / np.asarray(radii)) ** 2).sum(-1) <= 1.0


def phantom_labels(points: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Labels 0-8 at world points (..., 3) in mm (RAS, brain centred at 0), ``scale`` = size."""
    p = points / scale
    labels = np.zeros(p.shape[:-1], np.uint8)
    labels[_inside(p, (0, 0, 0), (30, 38, 30))] = 4
    labels[_inside(p, (0, 4, 4), (26, 32, 22))] = 5
    labels[_inside(p, (0, 4, 4), (22, 28, 18))] = 1
    labels[_inside(p, (0, 4, 2), (9, 7, 6))] = 6
    for x in (-9.0, 9.0):
        labels[_inside(p, (x, -2, 6), (3.5, 14, 4))] = 2
    labels[
        (np.abs(p[..., 0]) <= 2) & (np.abs(p[..., 1] - 4) <= 12) & (np.abs(p[..., 2] - 14) <= 1.5)
    ] = 8
    labels[_inside(p, (0, -27, -15), (15, 7, 8))] = 3
    labels[_inside(p, (0, -12, -18), (5, 5, 9))] = 7
    return labels


def grid_points(shape, affine) -> np.ndarray:
    """World points (I, J, K, 3) of a grid's voxel centres."""
    index = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    return index @ affine[:3, :3].T + affine[:3, 3]


def image_of(labels: np.ndarray) -> np.ndarray:
    """A smooth T2-like image of a label map."""
    levels = np.array([LEVELS[v] for v in range(9)], np.float32)
    return ndimage.gaussian_filter(levels[labels], 0.7) * (labels > 0)


def save(path: Path, array: np.ndarray, affine: np.ndarray) -> Path:
    image = nib.Nifti1Image(array, affine)
    image.set_sform(affine, code=1)
    image.set_qform(affine, code=1)
    nib.save(image, str(path))
    return path


def centred_affine(shape, spacing: float, rotation: np.ndarray | None = None, shift=(0, 0, 0)):
    """A voxel-to-world affine of a grid centred on ``shift``, turned by ``rotation``."""
    rotation = np.eye(3) if rotation is None else rotation
    affine = np.eye(4)
    affine[:3, :3] = rotation * spacing
    affine[:3, 3] = np.asarray(shift) - affine[:3, :3] @ ((np.asarray(shape) - 1) / 2.0)
    return affine


def atlas_folder(root: Path, ages=(26.0, 27.0, 29.0, 30.0), spacing: float = 2.0) -> Path:
    """``root/GA<age>_phantom/{srr,mask,parcellation}.nii.gz``, the phantom grown with age."""
    shape = (40, 48, 40)
    affine = centred_affine(shape, spacing)
    points = grid_points(shape, affine)
    for age in ages:
        folder = root / f"GA{int(age)}_phantom"
        folder.mkdir(parents=True)
        labels = phantom_labels(points, scale=1.0 + 0.03 * (age - 28.0))
        save(folder / "parcellation.nii.gz", labels, affine)
        save(folder / "mask.nii.gz", (labels > 0).astype(np.uint8), affine)
        save(folder / "srr.nii.gz", image_of(labels).astype(np.float32), affine)
    return root
