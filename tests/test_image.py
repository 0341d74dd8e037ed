"""NIfTI I/O with correct affines (checked against SimpleITK), and world-point sampling."""

from __future__ import annotations

import gzip

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813 (the usual alias)
import torch
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from svr.files import OutputExistsError
from svr.image import Image, ImageError, load_nifti, sample_world, save_nifti, world_to_voxel


def oblique_affine(rng: np.random.Generator) -> np.ndarray:
    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix() @ np.diag([0.8, 1.1, 3.0])
    affine[:3, 3] = rng.normal(scale=30, size=3)
    return affine


def write(path, array, affine) -> None:
    nib.save(nib.Nifti1Image(np.asarray(array, dtype=np.float32), affine), str(path))


def sitk_affine(path) -> np.ndarray:
    """Voxel -> RAS world affine from SimpleITK's LPS origin/spacing/direction."""
    img = sitk.ReadImage(str(path))
    direction = np.array(img.GetDirection()).reshape(3, 3)
    lps = np.eye(4)
    lps[:3, :3] = direction * np.array(img.GetSpacing())
    lps[:3, 3] = img.GetOrigin()
    return np.diag([-1.0, -1.0, 1.0, 1.0]) @ lps


def test_save_load_round_trip_and_affine_agrees_with_simpleitk(tmp_path, rng):
    affine = oblique_affine(rng)
    data = torch.from_numpy(rng.normal(size=(7, 9, 5))).float()
    path = save_nifti(Image(data, torch.from_numpy(affine)), tmp_path / "x.nii.gz")
    loaded = load_nifti(path)
    torch.testing.assert_close(loaded.data, data)
    np.testing.assert_allclose(loaded.affine.numpy(), affine, atol=1e-5)
    np.testing.assert_allclose(sitk_affine(path), loaded.affine.numpy(), atol=1e-4)
    header = nib.load(str(path)).header
    assert int(header["sform_code"]) == 1 and int(header["qform_code"]) == 1
    assert header.get_data_dtype() == np.float32
    np.testing.assert_allclose(loaded.spacing.numpy(), [0.8, 1.1, 3.0], rtol=1e-5)


def test_save_refuses_to_overwrite_and_leaves_no_temporary_files(tmp_path):
    img = Image(torch.zeros(2, 2, 2), torch.eye(4, dtype=torch.float64))
    path = save_nifti(img, tmp_path / "x.nii")
    with pytest.raises(OutputExistsError, match="output exists"):
        save_nifti(img, path)
    save_nifti(Image(torch.ones(2, 2, 2), img.affine), path, overwrite=True)
    assert load_nifti(path).data.sum() == 8
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.nii"]
    with pytest.raises(ImageError, match=r"must end in \.nii"):
        save_nifti(img, tmp_path / "x.png")


def _bad_files(tmp_path):
    eye = np.eye(4)
    write(tmp_path / "good.nii.gz", np.ones((4, 4, 4)), eye)
    (tmp_path / "text.nii.gz").write_bytes(b"this is not a NIfTI file at all")
    raw = gzip.compress((tmp_path / "good.nii.gz").read_bytes())
    write(tmp_path / "big.nii.gz", np.random.default_rng(0).normal(size=(20, 20, 20)), eye)
    (tmp_path / "truncated.nii.gz").write_bytes((tmp_path / "big.nii.gz").read_bytes()[:2000])
    (tmp_path / "double.nii.gz").write_bytes(raw[:60])
    write(tmp_path / "flat.nii.gz", np.ones((4, 4)), eye)
    write(tmp_path / "four_d.nii.gz", np.ones((4, 4, 4, 3)), eye)
    nan = np.ones((4, 4, 4))
    nan[1, 2, 3] = np.nan
    write(tmp_path / "nan.nii.gz", nan, eye)
    write(tmp_path / "empty.nii.gz", np.ones((4, 0, 4)), eye)
    singular = eye.copy()
    singular[2, 2] = 0.0
    nii = nib.Nifti1Image(np.ones((4, 4, 4), dtype=np.float32), None)
    nii.set_sform(singular, code=1)  # a singular sform, no qform: nibabel cannot write it to both
    nib.save(nii, str(tmp_path / "singular.nii.gz"))
    (tmp_path / "image.png").write_bytes(b"\x89PNG")
    return {
        "missing.nii.gz": "no such file",
        "text.nii.gz": "cannot read as NIfTI",
        "truncated.nii.gz": "cannot read as NIfTI",
        "double.nii.gz": "cannot read as NIfTI",
        "flat.nii.gz": "expected a 3D image, got 2D",
        "four_d.nii.gz": "expected a 3D image, got 4D",
        "nan.nii.gz": "1 voxels are NaN or Inf",
        "empty.nii.gz": "image is empty",
        "singular.nii.gz": "singular",
        "image.png": "not a NIfTI file name",
    }


def test_bad_files_raise_one_clear_error_naming_the_file(tmp_path):
    for name, problem in _bad_files(tmp_path).items():
        with pytest.raises(ImageError) as info:
            load_nifti(tmp_path / name)
        message = str(info.value)
        assert message.startswith(f"{tmp_path / name}: ") and problem in message, message
        assert "\n" not in message


def test_trailing_singleton_dimension_is_dropped(tmp_path):
    write(tmp_path / "x.nii", np.ones((3, 4, 5, 1)), np.eye(4))
    assert load_nifti(tmp_path / "x.nii").shape == (3, 4, 5)


def test_sample_world_matches_voxels_and_scipy(rng):
    affine = torch.from_numpy(oblique_affine(rng))
    data = torch.from_numpy(rng.normal(size=(12, 10, 8)))
    img = Image(data, affine)
    idx = torch.from_numpy(rng.integers(0, [12, 10, 8], size=(50, 3))).double()
    world = idx @ affine[:3, :3].T + affine[:3, 3]
    torch.testing.assert_close(sample_world(img, world), data[tuple(idx.long().T)])
    torch.testing.assert_close(world_to_voxel(affine, world), idx)
    inside = torch.from_numpy(rng.uniform(0, [11, 9, 7], size=(200, 3)))
    world = inside @ affine[:3, :3].T + affine[:3, 3]
    want = map_coordinates(data.numpy(), inside.numpy().T, order=1)
    np.testing.assert_allclose(sample_world(img, world).numpy(), want, rtol=1e-10, atol=1e-10)
    nearest = sample_world(img, world, mode="nearest")
    np.testing.assert_allclose(
        nearest.numpy(), map_coordinates(data.numpy(), inside.numpy().T, order=0), atol=1e-12
    )
    outside = torch.tensor([[1e4, 0.0, 0.0]], dtype=torch.float64)
    assert sample_world(img, outside).item() == 0.0


def test_image_validation():
    with pytest.raises(ValueError, match="3D"):
        Image(torch.zeros(2, 2), torch.eye(4))
    with pytest.raises(ValueError, match="'points'"):
        sample_world(
            Image(torch.zeros(2, 2, 2), torch.eye(4, dtype=torch.float64)), torch.zeros(3, 2)
        )


def test_real_atlas_affine_matches_simpleitk(shared_data):
    path = shared_data / "atlas" / "sb-fidon2021" / "GA28_operated" / "srr.nii.gz"
    img = load_nifti(path)
    assert img.shape == (135, 189, 155)
    np.testing.assert_allclose(img.affine.numpy(), sitk_affine(path), atol=1e-4)


def test_voxel_to_world_matches_nibabel_and_inverts_world_to_voxel():
    from nibabel.affines import apply_affine

    from svr.image import voxel_centres, voxel_to_world, world_to_voxel

    rng = np.random.default_rng(4)
    affine = np.eye(4)
    affine[:3, :3] = rng.normal(size=(3, 3))
    affine[:3, 3] = rng.normal(scale=20, size=3)
    voxels = rng.uniform(-2, 30, size=(17, 3))
    got = voxel_to_world(torch.from_numpy(affine), torch.from_numpy(voxels))
    np.testing.assert_allclose(got.numpy(), apply_affine(affine, voxels), atol=1e-10)
    back = world_to_voxel(torch.from_numpy(affine), got)
    np.testing.assert_allclose(back.numpy(), voxels, atol=1e-9)
    image = Image(torch.zeros(3, 4, 5), torch.from_numpy(affine))
    centres = voxel_centres(image)
    assert centres.shape == (3, 4, 5, 3)
    np.testing.assert_allclose(centres[2, 1, 4].numpy(), apply_affine(affine, [2, 1, 4]))


def test_mask_on_grid_same_grid_and_resampled():
    from svr.image import mask_on_grid, resample_to_grid

    affine = torch.eye(4, dtype=torch.float64)
    data = torch.zeros(8, 8, 8)
    data[2:6, 3:5, 1:7] = 1.0
    mask = Image(data, affine)
    torch.testing.assert_close(mask_on_grid(mask, mask), data > 0.5)
    # a grid of half the spacing over the same field: nearest neighbour by world position
    fine_affine = torch.diag(torch.tensor([0.5, 0.5, 0.5, 1.0], dtype=torch.float64))
    fine = Image(torch.zeros(16, 16, 16), fine_affine)
    on_fine = mask_on_grid(mask, fine)
    want = resample_to_grid(mask, fine, mode="nearest").data > 0.5
    torch.testing.assert_close(on_fine, want)
    assert on_fine[4, 6, 2] and not on_fine[0, 0, 0]
    assert int(on_fine.sum()) > 8 * int((data > 0.5).sum()) * 0.5


def test_intensity_scale_percentile_and_errors():
    from svr.image import intensity_scale

    values = torch.arange(1, 101, dtype=torch.float32)
    assert intensity_scale(values, "x") == pytest.approx(np.percentile(np.arange(1, 101), 99))
    with pytest.raises(ValueError, match=r"stack\.nii: all voxels are zero"):
        intensity_scale(torch.zeros(0), "stack.nii")
    with pytest.raises(ValueError, match=r"stack\.nii: the 99th percentile .* is 0\.0"):
        intensity_scale(torch.zeros(10), "stack.nii")


def test_largest_component_keeps_the_biggest_face_connected_piece():
    from svr.image import largest_component

    mask = np.zeros((8, 8, 3), dtype=bool)
    mask[0:3, 0:3, 0] = True  # 9 voxels
    mask[5:8, 5:8, :] = True  # 27 voxels
    mask[4, 4, 1] = True  # touches the big piece only along an edge: not face-connected
    assert np.array_equal(
        largest_component(mask), np.pad(np.ones((3, 3, 3), bool), ((5, 0),) * 2 + ((0, 0),))
    )
    flat = mask[:, :, 0]
    assert largest_component(flat).sum() == 9
    empty = np.zeros((4, 4), dtype=bool)
    assert not largest_component(empty).any()
