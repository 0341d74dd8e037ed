"""Regional volumes and linear measures of a tissue label map, in the atlas frame.

Every linear measure is taken on the label map resampled (nearest label) onto a grid aligned with
the atlas frame's axes: x left to right, y posterior to anterior, z inferior to superior (RAS,
the frame ``svr reconstruct --registration cnn`` writes its volume in; ``rotation`` corrects a
volume a few degrees off it). "Axial planes" are the planes of constant z, "sagittal" of constant
x. A length is counted edge to edge: (last voxel - first voxel + 1) x the grid spacing.

=====================  ====================================================================
measure                definition (labels: :data:`svr.tissue.labels.TISSUE_LABELS`)
=====================  ====================================================================
``brain_bpd_mm``       brain biparietal diameter: the greatest left-right width of the
                       cerebrum (white matter, ventricles, cortical and deep grey matter,
                       corpus callosum) in any axial plane
``brain_ofd_mm``       brain fronto-occipital diameter: the greatest anterior-posterior
                       length of the cerebrum in any axial plane
``tcd_mm``             transverse cerebellar diameter: the greatest left-right width of the
                       cerebellum in any axial plane
``atrium_left_mm``,    lateral ventricle atrial width: in the posterior half of each lateral
``atrium_right_mm``    ventricle (the ventricle label more than 2 mm from the mid-sagittal
                       plane, on that side), the diameter of the largest disc inside it in any
                       axial plane (the width across the ventricle's long axis)
``cc_length_mm``       corpus callosum length: the greatest anterior-posterior length of the
                       corpus callosum in the sagittal planes within 2 mm of the mid-sagittal
                       plane (genu to splenium)
=====================  ====================================================================

The mid-sagittal plane is taken halfway across the cerebrum's widest axial extent. A measure
whose structure is absent is NaN.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from svr.tissue.labels import STRUCTURES, TISSUE_LABELS

__all__ = [
    "LINEAR_MEASURES",
    "Biometry",
    "atlas_aligned",
    "label_volumes_ml",
    "linear_measures",
    "measure_labels",
]

LINEAR_MEASURES: dict[str, str] = {
    "brain_bpd_mm": "Brain biparietal diameter",
    "brain_ofd_mm": "Brain fronto-occipital diameter",
    "tcd_mm": "Transverse cerebellar diameter",
    "atrium_left_mm": "Atrial width, left lateral ventricle",
    "atrium_right_mm": "Atrial width, right lateral ventricle",
    "cc_length_mm": "Corpus callosum length",
}
"""Key -> name of each linear measure (module docstring for the definitions), in mm."""

MIDLINE_MM = 2.0
"""Half-width of the mid-sagittal band (mm): the third ventricle is left out of the lateral
ventricles within it, and the corpus callosum is measured within it."""


class Biometry(NamedTuple):
    """Volumes and linear measures of one label map.

    Attributes:
        volumes_ml: Label key or structure name -> volume (mL).
        measures_mm: Measure key -> length (mm; NaN where the structure is absent).
    """

    volumes_ml: dict[str, float]
    measures_mm: dict[str, float]


def label_volumes_ml(labels: np.ndarray, affine: np.ndarray) -> dict[str, float]:
    """Each label's and each structure's volume (mL): voxel count x voxel volume."""
    voxel_ml = abs(float(np.linalg.det(np.asarray(affine, dtype=np.float64)[:3, :3]))) / 1000.0
    counts = np.bincount(np.asarray(labels, dtype=np.int64).ravel(), minlength=256)
    volumes = {label.key: float(counts[label.value] * voxel_ml) for label in TISSUE_LABELS}
    for name, values in STRUCTURES.items():
        volumes[name] = float(sum(counts[v] for v in values) * voxel_ml)
    return volumes


def atlas_aligned(
    arrays: Sequence[np.ndarray],
    affine: np.ndarray,
    rotation: np.ndarray | None = None,
    spacing_mm: float | None = None,
) -> tuple[list[np.ndarray], float]:
    """Arrays on a grid aligned with the atlas axes (x, y, z = R, A, S), nearest voxel.

    The grid covers the nonzero voxels of the first array (a label map).

    Args:
        arrays: (I, J, K) arrays on one grid, the first a label map.
        affine: (4, 4) voxel-to-world (RAS, mm).
        rotation: (3, 3) rotation taking the volume's world directions to the atlas's
            (identity: the volume is in the atlas frame).
        spacing_mm: The grid's spacing (default: the volume's smallest voxel size).

    Returns:
        The (X, Y, Z) arrays, indexed along the atlas axes, and the spacing (mm). Arrays already
        on such a grid (a diagonal affine with positive, equal steps, no rotation) come back as
        they are.
    """
    affine = np.asarray(affine, dtype=np.float64)
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    steps = np.linalg.norm(affine[:3, :3], axis=0)
    spacing = float(steps.min()) if spacing_mm is None else float(spacing_mm)
    diagonal = np.allclose(affine[:3, :3], np.diag(np.diag(affine[:3, :3])), atol=1e-6)
    if (
        diagonal
        and (np.diag(affine[:3, :3]) > 0).all()
        and np.allclose(rotation, np.eye(3), atol=1e-9)
        and np.allclose(steps, spacing, rtol=1e-4)
    ):
        return [np.asarray(a) for a in arrays], spacing
    inside = np.argwhere(np.asarray(arrays[0]) > 0)
    if inside.size == 0:
        return [np.zeros((1, 1, 1), dtype=np.asarray(a).dtype) for a in arrays], spacing
    corners = np.array(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [-0.5, 0.5])).reshape(3, -1).T
    points = (inside[:, None, :] + corners[None]).reshape(-1, 3)
    atlas = (points @ affine[:3, :3].T + affine[:3, 3]) @ rotation.T
    low, high = atlas.min(0), atlas.max(0)
    size = np.maximum(1, np.ceil((high - low) / spacing).astype(int))
    axes = [low[d] + spacing * (np.arange(size[d]) + 0.5) for d in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    voxel = ((grid @ rotation - affine[:3, 3]) @ np.linalg.inv(affine[:3, :3]).T).T
    out = [
        ndimage.map_coordinates(
            np.asarray(a), voxel, order=0, mode="constant", cval=0, prefilter=False
        ).reshape(tuple(size))
        for a in arrays
    ]
    return out, spacing


def _extent_in_planes(mask: np.ndarray, along: int, planes: int) -> float:
    """Greatest extent (voxels, edge to edge) of ``mask`` along ``along`` in a plane.

    The planes are normal to axis ``planes``; 0 for an empty mask.
    """
    if not mask.any():
        return 0.0
    moved = np.moveaxis(mask, (planes, along), (0, 1))  # (plane, along, other)
    present = np.asarray(moved.any(axis=2))  # (plane, along)
    best = 0
    for row in present:
        hits = np.flatnonzero(row)
        if hits.size:
            best = max(best, int(hits[-1] - hits[0] + 1))
    return float(best)


def _largest_disc(mask: np.ndarray, spacing: float) -> float:
    """Diameter (mm) of the largest disc inside ``mask`` in any axial plane (axis 2)."""
    best = 0.0
    for z in np.flatnonzero(mask.any(axis=(0, 1))):
        plane = np.pad(mask[:, :, z], 1)
        distance = ndimage.distance_transform_edt(plane)
        best = max(best, float(distance.max()))
    # the distance runs from a voxel centre to the nearest outside centre: half a voxel past
    # the edge on each side
    return max(0.0, 2.0 * best * spacing - spacing)


def linear_measures(aligned: np.ndarray, spacing: float) -> dict[str, float]:
    """The linear measures (module docstring) of an atlas-aligned label map.

    Args:
        aligned: (X, Y, Z) labels on a grid along the atlas axes (:func:`atlas_aligned`).
        spacing: Its spacing (mm).

    Returns:
        Measure key -> mm (NaN where the structure is absent).
    """
    nan = math.nan
    cerebrum = np.isin(aligned, STRUCTURES["cerebrum"])
    out = dict.fromkeys(LINEAR_MEASURES, nan)
    if cerebrum.any():
        out["brain_bpd_mm"] = _extent_in_planes(cerebrum, along=0, planes=2) * spacing
        out["brain_ofd_mm"] = _extent_in_planes(cerebrum, along=1, planes=2) * spacing
        xs = np.flatnonzero(cerebrum.any(axis=(1, 2)))
        midline = 0.5 * (xs[0] + xs[-1])
    else:
        midline = 0.5 * (aligned.shape[0] - 1)
    cerebellum = aligned == 3
    if cerebellum.any():
        out["tcd_mm"] = _extent_in_planes(cerebellum, along=0, planes=2) * spacing
    x = (np.arange(aligned.shape[0]) - midline) * spacing
    band = np.abs(x) <= MIDLINE_MM
    ventricles = aligned == 2
    for key, side in (("atrium_left_mm", x < -MIDLINE_MM), ("atrium_right_mm", x > MIDLINE_MM)):
        lateral = ventricles & side[:, None, None]
        if not lateral.any():
            continue
        ys = np.flatnonzero(lateral.any(axis=(0, 2)))
        posterior = np.arange(aligned.shape[1]) <= 0.5 * (ys[0] + ys[-1])
        out[key] = _largest_disc(lateral & posterior[None, :, None], spacing)
    callosum = (aligned == 8) & band[:, None, None]
    if callosum.any():
        out["cc_length_mm"] = _extent_in_planes(callosum, along=1, planes=0) * spacing
    return out


def measure_labels(
    labels: np.ndarray,
    affine: np.ndarray,
    rotation: np.ndarray | None = None,
    spacing_mm: float | None = None,
) -> Biometry:
    """Volumes and linear measures of a label map (module docstring).

    Args:
        labels: (I, J, K) integer labels (:data:`TISSUE_LABELS` values).
        affine: (4, 4) voxel-to-world (RAS, mm).
        rotation: (3, 3) volume-world to atlas directions (identity: in the atlas frame).
        spacing_mm: The measuring grid's spacing (default: the smallest voxel size).

    Returns:
        The volumes (mL) and measures (mm).
    """
    (aligned,), spacing = atlas_aligned([labels], affine, rotation, spacing_mm)
    return Biometry(label_volumes_ml(labels, affine), linear_measures(aligned, spacing))
