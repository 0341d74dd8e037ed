"""Stacks from NIfTI files: crop geometry (nibabel oracle), slice poses, errors, masks, N4."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from svr.image import Image, ImageError, load_nifti, stack_slice_poses
from svr.masking import MaskingConfig, auto_masks
from svr.reconstruction.slices import extract_slices, plane_poses
from svr.reconstruction.stacks import StackConfig, load_stacks, prepare_stacks

BRAIN_CENTRE = np.array([2.0, -1.0, 4.0])
BRAIN_AXES = np.array([18.0, 14.0, 12.0])


def make_affine(
    rotvec: tuple[float, float, float],
    spacing: tuple[float, float, float],
    shape: tuple[int, int, int],
    centre_mm: tuple[float, float, float],
    base: np.ndarray | None = None,
) -> np.ndarray:
    """Voxel -> world affine: rotation ``Rot(rotvec) @ base``, voxel sizes, array centre."""
    rotation = Rotation.from_rotvec(rotvec).as_matrix() @ (np.eye(3) if base is None else base)
    affine = np.eye(4)
    affine[:3, :3] = rotation * np.asarray(spacing)
    affine[:3, 3] = np.asarray(centre_mm) - affine[:3, :3] @ ((np.asarray(shape) - 1) / 2)
    return affine


def voxel_world(affine: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """(*shape, 3) world mm of every voxel centre."""
    index = np.moveaxis(np.indices(shape), 0, -1).astype(np.float64)
    return index @ affine[:3, :3].T + affine[:3, 3]


def in_ellipsoid(points: np.ndarray, centre: np.ndarray, axes: np.ndarray) -> np.ndarray:
    return (((points - centre) / axes) ** 2).sum(-1) < 1


def write(path: Path, data: np.ndarray, affine: np.ndarray) -> Path:
    nib.save(nib.Nifti1Image(np.asarray(data, dtype=np.float32), affine), str(path))
    return path


def file_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The data and affine as nibabel reads them (the oracle)."""
    img = nib.load(str(path))
    return np.asarray(img.dataobj, dtype=np.float64), np.asarray(img.affine, dtype=np.float64)


# Three oblique stacks of different shapes and spacings (stack 0 left-handed, as scanners write
# them; stack 2 placed so that the brain reaches its array's border, so the crop is clipped).
STACKS = [
    dict(shape=(40, 36, 14), spacing=(1.0, 1.0, 3.0), rotvec=(0.3, -0.5, 0.9), centre=(5, -3, 10)),
    dict(shape=(33, 45, 12), spacing=(1.2, 0.9, 2.5), rotvec=(1.2, 0.4, -0.2), centre=(0, 0, 0)),
    dict(shape=(38, 30, 11), spacing=(1.1, 1.1, 3.3), rotvec=(-0.7, 0.2, 0.5), centre=(15, 8, 0)),
]
GAP_PLANE = 7  # stack 0's mask is emptied on this plane


@pytest.fixture
def oblique_files(tmp_path, rng) -> tuple[list[Path], list[Path]]:
    """Random intensities (every voxel distinct) and ellipsoid masks, written as NIfTI files."""
    stacks, masks = [], []
    for n, spec in enumerate(STACKS):
        base = np.diag([-1.0, 1.0, 1.0]) if n == 0 else None
        affine = make_affine(spec["rotvec"], spec["spacing"], spec["shape"], spec["centre"], base)
        mask = in_ellipsoid(voxel_world(affine, spec["shape"]), BRAIN_CENTRE, BRAIN_AXES)
        if n == 0:
            mask[:, :, GAP_PLANE] = False
        stacks.append(
            write(tmp_path / f"stack{n}.nii.gz", rng.uniform(10, 100, spec["shape"]), affine)
        )
        masks.append(write(tmp_path / f"mask{n}.nii.gz", mask, affine))
    return stacks, masks


def expected_crop(mask: np.ndarray, affine: np.ndarray, margin_mm: float) -> tuple[slice, ...]:
    """The crop of the module docstring, computed independently."""
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    bounds = []
    for axis in range(3):
        present = np.nonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))[0]
        margin = math.ceil(margin_mm / spacing[axis] - 1e-9) if axis < 2 else 0
        bounds.append(
            slice(max(present[0] - margin, 0), min(present[-1] + margin + 1, mask.shape[axis]))
        )
    return tuple(bounds)


@pytest.mark.parametrize("margin_mm", [0.0, 5.0])
def test_cropping_keeps_the_voxels_world_positions_and_values(oblique_files, margin_mm):
    stack_paths, mask_paths = oblique_files
    stacks = load_stacks(stack_paths, mask_paths, 3.0, StackConfig(crop_margin_mm=margin_mm))
    clipped = False
    for stack, stack_path, mask_path in zip(stacks, stack_paths, mask_paths, strict=True):
        data, affine = file_arrays(stack_path)
        mask = file_arrays(mask_path)[0] > 0.5
        crop = expected_crop(mask, affine, margin_mm)
        clipped |= crop[0].start == 0 or crop[1].stop == mask.shape[1]
        assert stack.name == str(stack_path)
        assert stack.full_shape == mask.shape[:2]
        assert stack.crop_origin == (crop[0].start, crop[1].start)
        assert stack.k_indices.tolist() == list(range(crop[2].start, crop[2].stop))
        assert stack.image.shape == data[crop].shape
        assert stack.image.data.dtype == torch.float32 and stack.mask.data.dtype == torch.bool
        assert stack.image.data.device.type == "cpu" and stack.thickness_mm == 3.0
        torch.testing.assert_close(stack.mask.affine, stack.image.affine)
        # Every kept voxel sits where the file puts it and holds its normalised masked value.
        np.testing.assert_allclose(
            voxel_world(stack.image.affine.numpy(), stack.image.shape),
            voxel_world(affine, mask.shape)[crop],
            atol=1e-9,
        )
        scale = np.percentile(data[mask], 99)
        np.testing.assert_allclose(
            stack.image.data.numpy(), np.where(mask, data / scale, 0)[crop], rtol=1e-6
        )
        np.testing.assert_array_equal(stack.mask.data.numpy(), mask[crop])
        assert int(stack.mask.data.sum()) == int(mask.sum())  # the crop holds the whole mask
    assert clipped


def test_slices_are_where_the_files_put_their_voxels(oblique_files):
    stack_paths, mask_paths = oblique_files
    slices = extract_slices(load_stacks(stack_paths, mask_paths, (2.0, 2.5, 3.0)))
    assert slices.stack_names == tuple(str(p) for p in stack_paths)
    assert len({s.image.shape[:2] for s in load_stacks(stack_paths, mask_paths, 2.0)}) == 3
    height, width = slices.size
    a, b = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    for sid, (stack_path, mask_path) in enumerate(zip(stack_paths, mask_paths, strict=True)):
        data, affine = file_arrays(stack_path)
        mask = file_arrays(mask_path)[0] > 0.5
        masked = np.where(mask, data / np.percentile(data[mask], 99), 0)
        rows = slices.stack_slices(sid).numpy()
        planes_with_brain = np.nonzero(mask.any(axis=(0, 1)))[0]
        np.testing.assert_array_equal(slices.slice_indices[rows].numpy(), planes_with_brain)
        assert GAP_PLANE not in planes_with_brain or sid != 0
        np.testing.assert_allclose(slices.thickness_mm[rows].numpy(), (2.0, 2.5, 3.0)[sid])
        for n in rows:
            spacing = slices.spacing_mm[n].numpy()
            plane = np.stack(
                [
                    (a - (height - 1) / 2) * spacing[0],
                    (b - (width - 1) / 2) * spacing[1],
                    0 * a,
                    1 + 0 * a,
                ],
                axis=-1,
            )
            world = plane @ slices.poses[n].numpy().T
            voxel = world @ np.linalg.inv(affine).T
            index = np.rint(voxel[..., :3]).astype(int)
            np.testing.assert_allclose(voxel[..., :3], index, atol=1e-4)
            assert (index[..., 2] == int(slices.slice_indices[n])).all()
            inside = ((index >= 0) & (index < np.array(mask.shape))).all(-1)
            i, j, k = np.where(inside[..., None], index, 0).transpose(2, 0, 1)
            expected_image = np.where(inside, masked[i, j, k], 0)
            np.testing.assert_allclose(slices.images[n].numpy(), expected_image, rtol=1e-6, atol=0)
            np.testing.assert_array_equal(slices.masks[n].numpy(), inside & mask[i, j, k])
        # The reported poses are those of the file's own k-planes.
        file_poses = stack_slice_poses(load_nifti(stack_path))[slices.slice_indices[rows]]
        torch.testing.assert_close(plane_poses(slices)[rows], file_poses, atol=1e-6, rtol=0)


def test_a_mask_on_another_overlapping_grid_is_resampled(oblique_files, tmp_path):
    stack_paths, mask_paths = oblique_files
    mask, affine = file_arrays(mask_paths[1])
    # The mask's bounding box and one voxel around it: another shape, origin and extent.
    lo = [int(np.nonzero(mask.any(axis=tuple({0, 1, 2} - {a})))[0][0]) - 1 for a in range(3)]
    hi = [int(np.nonzero(mask.any(axis=tuple({0, 1, 2} - {a})))[0][-1]) + 2 for a in range(3)]
    lo = [max(v, 0) for v in lo]
    sub_affine = affine.copy()
    sub_affine[:3, 3] = affine[:3, :3] @ np.array(lo, dtype=float) + affine[:3, 3]
    sub = mask[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    assert sub.shape != mask.shape and sub.sum() == mask.sum()
    sub_path = write(tmp_path / "sub_mask.nii", sub, sub_affine)
    same, resampled = (
        load_stacks(stack_paths[1:2], [m], 3.0)[0] for m in (mask_paths[1], sub_path)
    )
    assert resampled.crop_origin == same.crop_origin
    torch.testing.assert_close(resampled.image.affine, same.image.affine)
    torch.testing.assert_close(resampled.mask.data, same.mask.data)
    torch.testing.assert_close(resampled.image.data, same.image.data)


def test_thickness_defaults_to_the_slice_spacing_with_a_warning(oblique_files, caplog):
    stack_paths, mask_paths = oblique_files
    with caplog.at_level(logging.WARNING, logger="svr.reconstruction.stacks"):
        stacks = load_stacks(stack_paths, mask_paths)
    assert [s.thickness_mm for s in stacks] == pytest.approx([3.0, 2.5, 3.3], abs=1e-5)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 3
    for path, message in zip(stack_paths, warnings, strict=True):
        assert message.startswith(str(path)) and "thickness" in message
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="svr.reconstruction.stacks"):
        assert [s.thickness_mm for s in load_stacks(stack_paths, mask_paths, [4.0])] == [4.0] * 3
    assert not caplog.records


# --- errors -------------------------------------------------------------------------------------


def _good(tmp_path: Path) -> tuple[Path, Path, np.ndarray]:
    affine = make_affine((0.2, 0.1, -0.3), (1.0, 1.0, 3.0), (20, 20, 5), (0, 0, 0))
    mask = np.zeros((20, 20, 5))
    mask[5:15, 5:15, 1:4] = 1
    data = np.random.default_rng(0).uniform(1, 2, (20, 20, 5))
    return (
        write(tmp_path / "good.nii.gz", data, affine),
        write(tmp_path / "good_mask.nii.gz", mask, affine),
        affine,
    )


def _load_auto(paths: list[Path], thicknesses: float | None = None):
    """Stacks without masks, as the commands load them: read, the Otsu masks, then preparation."""
    names = [str(path) for path in paths]
    images = [load_nifti(path) for path in paths]
    masks = auto_masks(images, MaskingConfig(method="otsu"), names)
    return prepare_stacks(images, masks, thicknesses, names=names)


def _bad_stack(tmp_path: Path, kind: str) -> tuple[Path, Path | None]:
    """A bad stack (with the good mask) or a bad mask (with the good stack); returns (bad, mask)."""
    _, good_mask, affine = _good(tmp_path)
    ok = np.ones((20, 20, 5))
    if kind == "missing":
        return tmp_path / "missing.nii.gz", None
    if kind == "not nifti":
        (tmp_path / "stack.txt").write_text("not an image")
        return tmp_path / "stack.txt", None
    if kind == "corrupt":
        (tmp_path / "corrupt.nii.gz").write_bytes(b"\x1f\x8b garbage")
        return tmp_path / "corrupt.nii.gz", None
    if kind == "2D":
        return write(tmp_path / "flat.nii", np.ones((20, 20)), affine), None
    if kind == "4D":
        return write(tmp_path / "series.nii", np.ones((20, 20, 5, 2)), affine), None
    if kind == "NaN":
        nan = ok.copy()
        nan[3, 4, 2] = np.nan
        return write(tmp_path / "nan.nii", nan, affine), good_mask
    if kind == "zero-size":
        return write(tmp_path / "empty.nii", np.ones((20, 0, 5)), affine), None
    if kind == "sheared":
        sheared = affine.copy()
        sheared[:3, 1] += 0.2 * affine[:3, 0]
        return write(tmp_path / "sheared.nii", ok, sheared), None
    if kind == "zero intensities":
        return write(tmp_path / "zeros.nii", 0 * ok, affine), good_mask
    if kind == "no automatic mask":
        return write(tmp_path / "constant.nii", ok, affine), None
    raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind",
    [
        "missing",
        "not nifti",
        "corrupt",
        "2D",
        "4D",
        "NaN",
        "zero-size",
        "sheared",
        "zero intensities",
        "no automatic mask",
    ],
)
def test_bad_stacks_raise_one_line_naming_the_file(tmp_path, kind):
    bad, mask = _bad_stack(tmp_path, kind)
    with pytest.raises(ImageError) as err:
        _load_auto([bad]) if mask is None else load_stacks([bad], [mask])
    message = str(err.value)
    assert message.startswith(f"{bad}: ") and "\n" not in message


@pytest.mark.parametrize("kind", ["empty", "elsewhere", "2D"])
def test_bad_masks_raise_one_line_naming_the_mask(tmp_path, kind):
    good, _, affine = _good(tmp_path)
    if kind == "empty":
        bad = write(tmp_path / "empty_mask.nii", np.zeros((20, 20, 5)), affine)
    elif kind == "elsewhere":  # another shape, 200 mm away
        far = affine.copy()
        far[:3, 3] += 200.0
        bad = write(tmp_path / "far_mask.nii", np.ones((12, 14, 5)), far)
    else:
        bad = write(tmp_path / "flat_mask.nii", np.ones((20, 20)), affine)
    with pytest.raises(ImageError) as err:
        load_stacks([good], [bad])
    message = str(err.value)
    assert message.startswith(f"{bad}: ") and "\n" not in message


def test_argument_errors(tmp_path):
    good, good_mask, _ = _good(tmp_path)
    with pytest.raises(ValueError, match="no stacks"):
        load_stacks([], [])
    with pytest.raises(ValueError, match=r"'mask_paths' is None: .*svr.masking.auto_masks"):
        load_stacks([good], None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"'masks' is None: .*svr.masking.auto_masks"):
        prepare_stacks([load_nifti(good)], None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="no stacks"):
        auto_masks([])
    with pytest.raises(ValueError, match="got 1 masks for 2 stacks"):
        load_stacks([good, good], [good_mask])
    with pytest.raises(ValueError, match="got 2 thicknesses for 3 stacks"):
        load_stacks([good] * 3, [good_mask] * 3, [2.0, 3.0])
    for value in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match=f"^{good}: the slice thickness"):
            load_stacks([good], [good_mask], value)
    with pytest.raises(ValueError, match="crop_margin_mm"):
        StackConfig(crop_margin_mm=-1.0)
    with pytest.raises(ValueError, match="n4_shrink_factor"):
        StackConfig(n4_shrink_factor=0)
    with pytest.raises(ValueError, match="'method' must be one of 'network', 'otsu', got 'unet'"):
        MaskingConfig(method="unet")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'fuse' must be false unless method='network'"):
        MaskingConfig(method="otsu", fuse=True)


# --- automatic mask -----------------------------------------------------------------------------

_ORIENTATIONS = {  # in-plane axes and normal as columns
    "axial": np.eye(3),
    "sagittal": np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=float),
    "coronal": np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=float),
}


def test_automatic_mask_finds_the_brain_inside_the_shared_field_of_view(tmp_path, rng):
    """A textured ellipsoid brain; a bright slab joined to it is in the axial stack's view only."""
    brain_axes = np.array([22.0, 17.0, 14.0])
    specs = [  # (orientation, small rotation, shape at 1.5 x 1.5 x 3 mm)
        ("axial", (0.05, -0.04, 0.08), (64, 48, 14)),  # x in +-48 mm: sees the slab
        ("sagittal", (0.1, 0.03, -0.05), (48, 30, 18)),  # x in +-27 mm
        ("coronal", (-0.06, 0.08, 0.04), (38, 30, 16)),  # x in +-28 mm
    ]
    paths, truths = [], []
    for orientation, rotvec, shape in specs:
        affine = make_affine(rotvec, (1.5, 1.5, 3.0), shape, (0, 0, 0), _ORIENTATIONS[orientation])
        x, y, z = np.moveaxis(voxel_world(affine, shape), -1, 0)
        brain = in_ellipsoid(np.stack([x, y, z], -1), np.zeros(3), brain_axes)
        slab = (x > 32) & (x < 46) & (np.abs(y) < 25)
        bridge = (x > 18) & (x <= 32) & (y**2 + z**2 < 16)
        texture = 0.75 + 0.25 * np.sin(x / 4) * np.sin(y / 5) * np.sin(z / 3)
        data = np.where(brain, texture, 0.0) + 0.8 * (slab | bridge) + 0.05
        data = np.abs(data + rng.normal(0, 0.03, shape))
        paths.append(write(tmp_path / f"{orientation}.nii.gz", data, affine))
        truths.append(brain)
    stacks = _load_auto(paths, thicknesses=3.0)
    for stack, truth, path in zip(stacks, truths, paths, strict=True):
        found = np.zeros(truth.shape, dtype=bool)
        i0, j0 = stack.crop_origin
        i, j, _ = stack.mask.shape
        found[i0 : i0 + i, j0 : j0 + j, stack.k_indices.numpy()] = stack.mask.data.numpy()
        dice = 2 * (found & truth).sum() / (found.sum() + truth.sum())
        assert dice > 0.8, (path.name, dice)
        x = voxel_world(file_arrays(path)[1], truth.shape)[..., 0]
        assert not (found & (x > 30)).any()  # the slab, outside the other stacks' view, is left out


def test_prepare_stacks_takes_images_in_memory(oblique_files):
    stack_paths, mask_paths = oblique_files
    images = [load_nifti(p) for p in stack_paths]
    masks = [load_nifti(p) for p in mask_paths]
    in_memory = prepare_stacks(images, masks, 3.0)
    from_files = load_stacks(stack_paths, mask_paths, 3.0)
    assert [s.name for s in in_memory] == ["stack 0", "stack 1", "stack 2"]
    for a, b in zip(in_memory, from_files, strict=True):
        torch.testing.assert_close(a.image.data, b.image.data)
        torch.testing.assert_close(a.image.affine, b.image.affine)
    with pytest.raises(ImageError, match=r"^mask of stack 0: the mask is empty"):
        prepare_stacks(images[:1], [Image(torch.zeros(masks[0].shape), masks[0].affine)], 3.0)


# --- bias field ---------------------------------------------------------------------------------


def test_n4_reduces_a_multiplicative_bias(tmp_path, rng):
    shape = (48, 48, 10)
    affine = make_affine((0.2, -0.1, 0.3), (1.0, 1.0, 3.0), shape, (0, 0, 0))
    points = voxel_world(affine, shape)
    mask = in_ellipsoid(points, np.zeros(3), np.array([20.0, 18.0, 13.0]))
    x, y, z = np.moveaxis(points, -1, 0)
    bias = np.exp(0.3 * x / 20 - 0.2 * (y / 20) ** 2 + 0.1 * z / 15)
    data = np.where(mask, 100.0, 5.0) * bias * (1 + rng.normal(0, 0.01, shape))
    stack_path = write(tmp_path / "biased.nii.gz", data, affine)
    mask_path = write(tmp_path / "mask.nii.gz", mask, affine)

    def cv(config: StackConfig) -> float:
        stack = load_stacks([stack_path], [mask_path], 3.0, config)[0]
        values = stack.image.data[stack.mask.data].double()
        return float(values.std() / values.mean())

    before, after = cv(StackConfig()), cv(StackConfig(bias_correction=True))
    assert before > 0.1
    assert after < 0.4 * before, (before, after)
