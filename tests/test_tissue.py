"""The tissue stage's parts: SimpleITK geometry, biometry on known shapes, fusion, growth."""

from __future__ import annotations

import math

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813
from scipy.spatial.transform import Rotation

from svr.tissue.biometry import atlas_aligned, label_volumes_ml, linear_measures, measure_labels
from svr.tissue.fusion import fuse_labels, local_weights
from svr.tissue.growth import GrowthCurve, suggested_age
from svr.tissue.sitk_images import from_sitk, sitk_affine, to_sitk

LPS = np.diag([-1.0, -1.0, 1.0])


def _oblique_affine() -> np.ndarray:
    affine = np.eye(4)
    rotation = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    affine[:3, :3] = rotation @ np.diag([0.8, 0.9, 1.1])
    affine[:3, 3] = [-12.0, 30.5, 4.25]
    return affine


def test_sitk_image_has_the_nifti_geometry_as_simpleitk_reads_it(tmp_path, rng):
    array = rng.random((7, 6, 5)).astype(np.float32)
    affine = _oblique_affine()
    image = to_sitk(array, affine)
    path = tmp_path / "oblique.nii.gz"
    nib.save(nib.Nifti1Image(array, affine), str(path))
    read = sitk.ReadImage(str(path))  # SimpleITK's own NIfTI reader: the oracle
    np.testing.assert_allclose(image.GetOrigin(), read.GetOrigin(), atol=1e-4)
    np.testing.assert_allclose(image.GetSpacing(), read.GetSpacing(), atol=1e-5)
    np.testing.assert_allclose(image.GetDirection(), read.GetDirection(), atol=1e-5)
    np.testing.assert_array_equal(from_sitk(image), array)
    np.testing.assert_array_equal(from_sitk(read), array)
    np.testing.assert_allclose(sitk_affine(image), affine, atol=1e-9)
    point = image.TransformIndexToPhysicalPoint((3, 2, 4))
    np.testing.assert_allclose(point, LPS @ (affine @ [3, 2, 4, 1])[:3], atol=1e-9)


def test_sitk_image_refuses_shear_and_non_3d():
    sheared = np.eye(4)
    sheared[0, 1] = 0.5
    with pytest.raises(ValueError, match="shear"):
        to_sitk(np.zeros((2, 2, 2)), sheared)
    with pytest.raises(ValueError, match="3D"):
        to_sitk(np.zeros((2, 2)), np.eye(4))


def _shapes(spacing: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of known size on an atlas-aligned grid (1 mm): every measure known exactly."""
    labels = np.zeros((61, 71, 41), np.uint8)
    labels[20:41, 20:51, 15:26] = 1  # cerebrum 21 (x) by 31 (y) mm
    labels[25:34, 5:10, 5:10] = 3  # cerebellum 9 mm wide
    labels[21:28, 22:46, 18:22] = 2  # left ventricle 7 mm wide, 24 mm long
    labels[33:38, 22:46, 18:22] = 2  # right ventricle 5 mm wide
    labels[30, 24:39, 24] = 8  # corpus callosum 15 mm long, on the midline (x = 30)
    affine = np.diag([spacing, spacing, spacing, 1.0])
    return labels, affine


def test_linear_measures_of_boxes_are_their_sizes():
    labels, _ = _shapes()
    measures = linear_measures(labels, 1.0)
    assert measures["brain_bpd_mm"] == 21.0
    assert measures["brain_ofd_mm"] == 31.0
    assert measures["tcd_mm"] == 9.0
    assert measures["atrium_left_mm"] == 7.0
    assert measures["atrium_right_mm"] == 5.0
    assert measures["cc_length_mm"] == 15.0


def test_linear_measures_are_nan_for_missing_structures():
    labels = np.zeros((10, 10, 10), np.uint8)
    labels[2:8, 2:8, 2:8] = 1
    measures = linear_measures(labels, 1.0)
    assert math.isnan(measures["tcd_mm"]) and math.isnan(measures["cc_length_mm"])
    assert math.isnan(measures["atrium_left_mm"])


def test_atrial_width_is_the_widest_disc_of_the_posterior_ventricle():
    labels = np.zeros((60, 70, 9), np.uint8)
    x, y = np.meshgrid(np.arange(60), np.arange(70), indexing="ij")
    labels[(x - 30) ** 2 + ((y - 35) / 1.3) ** 2 <= 26**2, 2:7] = 1  # cerebrum, midline x = 30
    body = (np.abs(x - 16) <= 1.5) & (y >= 20) & (y <= 55)  # the body: a 4 mm wide strip
    atrium = (x - 16) ** 2 + (y - 20) ** 2 <= 5.0**2  # the atrium: a disc 10 mm across
    labels[body | atrium, 4] = 2
    labels[29:32, 30:40, 4] = 2  # the third ventricle, on the midline: not the atrium
    measures = linear_measures(labels, 1.0)
    assert abs(measures["atrium_left_mm"] - 10.0) <= 1.0
    assert math.isnan(measures["atrium_right_mm"])


def test_measures_hold_on_an_oblique_grid_and_a_turned_frame():
    """The same boxes resampled onto an oblique grid (the frame turned 25 deg) measure the same."""
    labels, _ = _shapes()
    turn = Rotation.from_euler("xyz", [10, -15, 18], degrees=True).as_matrix()
    # a volume whose world frame is the atlas frame turned by `turn`: world = turn.T @ atlas
    oblique = np.eye(4)
    oblique[:3, :3] = turn.T * 0.5
    centre = np.array(labels.shape) / 2.0
    oblique[:3, 3] = turn.T @ centre - oblique[:3, :3] @ (np.array([130, 150, 90]) / 2.0)
    index = np.stack(np.meshgrid(*[np.arange(n) for n in (130, 150, 90)], indexing="ij"), -1)
    atlas_points = (index @ oblique[:3, :3].T + oblique[:3, 3]) @ turn.T
    source = np.floor(atlas_points + 0.5).astype(int) - 0  # nearest atlas voxel (1 mm grid)
    valid = ((source >= 0) & (source < np.array(labels.shape))).all(-1)
    resampled = np.zeros(index.shape[:3], np.uint8)
    resampled[valid] = labels[tuple(source[valid].T)]
    truth = linear_measures(labels, 1.0)
    measured = measure_labels(resampled, oblique, rotation=turn).measures_mm
    for key, value in truth.items():
        assert abs(measured[key] - value) <= 1.0, key
    # not correcting for the turn measures along the wrong axes
    wrong = measure_labels(resampled, oblique).measures_mm
    assert abs(wrong["brain_ofd_mm"] - truth["brain_ofd_mm"]) > 1.0


def test_atlas_aligned_keeps_an_aligned_map_as_is():
    labels, affine = _shapes()
    (out,), spacing = atlas_aligned([labels], affine)
    assert out is labels and spacing == 1.0


def test_volumes_are_voxel_counts_times_voxel_volume():
    labels, _ = _shapes()
    affine = np.diag([0.5, 0.6, 0.7, 1.0])
    volumes = label_volumes_ml(labels, affine)
    voxel_ml = 0.5 * 0.6 * 0.7 / 1000.0
    assert volumes["white_matter"] == pytest.approx((labels == 1).sum() * voxel_ml)
    assert volumes["ventricles"] == pytest.approx((labels == 2).sum() * voxel_ml)
    assert volumes["intracranial"] == pytest.approx((labels > 0).sum() * voxel_ml)
    assert volumes["brain_tissue"] == pytest.approx(
        np.isin(labels, [1, 3, 5, 6, 7, 8]).sum() * voxel_ml
    )


def test_local_weights_favour_the_atlas_that_matches_there(rng):
    volume = rng.random((20, 20, 20)).astype(np.float32)
    first = 2.0 * volume + 1.0  # matches (up to a linear map) on the first half only
    first[10:] = rng.random((10, 20, 20))
    second = 3.0 * volume  # matches on the second half only
    second[:10] = rng.random((10, 20, 20))
    mask = np.ones(volume.shape, bool)
    weights = local_weights(volume, [first, second], mask, (1.0, 1.0, 1.0), power=1.0)
    np.testing.assert_allclose(weights.sum(0), 1.0, atol=1e-5)
    assert weights[0, :7].mean() > 0.6 and weights[0, 13:].mean() < 0.4
    exact = local_weights(volume, [2.0 * volume + 1.0, second], mask, (1.0, 1.0, 1.0), 1.0)
    assert exact[0].min() > 0.9
    majority = local_weights(volume, [first, second], mask, (1.0, 1.0, 1.0), power=0.0)
    np.testing.assert_allclose(majority, 0.5)


def test_fused_labels_and_agreement():
    one = np.zeros((3, 4, 1, 1), np.float32)
    two = np.zeros((3, 4, 1, 1), np.float32)
    one[1] = 1.0  # atlas one: label 1 everywhere
    two[1, :2] = 1.0  # atlas two: label 1 on the first two voxels, 2 on the others
    two[2, 2:] = 1.0
    weights = np.array([0.7, 0.3], np.float32)[:, None, None, None] * np.ones(
        (2, 4, 1, 1), np.float32
    )
    mask = np.array([True, True, True, False])[:, None, None]
    fused = fuse_labels([one, two], weights, mask)
    np.testing.assert_array_equal(fused.labels[:, 0, 0], [1, 1, 1, 0])
    np.testing.assert_allclose(fused.probability[:, 0, 0], [1.0, 1.0, 0.7, 1.0])
    np.testing.assert_allclose(fused.agreement[:, 0, 0], [1.0, 1.0, 0.5, 1.0])
    with pytest.raises(ValueError, match="atlases"):
        fuse_labels([one], weights, mask)


def test_suggested_age_reads_the_curve_back():
    ages = np.arange(21.0, 35.0)
    values = 3.0 * ages**2 - 80.0 * ages + 600.0
    curve = GrowthCurve("x", ages, values, np.polyfit(ages, values, 2))
    for weeks in (23.0, 27.5, 33.0):
        assert suggested_age(curve, float(curve.at(weeks))) == pytest.approx(weeks, abs=0.03)
    assert math.isnan(suggested_age(curve, math.nan))
    flat = GrowthCurve("y", ages, -values, np.polyfit(ages, -values, 2))
    assert math.isnan(suggested_age(flat, -1000.0))


def test_labels_are_written_with_the_references_header(tmp_path, rng):
    from svr.image import ImageError, save_labels_like

    affine = _oblique_affine()
    reference = tmp_path / "volume.nii.gz"
    nib.save(nib.Nifti1Image(rng.random((6, 5, 4)).astype(np.float32), affine), str(reference))
    labels = rng.integers(0, 9, (6, 5, 4))
    save_labels_like(labels, reference, tmp_path / "dseg.nii.gz")
    written = nib.load(str(tmp_path / "dseg.nii.gz"))
    assert written.get_data_dtype() == np.uint8
    np.testing.assert_array_equal(np.asarray(written.dataobj), labels)
    np.testing.assert_allclose(written.affine, nib.load(str(reference)).affine)
    with pytest.raises(ImageError, match=r"0\.\.255"):
        save_labels_like(labels + 300, reference, tmp_path / "big.nii.gz")
    with pytest.raises(ImageError, match="label map shape"):
        save_labels_like(labels[:3], reference, tmp_path / "small.nii.gz")
