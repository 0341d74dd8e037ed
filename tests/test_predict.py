"""Slice-pose prediction: slice preparation geometry and intensities, poses, slice folders, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import svr.cli
from svr.geometry import se3_compose, se3_inverse, so3_exp, vector_to_se3
from svr.image import Image, ImageError, save_nifti, stack_slice_poses
from svr.models.backbones import BackboneConfig
from svr.models.checkpoint import CheckpointError, save_checkpoint
from svr.models.network import ModelConfig, build_model, checkpoint_model_config
from svr.models.predict import (
    load_pose_model,
    load_slice_folder,
    predict_plane_poses,
    predict_slice_folder,
    prepare_stack_slices,
)
from svr.pose_io import read_pose_table
from svr.sampling.slicer import SliceConfig, sample_slices

CONFIG = ModelConfig(backbone=BackboneConfig(width=8, depth=2), input_size=(32, 32), spacing_mm=2.0)
F64 = torch.float64


def save_model(folder: Path, model: torch.nn.Module, config: ModelConfig = CONFIG) -> Path:
    return save_checkpoint(folder, model.state_dict(), checkpoint_model_config(config))


@pytest.fixture(scope="module")
def untrained(tmp_path_factory) -> Path:
    """Checkpoint of an untrained network (its head predicts the identity pose)."""
    return save_model(tmp_path_factory.mktemp("ckpt") / "untrained", build_model(CONFIG))


@pytest.fixture(scope="module")
def perturbed(tmp_path_factory) -> Path:
    """Checkpoint of a network with random head weights (input-dependent predictions)."""
    torch.manual_seed(3)
    model = build_model(CONFIG)
    with torch.no_grad():
        for p in model.head.parameters():
            p.normal_(0.0, 0.1)
    return save_model(tmp_path_factory.mktemp("ckpt") / "perturbed", model)


def oblique_affine(spacing: tuple[float, float, float]) -> torch.Tensor:
    """Voxel -> world affine: a generic rotation, the given voxel sizes and an offset."""
    affine = torch.eye(4, dtype=F64)
    affine[:3, :3] = so3_exp(torch.tensor([0.3, -0.5, 0.9], dtype=F64)) * torch.tensor(
        spacing, dtype=F64
    )
    affine[:3, 3] = torch.tensor([12.0, -40.0, 7.5], dtype=F64)
    return affine


def squares_stack() -> tuple[Image, Image]:
    """48 x 48 x 3 oblique stack at 1 x 1 x 3 mm with in-mask squares of value 100.

    Slice 0: empty mask (and bright voxels outside any mask). Slice 1: a 16 x 16 voxel square at
    i in [20, 36), j in [6, 22) (centroid (27.5, 13.5)). Slice 2: a 10 x 14 square at i in [4, 14),
    j in [30, 44) (centroid (8.5, 36.5)).
    """
    data = torch.zeros(48, 48, 3)
    mask = torch.zeros(48, 48, 3)
    data[:, :, 0] = 500.0
    mask[20:36, 6:22, 1] = 1
    mask[4:14, 30:44, 2] = 1
    data[mask > 0] = 100.0
    affine = oblique_affine((1.0, 1.0, 3.0))
    return Image(data, affine), Image(mask, affine.clone())


def centroid(image: torch.Tensor) -> torch.Tensor:
    """Intensity-weighted (a, b) centroid of an (H, W) image, in pixels."""
    a = torch.arange(image.shape[0], dtype=F64)[:, None]
    b = torch.arange(image.shape[1], dtype=F64)[None, :]
    w = image.double() / image.double().sum()
    return torch.stack([(w * a).sum(), (w * b).sum()])


def test_load_pose_model_returns_an_eval_model(untrained):
    model = load_pose_model(untrained)
    assert model.config == CONFIG and not model.training
    out = model.predict_poses(torch.rand(2, 1, 32, 32))
    assert torch.equal(out, torch.zeros(2, 6))  # untrained head: the identity pose


def test_load_pose_model_errors_name_the_checkpoint(untrained, tmp_path):
    missing = tmp_path / "missing"
    with pytest.raises(CheckpointError, match="missing: checkpoint folder does not exist"):
        load_pose_model(missing)
    other = ModelConfig(backbone=BackboneConfig(width=16, depth=2), input_size=(32, 32))
    wrong = save_model(tmp_path / "wrong", build_model(CONFIG), other)
    with pytest.raises(CheckpointError, match="wrong: weights do not fit the model") as info:
        load_pose_model(wrong)
    assert "\n" not in str(info.value)
    no_model = save_checkpoint(tmp_path / "no_model", build_model(CONFIG).state_dict(), {})
    with pytest.raises(CheckpointError, match='no "model" section'):
        load_pose_model(no_model)


def test_prepared_slices_are_centred_on_the_mask_at_the_model_spacing():
    stack, mask = squares_stack()
    slices, indices = prepare_stack_slices(stack, mask, CONFIG)
    assert slices.shape == (2, 1, 32, 32) and slices.dtype == torch.float32
    assert indices.tolist() == [1, 2]  # slice 0 has an empty mask
    # 16 voxels of 1 mm -> 8 pixels of 2 mm, centred: pixels 12..19 of 32 (centre 15.5).
    expected = torch.zeros(32, 32)
    expected[12:20, 12:20] = 1.0  # in-mask 99th percentile (100) -> 1
    torch.testing.assert_close(slices[0, 0], expected, atol=1e-4, rtol=0)
    torch.testing.assert_close(
        centroid(slices[1, 0]), torch.tensor([15.5, 15.5], dtype=F64), atol=1e-4, rtol=0
    )


def test_stack_slice_poses_follow_the_affine():
    stack, _ = squares_stack()
    poses = stack_slice_poses(stack)
    R = poses[0, :3, :3]
    torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=F64))
    torch.testing.assert_close(R[:, :2], stack.affine[:3, :2])  # unit in-plane axes (1 mm)
    centre = stack.affine[:3, :3] @ torch.tensor([23.5, 23.5, 2.0], dtype=F64) + stack.affine[:3, 3]
    torch.testing.assert_close(poses[2, :3, 3], centre)


def test_prepared_slices_are_cut_where_the_poses_say(untrained):
    """A stack cut from a smooth volume at known poses S_k (its world = the canonical frame).

    With an untrained model (crop pose predicted as the identity) the returned pose is
    T_k = C_k^-1 o S_k, so C_k = S_k o T_k^-1 must be where the prepared slice lies in the volume.
    """
    n, sp = 40, 2.0
    axis = (torch.arange(n, dtype=F64) - (n - 1) / 2) * sp
    x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1)
    blobs = [
        ((8, -5, 3), (9, 6, 5), 1.0),
        ((-10, 6, -4), (5, 8, 7), 0.7),
        ((0, 12, 8), (4, 4, 6), 0.5),
    ]
    data = sum(
        w * torch.exp(-(((x - torch.tensor(c)) / torch.tensor(r)) ** 2).sum(-1) / 2)
        for c, r, w in blobs
    )
    volume = Image(data.float(), torch.diag(torch.tensor([sp, sp, sp, 1.0], dtype=F64)))
    volume.affine[:3, 3] = axis[0]
    R = so3_exp(torch.tensor([0.4, -0.7, 0.2], dtype=F64))
    k, size, gap = 10, 40, 3.0  # 40 x 40 slices of 1 mm, 3 mm apart
    S = torch.eye(4, dtype=F64).repeat(k, 1, 1)
    S[:, :3, :3] = R
    S[:, :3, 3] = (
        torch.tensor([2.0, -1.0, 1.0]) + ((torch.arange(k) - (k - 1) / 2) * gap)[:, None] * R[:, 2]
    )
    affine = torch.eye(4, dtype=F64)
    affine[:3, :3] = R * torch.tensor([1.0, 1.0, gap], dtype=F64)
    affine[:3, 3] = S[0, :3, 3] - (size - 1) / 2 * (R[:, 0] + R[:, 1])
    cut = sample_slices(volume, S, SliceConfig(size=(size, size), spacing_mm=1.0))
    stack = Image(cut.permute(1, 2, 0).contiguous(), affine)
    model = load_pose_model(untrained)
    table = predict_plane_poses(model, stack).table("stack")
    slices = prepare_stack_slices(stack, None, model.config)[0][:, 0, 7:25, 7:25]  # in the stack
    crop = se3_compose(S, se3_inverse(vector_to_se3(table.poses)))
    for shift, close in ((0.0, True), (1.0, False)):
        moved = crop.clone()
        moved[:, :3, 3] += shift * crop[:, :3, 0]
        ref = sample_slices(volume, moved, SliceConfig(size=(32, 32), spacing_mm=2.0))
        ref = ref[:, 7:25, 7:25]
        scale = (slices * ref).sum() / (ref * ref).sum()  # the stack's own intensity scale
        assert (float((slices - scale * ref).abs().max()) < 0.03) == close


def test_intensities_are_divided_by_the_stack_in_mask_99th_percentile(rng):
    data = torch.from_numpy(rng.uniform(1.0, 1000.0, (30, 30, 2))).float()
    mask = torch.zeros(30, 30, 2)
    mask[5:15, 12:22, 0] = 1
    mask[10:20, 3:13, 1] = 1
    affine = torch.diag(torch.tensor([2.0, 2.0, 4.0, 1.0], dtype=F64))  # the model's spacing
    slices, indices = prepare_stack_slices(Image(data, affine), Image(mask, affine), CONFIG)
    scale = np.percentile(data[mask > 0].double().numpy(), 99)
    assert indices.tolist() == [0, 1]
    # A 10 x 10 mask (half-integer centroid) puts the 32 pixels on voxels: pixels 11..20.
    expected = torch.zeros(2, 32, 32)
    expected[0, 11:21, 11:21] = data[5:15, 12:22, 0] / scale
    expected[1, 11:21, 11:21] = data[10:20, 3:13, 1] / scale
    torch.testing.assert_close(slices[:, 0], expected, atol=1e-5, rtol=1e-5)  # masked outside


def test_without_a_mask_slices_are_centred_padded_and_all_kept(rng):
    data = torch.from_numpy(rng.uniform(0.0, 10.0, (20, 20, 3))).float()
    data[:4] = 0.0
    affine = torch.diag(torch.tensor([2.0, 2.0, 3.0, 1.0], dtype=F64))
    slices, indices = prepare_stack_slices(Image(data, affine), None, CONFIG)
    scale = np.percentile(data[data != 0].double().numpy(), 99)
    assert indices.tolist() == [0, 1, 2]
    expected = torch.zeros(3, 32, 32)
    expected[:, 6:26, 6:26] = data.permute(2, 0, 1) / scale  # slice centre 9.5 -> pixel 15.5
    torch.testing.assert_close(slices[:, 0], expected, atol=1e-5, rtol=1e-5)


def test_a_mask_on_another_grid_is_resampled_onto_the_stack():
    stack, mask = squares_stack()
    cropped = mask.affine.clone()
    cropped[:3, 3] = mask.affine[:3, :3] @ torch.tensor([2.0, 1.0, 0.0], dtype=F64) + cropped[:3, 3]
    sub = Image(mask.data[2:40, 1:47].clone(), cropped)
    a, ia = prepare_stack_slices(stack, mask, CONFIG)
    b, ib = prepare_stack_slices(stack, sub, CONFIG)
    assert torch.equal(ia, ib)
    torch.testing.assert_close(a, b)


def test_preparation_errors():
    stack, mask = squares_stack()
    with pytest.raises(ValueError, match="stack: the mask is empty"):
        prepare_stack_slices(stack, Image(torch.zeros(48, 48, 3), mask.affine), CONFIG)
    with pytest.raises(ValueError, match="stack: all voxels are zero"):
        prepare_stack_slices(Image(torch.zeros(8, 8, 2), stack.affine), None, CONFIG)
    with pytest.raises(ValueError, match=r"99th percentile of the intensities is 0\.0"):
        prepare_stack_slices(Image(torch.zeros(48, 48, 3), stack.affine), mask, CONFIG)


def test_untrained_model_poses_each_slice_about_its_crop_centre(untrained):
    model = load_pose_model(untrained)
    stack, mask = squares_stack()
    table = predict_plane_poses(model, stack, mask, name="ax.nii.gz").table("ax.nii.gz")
    assert table.files == ["ax.nii.gz"] * 2 and table.frame == "canonical"
    assert table.slice_indices.tolist() == [1, 2]
    # The crop (mask centroid) is at the canonical origin; the plane centre (23.5, 23.5) lies at
    # (plane centre - centroid) mm along (u, v) from it.
    expected = torch.tensor([[0, 0, 0, -4.0, 10.0, 0], [0, 0, 0, 15.0, -13.0, 0]], dtype=F64)
    torch.testing.assert_close(table.poses, expected, atol=1e-9, rtol=0)


def test_poses_move_with_the_content_and_ignore_the_batch_size(perturbed):
    model = load_pose_model(perturbed)
    stack, mask = squares_stack()
    table = predict_plane_poses(model, stack, mask, batch_size=1).table("stack")
    assert table.poses.shape == (2, 6) and bool(table.poses.isfinite().all())
    assert table.poses[:, :3].abs().max() > 1e-3  # not the identity
    torch.testing.assert_close(
        predict_plane_poses(model, stack, mask, batch_size=64).table("stack").poses, table.poses
    )
    # Content and mask moved by (3, -2) voxels (mm): the same prepared slices, so the plane
    # centre is (-3, 2) mm further from the brain in slice coordinates.
    shift = (3, -2)
    moved = predict_plane_poses(
        model,
        Image(stack.data.roll(shift, (0, 1)), stack.affine),
        Image(mask.data.roll(shift, (0, 1)), mask.affine),
    ).table("stack")
    offset = torch.eye(4, dtype=F64)
    offset[:2, 3] = torch.tensor([-3.0, 2.0], dtype=F64)
    expected = se3_compose(vector_to_se3(table.poses), offset)
    torch.testing.assert_close(vector_to_se3(moved.poses), expected, atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="batch_size must be >= 1"):
        predict_plane_poses(model, stack, mask, batch_size=0)


def write_slice_folder(folder: Path) -> None:
    """Slices 0, 1, 2 (one slice each, oblique), masks for 1 (empty) and 2."""
    folder.mkdir()
    affine = oblique_affine((1.5, 1.5, 3.0))
    for n in range(3):
        data = torch.zeros(24, 24, 1)
        data[4 + n : 16 + n, 2:14] = 10.0 * (n + 1)
        shifted = affine.clone()
        shifted[:3, 3] += 3.0 * n * affine[:3, 2]
        save_nifti(Image(data, shifted), folder / f"{n}.nii.gz")
        if n > 0:
            save_nifti(Image((data > 0).float() * (n - 1), shifted), folder / f"mask_{n}.nii.gz")


def test_slice_folder_prediction(untrained, tmp_path):
    folder = tmp_path / "slices"
    write_slice_folder(folder)
    items = load_slice_folder(folder)
    assert [s.index for s in items] == [0, 1, 2] and items[0].mask is None
    model = load_pose_model(untrained)
    table = predict_slice_folder(model, folder)
    assert table.files == [str(folder)] * 2 and table.slice_indices.tolist() == [0, 2]
    # Slice 0 (no mask) is cropped at its centre: identity. Slice 2 about its mask centroid
    # (11.5, 7.5): its centre (11.5, 11.5) is 4 voxels of 1.5 mm along v from the origin.
    expected = torch.tensor([[0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 6.0, 0]], dtype=F64)
    torch.testing.assert_close(table.poses, expected, atol=1e-5, rtol=0)  # float32 affines


def test_slice_folder_errors(tmp_path):
    with pytest.raises(ImageError, match="no such folder"):
        load_slice_folder(tmp_path / "none")
    with pytest.raises(ImageError, match="no slice files"):
        load_slice_folder(tmp_path)
    save_nifti(Image(torch.ones(4, 4, 2), torch.eye(4, dtype=F64)), tmp_path / "0.nii.gz")
    with pytest.raises(ImageError, match=r"0.nii.gz: expected one slice \(I, J, 1\)"):
        load_slice_folder(tmp_path)


# --- the command line ---


@pytest.fixture
def cli():
    return svr.cli.main


@pytest.fixture
def inputs(tmp_path) -> dict[str, Path]:
    stack, mask = squares_stack()
    sampled = torch.zeros(32, 32, 5)  # as ``svr sample`` writes them: (H, W, N) at 2 mm
    sampled[8:24, 10:22] = torch.arange(1.0, 6.0)
    paths = {
        "stack": save_nifti(stack, tmp_path / "ax.nii.gz"),
        "mask": save_nifti(mask, tmp_path / "ax_mask.nii.gz"),
        "slices": save_nifti(
            Image(sampled, torch.diag(torch.tensor([2.0, 2.0, 1.0, 1.0], dtype=F64))),
            tmp_path / "slices.nii.gz",
        ),
        "folder": tmp_path / "folder",
    }
    write_slice_folder(paths["folder"])
    return paths


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("svr predict: error: "), err
    return err.strip()


def test_cli_writes_the_pose_table(cli, untrained, inputs, tmp_path, capsys):
    out = tmp_path / "poses.csv"
    stacks = [str(inputs["stack"]), str(inputs["slices"])]
    args = ["predict", "--model", str(untrained), "--input-stacks", *stacks, "--quiet"]
    folder = ["--input-slices", str(inputs["folder"])]
    assert cli([*args, *folder, "--output-poses", str(out), "--device", "cpu"]) == 0
    assert "3 inputs" in capsys.readouterr().out
    table = read_pose_table(out)
    assert table.frame == "canonical"
    assert table.files == [stacks[0]] * 3 + [stacks[1]] * 5 + [str(inputs["folder"])] * 2
    assert table.slice_indices.tolist() == [0, 1, 2, 0, 1, 2, 3, 4, 0, 2]
    # Untrained model: every crop at the canonical origin; unmasked slices cropped at their centre.
    assert torch.equal(table.poses[3:8], torch.zeros(5, 6, dtype=F64))
    assert bool(table.poses.isfinite().all())
    out_json = tmp_path / "poses.json"
    masked = [*args[:5], "--stack-masks", str(inputs["mask"]), "--output-poses", str(out_json)]
    assert cli([*masked, "--quiet"]) == 0
    rows = json.loads(out_json.read_text())["slices"]
    assert [r["slice_index"] for r in rows] == [1, 2] and rows[0]["t_y"] == pytest.approx(10.0)


def test_cli_refuses_to_overwrite(cli, untrained, inputs, tmp_path, capsys):
    out = tmp_path / "poses.csv"
    out.write_text("keep me")
    args = ["predict", "--model", str(untrained), "--input-stacks", str(inputs["slices"]), "-q"]
    assert cli([*args, "--output-poses", str(out)]) == 1
    assert one_line_error(capsys).endswith(f"{out}: output exists; pass --overwrite to replace it")
    assert out.read_text() == "keep me"
    assert cli([*args, "--output-poses", str(out), "--overwrite"]) == 0
    assert len(read_pose_table(out).poses) == 5


def test_cli_errors_are_one_line(cli, untrained, inputs, tmp_path, capsys):
    out = str(tmp_path / "poses.csv")
    stack = str(inputs["stack"])
    base = ["predict", "--input-stacks", stack, "--output-poses", out, "-q"]
    mismatch = [*base, "--model", str(untrained), "--stack-masks", stack, stack]
    assert cli(mismatch) == 1
    assert "--stack-masks: got 2 masks for 1 stacks; give none or one per stack" in one_line_error(
        capsys
    )
    assert cli([*base, "--model", str(tmp_path / "nope")]) == 1
    assert f"{tmp_path / 'nope'}: checkpoint folder does not exist" in one_line_error(capsys)
    corrupted = tmp_path / "corrupted"
    save_model(corrupted, build_model(CONFIG))
    weights = corrupted / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-10])
    assert cli([*base, "--model", str(corrupted)]) == 1
    assert str(corrupted) in one_line_error(capsys)
    bad_suffix = ["predict", "--model", str(untrained), "--input-stacks", stack]
    assert cli([*bad_suffix, "--output-poses", str(tmp_path / "poses.txt")]) == 1
    assert "must end in .csv or .json" in one_line_error(capsys)
    assert cli(["predict", "--model", str(untrained), "--output-poses", out]) == 1
    assert "nothing to predict" in one_line_error(capsys)
    assert not Path(out).exists()


def test_cli_help_has_an_example(cli, capsys):
    with pytest.raises(SystemExit) as info:
        cli(["predict", "--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    for option in ("--model", "--input-stacks", "--stack-masks", "--output-poses", "(default: 64)"):
        assert option in text
    assert "svr predict --model runs/" in text


def test_plane_predictions_carry_the_scanner_poses_of_their_planes(untrained):
    from svr.image import stack_slice_poses

    model = load_pose_model(untrained)
    stack, mask = squares_stack()
    planes = predict_plane_poses(model, stack, mask)
    assert planes.indices.tolist() == [1, 2]
    assert planes.poses.shape == planes.plane_poses.shape == (2, 4, 4)
    assert planes.poses.dtype == planes.plane_poses.dtype == F64
    torch.testing.assert_close(planes.plane_poses, stack_slice_poses(stack)[planes.indices])
    table = planes.table("ax.nii.gz")
    torch.testing.assert_close(vector_to_se3(table.poses), planes.poses, atol=1e-12, rtol=0)
