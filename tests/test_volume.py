"""Canonical volumes: masking, centring on the mask centroid, intensity normalisation, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from svr.image import Image, ImageError, save_nifti
from svr.sampling.volume import (
    VolumeSourceError,
    atlas_paths_near,
    atlas_volume_paths,
    canonicalize,
    load_canonical_volume,
    load_volumes,
)


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


def _atlas(tmp_path, rng, names=("GA24_a", "GA28_b", "GA30_c")):
    volume, mask = synthetic(rng)
    for name in names:
        (tmp_path / name).mkdir()
        save_nifti(volume, tmp_path / name / "srr.nii.gz")
        save_nifti(mask, tmp_path / name / "mask.nii.gz")
    (tmp_path / "GA26_empty").mkdir()  # no srr.nii.gz: skipped
    return tmp_path


def test_atlas_volume_paths_hold_out_and_only(tmp_path, rng):
    root = _atlas(tmp_path, rng)
    names = lambda pairs: [v.parent.name for v, _ in pairs]  # noqa: E731
    assert names(atlas_volume_paths(root)) == ["GA24_a", "GA28_b", "GA30_c"]
    assert names(atlas_volume_paths(root, hold_out=[24, 30])) == ["GA28_b"]
    assert names(atlas_volume_paths(root, only=[30, 24])) == ["GA24_a", "GA30_c"]
    pairs = atlas_volume_paths(root, only=[28])
    assert pairs == [(root / "GA28_b" / "srr.nii.gz", root / "GA28_b" / "mask.nii.gz")]
    volumes, sources = load_volumes(pairs)
    assert sources == [str(root / "GA28_b" / "srr.nii.gz")] and len(volumes) == 1


def test_atlas_paths_near_takes_the_ages_within_the_window_or_the_nearest(tmp_path, rng):
    root = _atlas(tmp_path, rng, names=("GA24_a", "GA25_x", "GA25_y", "GA28_b", "GA30_c"))
    names = lambda pairs: [v.parent.name for v, _ in pairs]  # noqa: E731
    assert names(atlas_paths_near(root, 24.4)) == ["GA24_a", "GA25_x", "GA25_y"]
    assert names(atlas_paths_near(root, 24)) == ["GA24_a", "GA25_x", "GA25_y"]  # 1 week: in
    assert names(atlas_paths_near(root, 29)) == ["GA28_b", "GA30_c"]  # 1 week either side
    assert names(atlas_paths_near(root, 29, window=0.5)) == ["GA28_b", "GA30_c"]  # the nearest
    assert names(atlas_paths_near(root, 28, window=0)) == ["GA28_b"]
    assert names(atlas_paths_near(root, 40)) == ["GA30_c"]
    assert names(atlas_paths_near(root, 26.5, window=2)) == ["GA25_x", "GA25_y", "GA28_b"]
    assert names(atlas_paths_near(root, 29.6, window=2)) == ["GA30_c", "GA28_b"]  # nearest first
    with pytest.raises(ValueError, match=r"'weeks' must be a positive number, got 0"):
        atlas_paths_near(root, 0)
    with pytest.raises(ValueError, match=r"'window' must be >= 0 weeks, got -1"):
        atlas_paths_near(root, 28, window=-1)
    with pytest.raises(VolumeSourceError, match="is not a folder"):
        atlas_paths_near(tmp_path / "missing", 28)


def test_atlas_volume_paths_errors(tmp_path, rng):
    with pytest.raises(VolumeSourceError, match="is not a folder"):
        atlas_volume_paths(tmp_path / "missing")
    root = _atlas(tmp_path, rng)
    with pytest.raises(VolumeSourceError, match=r"no GA.*volumes left") as info:
        atlas_volume_paths(root, hold_out=[24, 28, 30])
    assert info.value.missing_ages == ()
    with pytest.raises(VolumeSourceError, match="GA 32: no such") as info:
        atlas_volume_paths(root, only=[28, 32])
    assert info.value.missing_ages == (32,)
    (root / "GAxx").mkdir()
    with pytest.raises(VolumeSourceError, match="not named GA<weeks>"):
        atlas_volume_paths(root)


def test_load_volumes_defaults_to_phantoms():
    volumes, sources = load_volumes(phantom_ages=(22.0,))
    assert sources == ["phantom GA 22"] and len(volumes) == 1
    assert bool(volumes[0].mask.any())
