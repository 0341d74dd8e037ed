"""A stack's slices registered one by one to an atlas from a start frame (fit_slices_to_atlas)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from synthetic import ellipsoid_brain
from test_recon_init import oblique_stack

from svr.errors import ConfigFieldError
from svr.geometry import rotation_angle, se3_compose, so3_exp
from svr.image import Image, stack_slice_poses
from svr.reconstruction.initialisation.atlas_slices import AtlasSliceConfig, fit_slices_to_atlas
from svr.sampling.blocks import stack_frame, stack_pose_from_slices
from svr.sampling.volume import canonicalize

F64 = torch.float64


def _deg(a: torch.Tensor, b: torch.Tensor) -> float:
    return math.degrees(rotation_angle(a, b))


def _turn(axis: tuple[float, float, float], deg: float) -> torch.Tensor:
    out = torch.eye(4, dtype=F64)
    v = torch.nn.functional.normalize(torch.tensor(axis, dtype=F64), dim=0)
    out[:3, :3] = so3_exp(v * math.radians(deg))
    return out


@pytest.fixture(scope="module")
def moving_stack():
    """A stack whose slices turned with the fetus (0-8 deg), its true plane poses and the atlas."""
    n, sp = 40, 2.5
    volume, mask = ellipsoid_brain(
        n, sp, (24.0, 30.0, 20.0), seed=3, texture=3.0, origin_mm=(-(n - 1) / 2 * sp,) * 3
    )
    atlas = canonicalize(volume, mask)
    planes = 14
    # The fetus turns steadily about an oblique axis while the stack is acquired.
    motion = torch.stack([_turn((1.0, 0.5, -0.3), 8.0 * k / (planes - 1)) for k in range(planes)])
    stack, canonical = oblique_stack(
        volume, mask, "a.nii.gz", (0.2, -0.1, 0.3), (40, 36), planes, 3.0, 0, motion
    )
    to_atlas = torch.eye(4, dtype=F64)
    to_atlas[:3, 3] = -atlas.centre_mm.to(F64)
    truth = se3_compose(to_atlas[None], canonical)  # (K, 4, 4) plane -> atlas canonical
    return stack, truth, atlas


def test_the_slices_follow_the_fetus_and_the_stack_pose_is_their_mean(moving_stack) -> None:
    stack, truth, atlas = moving_stack
    true_pose = stack_pose_from_slices(truth, stack.image)
    true_frame = se3_compose(true_pose, torch.linalg.inv(stack_frame(stack.image)))
    start = se3_compose(_turn((0.3, -1.0, 0.4), 6.0), true_frame)
    start[:3, 3] += torch.tensor([2.0, -1.5, 1.0], dtype=F64)
    fit = fit_slices_to_atlas(stack.image, stack.mask.data, start, atlas, thickness_mm=3.0)
    assert fit.kept and fit.ncc > 0.8
    start_pose = se3_compose(start, stack_frame(stack.image))
    assert _deg(start_pose, true_pose) > 5.5
    assert _deg(fit.pose, true_pose) < 1.5
    assert float((fit.pose[:3, 3] - true_pose[:3, 3]).norm()) < 1.5
    # Each slice on its own follows the fetus's 8 deg of turning within the stack: most slices
    # end nearer their own truth than the stack's pose puts them (a few small or featureless
    # slices of this ellipsoid go astray; the robust mean ignores them).
    assert _deg(truth[0], truth[-1]) > 7.5
    errors = torch.tensor([_deg(p, t) for p, t in zip(fit.plane_poses, truth, strict=True)])
    rigid = se3_compose(fit.to_canonical[None], stack_slice_poses(stack.image))
    rigid_errors = torch.tensor([_deg(p, t) for p, t in zip(rigid, truth, strict=True)])
    assert float(errors.median()) < 1.0 < float(rigid_errors.median()), (errors, rigid_errors)
    assert int((errors < 3.0).sum()) >= 10, errors
    # The frame and the pose are one transform.
    assert torch.allclose(
        se3_compose(fit.to_canonical, stack_frame(stack.image)), fit.pose, atol=1e-9
    )


def test_an_atlas_unlike_the_brain_keeps_the_start(moving_stack) -> None:
    stack, _truth, atlas = moving_stack
    n, sp = 40, 2.5
    other, other_mask = ellipsoid_brain(
        n, sp, (24.0, 30.0, 20.0), seed=11, texture=3.0, origin_mm=(-(n - 1) / 2 * sp,) * 3
    )
    unlike = canonicalize(other, other_mask)  # same shape, another texture
    start = torch.eye(4, dtype=F64)
    start[:3, :3] = so3_exp(torch.tensor([0.1, 0.2, -0.1], dtype=F64))
    fit = fit_slices_to_atlas(stack.image, stack.mask.data, start, unlike)
    assert not fit.kept and fit.ncc < 0.6
    assert torch.equal(fit.to_canonical, start)
    assert torch.allclose(fit.plane_poses, se3_compose(start[None], stack_slice_poses(stack.image)))
    # The same atlas with the gate opened: the fit is taken whatever it matched.
    forced = fit_slices_to_atlas(
        stack.image, stack.mask.data, start, unlike, config=AtlasSliceConfig(min_ncc=-1.0)
    )
    assert forced.kept and not torch.equal(forced.to_canonical, start)
    # The matching atlas from the same start passes the gate.
    assert fit_slices_to_atlas(stack.image, stack.mask.data, start, atlas).ncc > fit.ncc


def test_bad_arguments_are_named(moving_stack) -> None:
    stack, _truth, atlas = moving_stack
    mask = stack.mask.data
    eye = torch.eye(4, dtype=F64)
    with pytest.raises(ValueError, match="'mask' must have the stack's shape"):
        fit_slices_to_atlas(stack.image, mask[:, :, :-1], eye, atlas)
    with pytest.raises(ValueError, match="'mask' has no brain voxel"):
        fit_slices_to_atlas(stack.image, torch.zeros_like(mask), eye, atlas)
    with pytest.raises(ValueError, match="'to_canonical' must be"):
        fit_slices_to_atlas(stack.image, mask, eye[:3], atlas)
    blank = Image(torch.zeros(stack.image.shape), stack.image.affine)
    with pytest.raises(ValueError, match=r"'stack': the 99th percentile .* expected a positive"):
        fit_slices_to_atlas(blank, mask, eye, atlas)
    with pytest.raises(ConfigFieldError, match="min_ncc"):
        AtlasSliceConfig(min_ncc=1.5)
    with pytest.raises(ConfigFieldError, match="levels"):
        AtlasSliceConfig(levels=0)


@pytest.mark.parametrize("given", ["volume", "folder"])
def test_svr_predict_writes_the_fitted_slices_and_stack_pose(moving_stack, tmp_path, given) -> None:
    """``svr predict --model stack-pose --atlas-volume`` (or ``--atlas-dir`` and an age): the
    pose table holds each slice's own fitted pose, the JSON the stack pose, their robust mean."""
    import svr.cli
    from svr.geometry import vector_to_se3
    from svr.image import save_nifti
    from svr.pose_io import read_pose_table

    stack, _truth, atlas = moving_stack
    paths = {name: tmp_path / f"{name}.nii.gz" for name in ("stack", "mask", "atlas", "brain")}
    save_nifti(stack.image, paths["stack"])
    save_nifti(Image(stack.mask.data.float(), stack.mask.affine), paths["mask"])
    save_nifti(atlas.image, paths["atlas"])
    save_nifti(Image(atlas.mask.float(), atlas.image.affine), paths["brain"])
    out, stack_out = tmp_path / "poses.csv", tmp_path / "stacks.json"
    args = ["predict", "--model", "stack-pose", "--input-stacks", str(paths["stack"])]
    args += ["--stack-masks", str(paths["mask"]), "--output-poses", str(out), "--quiet"]
    args += ["--output-stack-poses", str(stack_out)]
    atlas_args = ["--atlas-volume", str(paths["atlas"]), "--atlas-mask", str(paths["brain"])]
    if given == "folder":  # the nearest age's atlas: GA28, not GA30's (not a brain: unreadable)
        for name, source in (("GA28_x", paths), ("GA30_y", None)):
            (tmp_path / "atlas" / name).mkdir(parents=True)
            for file, key in (("srr.nii.gz", "atlas"), ("mask.nii.gz", "brain")):
                target = tmp_path / "atlas" / name / file
                if source is None:
                    target.write_text("not a NIfTI")
                else:
                    target.write_bytes(source[key].read_bytes())
        atlas_args = ["--atlas-dir", str(tmp_path / "atlas"), "--gestational-age", "28.6"]
    assert svr.cli.main([*args, *atlas_args]) == 0
    (record,) = json.loads(stack_out.read_text())["stacks"]
    # This atlas is the brain itself, so the fit is kept.
    assert record["method"].startswith("learned+atlas slices (NCC"), record
    table = read_pose_table(out)
    planes = vector_to_se3(table.poses)
    pose = torch.tensor(record["matrix"], dtype=F64)
    present = torch.zeros(stack.image.shape[2], dtype=torch.bool)
    present[table.slice_indices] = True
    # Every k-plane where the stack's pose alone would put it, then the table's fitted slices.
    frame = se3_compose(pose, torch.linalg.inv(stack_frame(stack.image)))
    rigid = se3_compose(frame[None], stack_slice_poses(stack.image))
    full = rigid.clone()
    full[table.slice_indices] = planes
    assert torch.allclose(stack_pose_from_slices(full, stack.image, present), pose, atol=1e-6)
    # The slices were registered one by one: they do not all take the stack's pose.
    assert not torch.allclose(planes, rigid[table.slice_indices], atol=1e-3)
