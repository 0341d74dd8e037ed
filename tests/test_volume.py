"""Canonical volumes: masking, centring on the mask centroid, intensity normalisation, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from svr.image import Image, ImageError, save_nifti
from svr.sampling.volume import canonicalize, load_canonical_volume


def synthetic(rng: np.random.Generator) -> tuple[Image, Image]:
    affine = torch.tensor(
        [[0.8, 0, 0, -10.0], [0, 0.8, 0, 5.0], [0, 0, 1.2, 30.0], [0, 0, 0, 1]], dtype=torch.float64
    )
    data = torch.from_numpy(rng.uniform(100, 1000, size=(20, 24, 16))).float()
    mask = torch.zeros(20, 24, 16)
    mask[4:12, 6:20, 3:9] = 1.0
    return Image(data, affine), Image(mask, affine)


def test_centre_is_mask_centroid_and_origin_moves_there(rng):
    volume, mask = synthetic(rng)
    cv = canonicalize(volume, mask)
    centroid_idx = torch.tensor([7.5, 12.5, 5.5], dtype=torch.float64)
    expected = volume.affine[:3, :3] @ centroid_idx + volume.affine[:3, 3]
    torch.testing.assert_close(cv.centre_mm, expected)
    # canonical world of the centroid voxel position is the origin
    canonical = cv.image.affine[:3, :3] @ centroid_idx + cv.image.affine[:3, 3]
    torch.testing.assert_close(canonical, torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(cv.source_affine, volume.affine)


def test_intensity_rule(rng):
    volume, mask = synthetic(rng)
    cv = canonicalize(volume, mask, percentile=90.0)
    inside = volume.data[mask.data > 0.5].numpy()
    assert cv.intensity_scale == pytest.approx(np.percentile(inside, 90.0))
    assert (cv.image.data[mask.data < 0.5] == 0).all()
    np.testing.assert_allclose(
        cv.image.data[mask.data > 0.5].numpy(), inside / cv.intensity_scale, rtol=1e-6
    )
    assert np.mean(cv.image.data[mask.data > 0.5].numpy() <= 1.0) == pytest.approx(0.9, abs=0.01)
    assert cv.mask.dtype == torch.bool and cv.image.data.dtype == torch.float32


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("empty", "the mask is empty"),
        ("grid", "mask and volume grids differ"),
        ("shape", "mask and volume grids differ"),
        ("nan", "NaN or Inf"),
        ("zero", "expected a positive value"),
    ],
)
def test_errors(rng, change, message):
    volume, mask = synthetic(rng)
    if change == "empty":
        mask = Image(torch.zeros_like(mask.data), mask.affine)
    elif change == "grid":
        shifted = mask.affine.clone()
        shifted[0, 3] += 1.0
        mask = Image(mask.data, shifted)
    elif change == "shape":
        mask = Image(mask.data[:-1], mask.affine)
    elif change == "nan":
        volume.data[0, 0, 0] = float("nan")
    elif change == "zero":
        volume = Image(torch.zeros_like(volume.data), volume.affine)
    with pytest.raises(ValueError, match=message):
        canonicalize(volume, mask, name="brain.nii.gz")


def test_percentile_validated(rng):
    with pytest.raises(ValueError, match="'percentile'"):
        canonicalize(*synthetic(rng), percentile=0.0)


def test_load_reports_files(tmp_path, rng):
    volume, mask = synthetic(rng)
    save_nifti(volume, tmp_path / "v.nii.gz")
    save_nifti(Image(torch.zeros_like(mask.data), mask.affine), tmp_path / "m.nii.gz")
    with pytest.raises(ImageError, match=r"v\.nii\.gz.*m\.nii\.gz.*the mask is empty"):
        load_canonical_volume(tmp_path / "v.nii.gz", tmp_path / "m.nii.gz")
    with pytest.raises(ImageError, match=r"missing\.nii\.gz: no such file"):
        load_canonical_volume(tmp_path / "missing.nii.gz", tmp_path / "m.nii.gz")


def test_atlas_centre_matches_the_bench_cases(shared_data):
    atlas = shared_data / "atlas" / "sb-fidon2021" / "GA28_operated"
    cv = load_canonical_volume(atlas / "srr.nii.gz", atlas / "mask.nii.gz")
    case = json.loads((shared_data / "bench" / "sb28-moderate" / "case.json").read_text())
    np.testing.assert_allclose(cv.centre_mm.numpy(), case["atlas_centre_mm"], atol=1e-6)
    assert 0.9 < float(cv.image.data.max()) < 2.0
