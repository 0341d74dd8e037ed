"""Reconstruction outputs: volume, transforms table, NeSVoR slice folder, QA figure."""

from __future__ import annotations

import csv
import json
import re

import nibabel as nib
import numpy as np
import pytest
import torch
from synthetic import ellipsoid_brain

from svr.files import OutputExistsError
from svr.geometry import so3_exp, vector_to_se3
from svr.image import Image, ImageError, load_nifti, resample_to_grid, stack_slice_poses
from svr.models.predict import load_slice_folder
from svr.pose_io import COLUMNS, PoseTable, read_pose_table, write_pose_table
from svr.reconstruction.outputs import (
    slice_affines,
    write_slices_folder,
    write_transforms,
    write_volume,
)
from svr.reconstruction.qa import axis_aligned, qa_figure
from svr.reconstruction.result import ReconstructionResult
from svr.reconstruction.slices import SliceSet, extract_slices
from svr.reconstruction.stacks import prepare_stacks

F64 = torch.float64


def oblique_stack(seed: int, shape: tuple[int, int, int]) -> tuple[Image, Image]:
    """A stack at 1.5 x 1.5 x 3 mm in an oblique orientation with a box mask off-centre."""
    generator = torch.Generator().manual_seed(seed)
    affine = torch.eye(4, dtype=F64)
    rotation = so3_exp(torch.randn(3, generator=generator, dtype=F64))
    affine[:3, :3] = rotation * torch.tensor([1.5, 1.5, 3.0], dtype=F64)
    affine[:3, 3] = 20 * torch.randn(3, generator=generator, dtype=F64)
    data = 1 + torch.rand(shape, generator=generator)
    mask = torch.zeros(shape)
    mask[3:14, 5:15, 1 : shape[2] - 2] = 1  # crops in-plane and drops planes
    return Image(data, affine), Image(mask, affine.clone())


@pytest.fixture
def stacks() -> list[Image]:
    return [oblique_stack(1, (20, 22, 8)), oblique_stack(2, (18, 24, 7))]


@pytest.fixture
def slices(stacks) -> SliceSet:
    prepared = prepare_stacks(
        [s for s, _ in stacks], [m for _, m in stacks], 3.0, names=["a.nii.gz", "b.nii.gz"]
    )
    return extract_slices(prepared)


def make_result(slices: SliceSet) -> ReconstructionResult:
    volume, mask = ellipsoid_brain(24, 2.0, (16.0, 12.0, 10.0), seed=3, origin_mm=(-23.0,) * 3)
    n = len(slices)
    generator = torch.Generator().manual_seed(0)
    return ReconstructionResult(
        volume=volume,
        mask=mask,
        initial_volume=Image(volume.data * 0.5 + 0.2 * mask.data, volume.affine),
        slices=slices,
        slice_ncc=torch.rand(n, generator=generator),
        slice_weights=torch.rand(n, generator=generator),
        excluded=torch.arange(n) % 5 == 2,
        initialisation=("stack", "cnn"),
        timings_s={"slices": 0.1, "initialisation": 2.0, "super-resolution": 3.5},
    )


def moved(slices: SliceSet) -> SliceSet:
    """The slices moved by one rigid transform into the canonical frame."""
    G = torch.eye(4, dtype=F64)
    G[:3, :3] = so3_exp(torch.tensor([0.3, -0.2, 0.9], dtype=F64))
    G[:3, 3] = torch.tensor([5.0, -7.0, 2.0], dtype=F64)
    return slices.with_poses(G @ slices.poses, "canonical")


# --- write_volume ---


def test_write_volume_is_float32_with_the_affine(tmp_path):
    volume, _ = ellipsoid_brain(12, 2.0, (8.0, 6.0, 5.0), seed=0, origin_mm=(1.0, 2.0, 3.0))
    path = write_volume(Image(volume.data.double(), volume.affine), tmp_path / "v.nii.gz")
    assert nib.load(path).get_data_dtype() == np.float32
    back = load_nifti(path)
    torch.testing.assert_close(back.data, volume.data)
    torch.testing.assert_close(back.affine, volume.affine)
    with pytest.raises(OutputExistsError):
        write_volume(volume, path)
    with pytest.raises(ImageError, match=r"v\.mgz: output must end in \.nii or \.nii\.gz"):
        write_volume(volume, tmp_path / "v.mgz")


# --- write_transforms ---


@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_transforms_are_the_poses_of_the_files_k_planes(stacks, slices, tmp_path, suffix):
    path = write_transforms(slices, tmp_path / f"t{suffix}")
    table = read_pose_table(path)
    assert table.frame == "scanner" and len(table.files) == len(slices)
    names = [slices.stack_names[int(s)] for s in slices.stack_ids]
    assert table.files == names
    assert table.slice_indices.tolist() == slices.slice_indices.tolist()
    for row, (name, k) in enumerate(zip(table.files, table.slice_indices.tolist(), strict=True)):
        image = stacks[slices.stack_names.index(name)][0]
        expected = stack_slice_poses(image)[k]  # the file's own k-plane (cropping undone)
        torch.testing.assert_close(vector_to_se3(table.poses[row]), expected)
    assert set(table.slice_indices.tolist()) == set(range(1, 6))  # empty-mask planes dropped


def test_result_transforms_carry_ncc_weight_and_exclusion(stacks, slices, tmp_path):
    result = make_result(moved(slices))
    table = read_pose_table(write_transforms(result, tmp_path / "t.json"))
    assert table.frame == "canonical"
    rows = json.loads((tmp_path / "t.json").read_text())["slices"]
    assert [r["ncc"] for r in rows] == pytest.approx(result.slice_ncc.tolist())
    assert [r["weight"] for r in rows] == pytest.approx(result.slice_weights.tolist())
    assert [r["excluded"] for r in rows] == result.excluded.tolist()
    G = result.slices.poses[0] @ torch.linalg.inv(slices.poses[0])
    name, k = table.files[0], int(table.slice_indices[0])
    plane = stack_slice_poses(stacks[slices.stack_names.index(name)][0])[k]
    torch.testing.assert_close(vector_to_se3(table.poses[0]), G @ plane)
    with (write_transforms(result, tmp_path / "t.csv")).open(newline="") as f:
        csv_rows = list(csv.DictReader(f))
    assert [r["excluded"] == "True" for r in csv_rows] == result.excluded.tolist()
    assert float(csv_rows[3]["ncc"]) == pytest.approx(float(result.slice_ncc[3]))
    with pytest.raises(OutputExistsError):
        write_transforms(result, tmp_path / "t.csv")
    with pytest.raises(ValueError, match=r"t\.txt: pose tables are written as \.csv or \.json"):
        write_transforms(result, tmp_path / "t.txt")


def test_pose_table_extra_columns(tmp_path):
    poses = torch.tensor([[0.1, 0.2, 0.3, 1.0, 2.0, 3.0], [0.0] * 6], dtype=F64)
    table = PoseTable(["s.nii.gz"] * 2, torch.tensor([4, 5]), poses, "atlas")
    extra = {"score": [0.5, 0.25], "note": ["a", "b"]}
    back = read_pose_table(write_pose_table(table, tmp_path / "extra.csv", extra_columns=extra))
    assert back.files == table.files and back.frame == "atlas"
    torch.testing.assert_close(back.poses, poses, rtol=0, atol=1e-15)
    with (tmp_path / "extra.csv").open(newline="") as f:
        header = next(csv.reader(f))
    assert header == [*COLUMNS, "score", "note"]
    with pytest.raises(ValueError, match="'frame' is a standard pose-table column"):
        write_pose_table(table, tmp_path / "x.csv", extra_columns={"frame": ["a", "b"]})
    with pytest.raises(ValueError, match="'score' has 1 values for 2 slices"):
        write_pose_table(table, tmp_path / "x.json", extra_columns={"score": [1.0]})
    assert not (tmp_path / "x.csv").exists() and not (tmp_path / "x.json").exists()


# --- write_slices_folder ---


def test_slice_folder_round_trip(slices, tmp_path):
    posed = moved(slices)
    keep = torch.ones(len(slices), dtype=torch.bool)
    keep[[1, 4]] = False
    folder = write_slices_folder(posed, tmp_path / "slices", keep=keep)
    items = load_slice_folder(folder)
    assert [s.index for s in items] == [n for n in range(len(slices)) if n not in (1, 4)]
    h, w = slices.size
    for item in items:
        n = item.index
        assert item.image.shape == (h, w, 1) and item.mask is not None
        torch.testing.assert_close(item.image.data[:, :, 0], posed.images[n])
        assert torch.equal(item.mask.data[:, :, 0] > 0.5, posed.masks[n])
        # float32 sform: 1e-4 mm
        torch.testing.assert_close(
            stack_slice_poses(item.image)[0], posed.poses[n], atol=1e-4, rtol=1e-5
        )
        spacing = item.image.spacing
        expected = torch.tensor([*posed.spacing_mm[n].tolist(), 3.0], dtype=F64)
        torch.testing.assert_close(spacing, expected, atol=1e-5, rtol=1e-5)
    # Pixel (a, b) sits at T (u, v, 0), u = (a - (H - 1) / 2) s_u, v = (b - (W - 1) / 2) s_v.
    a, b = 2, w - 3
    su, sv = posed.spacing_mm[0].tolist()
    local = torch.tensor([(a - (h - 1) / 2) * su, (b - (w - 1) / 2) * sv, 0.0, 1.0], dtype=F64)
    voxel = torch.tensor([a, b, 0.0, 1.0], dtype=F64)
    torch.testing.assert_close(slice_affines(posed)[0] @ voxel, posed.poses[0] @ local)


def test_slice_folder_is_atomic_and_never_overwritten(slices, tmp_path):
    folder = tmp_path / "slices"
    folder.mkdir()
    (folder / "keep.txt").write_text("keep me")
    with pytest.raises(OutputExistsError):
        write_slices_folder(slices, folder)
    assert (folder / "keep.txt").read_text() == "keep me"
    write_slices_folder(slices, folder, overwrite=True)
    assert not (folder / "keep.txt").exists() and (folder / "mask_0.nii.gz").exists()
    assert len(load_slice_folder(folder)) == len(slices)
    with pytest.raises(ValueError, match=r"'keep' must have shape"):
        write_slices_folder(slices, tmp_path / "other", keep=torch.ones(2, dtype=torch.bool))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slices"]


# --- QA ---


def test_qa_figure_png_and_pdf(slices, tmp_path):
    result = make_result(slices)
    reference = Image(result.volume.data.flip(0), result.volume.affine)
    png = qa_figure(result, tmp_path / "qa.png", reference=reference)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    pdf = qa_figure(result, tmp_path / "qa.pdf")
    assert pdf.read_bytes()[:5] == b"%PDF-"
    with pytest.raises(OutputExistsError):
        qa_figure(result, png)
    with pytest.raises(ValueError, match=r"qa\.jpg: QA figures are written as \.png or \.pdf"):
        qa_figure(result, tmp_path / "qa.jpg")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["qa.pdf", "qa.png"]
    # A canonical-frame result whose affine was relabelled by a turn is drawn in world-aligned
    # planes.
    from dataclasses import replace

    turn = vector_to_se3(torch.tensor([0.2, 0.4, -0.3, 1.0, 2.0, 3.0], dtype=F64))
    canonical = replace(
        result,
        slices=moved(slices),
        volume=Image(result.volume.data, turn @ result.volume.affine),
        mask=Image(result.mask.data, turn @ result.mask.affine),
        initial_volume=Image(result.initial_volume.data, turn @ result.initial_volume.affine),
    )
    assert qa_figure(canonical, tmp_path / "canonical.png").stat().st_size > 0


def test_qa_text_carries_the_initialisation_notes(slices):
    from dataclasses import replace

    from svr.reconstruction.qa import NOTE_WIDTH, _text

    result = replace(
        make_result(slices),
        initialisation_notes=("cnn unsure (support 20%, 0 flipped)", "support 90%, 3 flipped"),
    )
    text = _text(result)
    lines = text.split("slices moved from it (median / max deg)\n")[1].splitlines()
    assert [re.sub(r"; moved \d+ / \d+$", "", line) for line in lines[:4]] == [
        "  a.nii.gz: stack",
        "    cnn unsure (support 20%, 0 flipped)",
        "  b.nii.gz: cnn",
        "    support 90%, 3 flipped",
    ]
    # A long note wraps under its stack, whole, so that it does not squeeze the figure.
    long = (
        "learned, score 2.95; packets 130 deg, 165 deg, NCC cnn 0.069 vs packets 0.217 vs "
        "stack -0.029"
    )
    wrapped = _text(replace(result, initialisation_notes=(long, "")))
    lines = wrapped.split("slices moved from it (median / max deg)\n")[1].splitlines()
    note = [line for line in lines if line.startswith("    ")]
    assert len(note) > 1 and all(len(line) <= 4 + NOTE_WIDTH for line in note)
    assert " ".join(line.strip() for line in note) == long
    assert any(line.startswith("  b.nii.gz: cnn; moved ") for line in lines)


def test_axis_aligned_resamples_by_world_position_onto_an_unrotated_grid():
    # A linear function of world position on a turned grid: trilinear sampling is exact for it.
    n, spacing = 20, 2.0
    affine = torch.eye(4, dtype=F64)
    affine[:3, :3] = so3_exp(torch.tensor([0.3, -0.5, 0.8], dtype=F64)) * spacing
    affine[:3, 3] = torch.tensor([4.0, -30.0, 7.0], dtype=F64)
    idx = torch.stack(torch.meshgrid(*[torch.arange(n)] * 3, indexing="ij"), -1).to(F64)
    world = idx @ affine[:3, :3].T + affine[:3, 3]
    slope, offset = torch.tensor([0.7, -1.3, 0.4], dtype=F64), 100.0
    image = Image((world @ slope + offset).float(), affine)
    mask = torch.zeros(n, n, n, dtype=torch.bool)
    mask[6:14, 5:15, 7:13] = True
    aligned = axis_aligned(image, mask)
    assert torch.allclose(aligned.affine[:3, :3], spacing * torch.eye(3, dtype=F64))
    grid = torch.stack(torch.meshgrid(*[torch.arange(k) for k in aligned.shape], indexing="ij"), -1)
    points = grid.to(F64) @ aligned.affine[:3, :3].T + aligned.affine[:3, 3]
    # Every mask voxel's world centre lies on the new grid, with a voxel to spare.
    inside = world[mask]
    low, high = points.reshape(-1, 3).min(0).values, points.reshape(-1, 3).max(0).values
    assert bool((inside >= low + spacing / 2).all() and (inside <= high - spacing / 2).all())
    # Where the new grid's points are well inside the source image, the values are f(world).
    back = (points - affine[:3, 3]) @ torch.linalg.inv(affine[:3, :3]).T
    well_inside = ((back > 1.0) & (back < n - 2.0)).all(-1)
    assert int(well_inside.sum()) > 1000
    torch.testing.assert_close(
        aligned.data.double()[well_inside],
        (points @ slope + offset)[well_inside],
        atol=2e-3,
        rtol=0,
    )


def test_resample_to_grid_by_world_position():
    volume, _ = ellipsoid_brain(16, 2.0, (10.0, 8.0, 6.0), seed=1, origin_mm=(-15.0,) * 3)
    # The same world positions on a grid with swapped axes and shifted origin.
    affine = torch.zeros(4, 4, dtype=F64)
    affine[0, 1] = affine[1, 0] = affine[2, 2] = 2.0
    affine[3, 3] = 1.0
    affine[:3, 3] = torch.tensor([-13.0, -15.0, -15.0], dtype=F64)
    like = Image(torch.zeros(16, 15, 16), affine)
    out = resample_to_grid(volume, like)
    assert out.shape == like.shape and torch.equal(out.affine, affine)
    torch.testing.assert_close(out.data, volume.data.permute(1, 0, 2)[:, 1:], atol=1e-5, rtol=0)


def test_atomic_outputs_follow_the_umask(tmp_path):
    import os

    from svr.files import atomic_directory, atomic_write_text

    old = os.umask(0o022)
    try:
        file = atomic_write_text(tmp_path / "a.txt", "x")
        with atomic_directory(tmp_path / "folder") as tmp:
            (tmp / "b.txt").write_text("y")
    finally:
        os.umask(old)
    assert oct(os.stat(file).st_mode & 0o777) == oct(0o644)
    assert oct(os.stat(tmp_path / "folder").st_mode & 0o777) == oct(0o755)
