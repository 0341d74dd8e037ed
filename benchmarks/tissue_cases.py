"""Evaluation cases for tissue segmentation, with their true labels (used by bench_tissue.py).

Two kinds, each a folder ``<out>/<case>/`` with ``volume.nii.gz`` (the input: a masked T2w brain
in the atlas frame up to a few degrees), ``truth_labels.nii.gz`` (its true labels on the same grid)
and ``case.json`` (``weeks``, ``family``, ``kind``, ``source``):

* ``gt-volume``: an atlas age's own volume, turned and shifted at random (up to 5 deg and 3 mm:
  the frame error a reconstruction may have) onto a 0.8 mm grid centred on the brain, as
  ``svr reconstruct`` writes its volume; the truth is that age's parcellation moved the same way.
* ``recon``: an ``svr reconstruct --registration cnn`` output of a bench case simulated from an
  atlas age; the truth is that age's parcellation brought onto the output's grid by a rigid
  registration of the output to that age's volume (as the reconstruction yardstick aligns them).

The ages of the cases are the ones the segmenters leave out of their atlases (and the learned
segmenter out of its training).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import SimpleITK as sitk  # noqa: N813
import torch
from scipy.spatial.transform import Rotation

from svr.image import Image, load_nifti, save_labels_like, save_nifti
from svr.tissue.registration import affine_register, resample_like
from svr.tissue.sitk_images import from_sitk, to_sitk

_LPS = np.diag([-1.0, -1.0, 1.0])


def _load(path: Path) -> tuple[np.ndarray, np.ndarray]:
    image = load_nifti(path)
    return image.data.numpy(), image.affine.numpy()


def _write_case(
    out: Path, volume: np.ndarray, affine: np.ndarray, truth: np.ndarray, info: dict
) -> None:
    """``volume.nii.gz``, ``truth_labels.nii.gz`` (its grid and header) and ``case.json``."""
    out.mkdir(parents=True, exist_ok=True)
    image = Image(torch.from_numpy(volume.astype(np.float32)), torch.from_numpy(affine))
    save_nifti(image, out / "volume.nii.gz", overwrite=True)
    save_labels_like(truth, out / "volume.nii.gz", out / "truth_labels.nii.gz", overwrite=True)
    (out / "case.json").write_text(json.dumps(info, indent=1), encoding="utf-8")


def gt_volume_case(atlas_age: Path, out: Path, family: str, weeks: float, seed: int) -> None:
    """An atlas age's volume moved at random onto a brain-centred 0.8 mm grid, and its labels."""
    srr, affine = _load(atlas_age / "srr.nii.gz")
    mask, _ = _load(atlas_age / "mask.nii.gz")
    labels, _ = _load(atlas_age / "parcellation.nii.gz")
    inside = np.argwhere(mask > 0.5)
    centre = (affine[:3, :3] @ inside.mean(0)) + affine[:3, 3]
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    rotation = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(rng.uniform(2, 5)))
    shift = rng.normal(size=3)
    shift = shift / np.linalg.norm(shift) * rng.uniform(1, 3)
    # the case's world point q shows the atlas at R q + centre + shift
    matrix = rotation.as_matrix()
    transform = sitk.AffineTransform(3)
    transform.SetMatrix(tuple((_LPS @ matrix @ _LPS).ravel()))
    transform.SetTranslation(tuple(_LPS @ (centre + shift)))
    extent = (inside.max(0) - inside.min(0) + 1) * 0.8 + 16.0
    size = np.ceil(extent / 0.8).astype(int)
    grid = np.eye(4)
    grid[:3, :3] *= 0.8
    grid[:3, 3] = -0.8 * (size - 1) / 2.0
    reference = to_sitk(np.zeros(size, np.float32), grid)
    volume = from_sitk(resample_like(to_sitk(srr * (mask > 0.5), affine), reference, transform))
    moved_mask = from_sitk(resample_like(to_sitk(mask, affine), reference, transform))
    truth = from_sitk(
        resample_like(to_sitk(labels, affine), reference, transform, sitk.sitkNearestNeighbor)
    )
    volume = np.where(moved_mask > 0.5, volume, 0.0)
    truth = np.where(moved_mask > 0.5, truth, 0)
    info = {
        "weeks": weeks,
        "family": family,
        "kind": "gt-volume",
        "source": str(atlas_age),
        "rotation_deg": float(np.degrees(rotation.magnitude())),
        "shift_mm": float(np.linalg.norm(shift)),
    }
    _write_case(out, volume, grid, truth, info)


def recon_case(recon: Path, atlas_age: Path, out: Path, family: str, weeks: float) -> float:
    """A reconstruction and its source age's labels placed by a rigid registration; its NCC."""
    volume, affine = _load(recon)
    srr, atlas_affine = _load(atlas_age / "srr.nii.gz")
    mask, _ = _load(atlas_age / "mask.nii.gz")
    labels, _ = _load(atlas_age / "parcellation.nii.gz")
    fixed = to_sitk(volume, affine)
    fixed_mask = to_sitk((volume > 0).astype(np.uint8), affine)
    moving = to_sitk(srr * (mask > 0.5), atlas_affine)
    moving_mask = to_sitk((mask > 0.5).astype(np.uint8), atlas_affine)
    rigid = affine_register(fixed, moving, fixed_mask, moving_mask, 200, rigid_only=True)
    truth = from_sitk(
        resample_like(to_sitk(labels, atlas_affine), fixed, rigid, sitk.sitkNearestNeighbor)
    )
    truth = np.where(volume > 0, truth, 0)
    moved = from_sitk(resample_like(moving, fixed, rigid))
    inside = volume > 0
    ncc = float(np.corrcoef(volume[inside], moved[inside])[0, 1])
    info = {
        "weeks": weeks,
        "family": family,
        "kind": "recon",
        "source": str(atlas_age),
        "recon": str(recon),
        "truth_ncc": ncc,
    }
    _write_case(out, volume, affine, truth, info)
    return ncc
