"""Slices of prepared stacks: dropping empty planes, padding, bookkeeping, SliceSet checks."""

from __future__ import annotations

import pytest
import torch
from scipy.spatial.transform import Rotation

from svr.image import Image, stack_slice_poses
from svr.reconstruction.slices import (
    SliceSet,
    Stack,
    array_poses,
    extract_slices,
    mask_centre,
    moved_from_stack,
    plane_poses,
)

F64 = torch.float64


def make_stack(
    name: str,
    shape: tuple[int, int, int],
    planes_with_brain: list[int],
    crop_origin: tuple[int, int],
    k0: int,
    full_shape: tuple[int, int],
    file_affine: torch.Tensor,
) -> Stack:
    """A crop of a file with ``file_affine``: crop voxel (0, 0, k') is its (i0, j0, k0 + k')."""
    mask = torch.zeros(shape, dtype=torch.bool)
    mask[1:-1, 1:-1, planes_with_brain] = True
    image = torch.arange(mask.numel(), dtype=torch.float32).reshape(shape) * mask
    shift = torch.eye(4, dtype=F64)
    shift[:3, 3] = torch.tensor([*crop_origin, k0], dtype=F64)
    affine = file_affine @ shift
    return Stack(
        name=name,
        image=Image(image, affine),
        mask=Image(mask, affine.clone()),
        thickness_mm=2.5,
        k_indices=torch.arange(k0, k0 + shape[2]),
        full_shape=full_shape,
        crop_origin=crop_origin,
    )


AFFINE_A = torch.tensor(
    [[0.0, 0.0, 3.0, -10.0], [-1.0, 0.0, 0.0, 20.0], [0.0, 1.5, 0.0, 5.0], [0, 0, 0, 1]], dtype=F64
)
AFFINE_C = torch.diag(torch.tensor([1.0, 2.0, 3.0, 1.0], dtype=F64))


@pytest.fixture
def stacks() -> list[Stack]:
    return [
        make_stack("a.nii.gz", (4, 7, 3), [0, 2], (2, 1), 5, (10, 12), AFFINE_A),
        make_stack("empty.nii.gz", (6, 6, 2), [], (0, 0), 0, (6, 6), AFFINE_C),
        make_stack("c.nii.gz", (7, 4, 2), [0, 1], (0, 3), 1, (9, 9), AFFINE_C),
    ]


def test_empty_planes_and_stacks_are_dropped_and_slices_padded(stacks):
    slices = extract_slices(stacks)
    assert slices.stack_names == ("a.nii.gz", "empty.nii.gz", "c.nii.gz")
    assert slices.size == (7, 7) and len(slices) == 4 and slices.frame == "scanner"
    assert slices.stack_ids.tolist() == [0, 0, 2, 2]
    assert slices.slice_indices.tolist() == [5, 7, 1, 2]
    torch.testing.assert_close(slices.thickness_mm, torch.full((4,), 2.5, dtype=F64))
    torch.testing.assert_close(slices.spacing_mm[0], torch.tensor([1.0, 1.5], dtype=F64))
    torch.testing.assert_close(slices.poses, slices.scanner_poses)
    for n, (sid, k) in enumerate([(0, 0), (0, 2), (2, 0), (2, 1)]):
        stack = stacks[sid]
        # The stack's plane sits somewhere in the padded array; the rest is zero and unmasked.
        image, mask = slices.images[n], slices.masks[n]
        assert image.sum() == stack.image.data[:, :, k].sum()
        assert mask.sum() == stack.mask.data[:, :, k].sum()
        assert not (image[~mask] != 0).any()


def test_plane_poses_are_the_files_k_plane_poses(stacks):
    slices = extract_slices(stacks)
    for sid, affine, shape in ((0, AFFINE_A, (10, 12, 9)), (2, AFFINE_C, (9, 9, 4))):
        rows = slices.stack_slices(sid)
        file_grid = Image(torch.zeros(shape), affine)
        expected = stack_slice_poses(file_grid)[slices.slice_indices[rows]]
        torch.testing.assert_close(plane_poses(slices)[rows], expected)
    torch.testing.assert_close(
        plane_poses(slices, torch.eye(4, dtype=F64).repeat(4, 1, 1))[:, :2, 3],
        -slices.plane_offsets_mm,
    )
    # array_poses inverts plane_poses (a pose table read back gives the slices' own poses).
    torch.testing.assert_close(array_poses(slices, plane_poses(slices)), slices.poses)


def test_extract_slices_errors(stacks):
    with pytest.raises(ValueError, match="'stacks' is empty"):
        extract_slices([])
    with pytest.raises(ValueError, match="every slice of every stack has an empty mask"):
        extract_slices([stacks[1]])


def test_slice_set_checks_and_copies(stacks):
    slices = extract_slices(stacks)
    part = slices.subset(slices.stack_ids == 2)
    assert part.slice_indices.tolist() == [1, 2] and part.stack_names == slices.stack_names
    moved = slices.with_poses(torch.eye(4).repeat(4, 1, 1), "canonical")
    assert moved.frame == "canonical" and moved.poses.dtype == F64
    torch.testing.assert_close(moved.scanner_poses, slices.scanner_poses)
    assert slices.to("cpu").device.type == "cpu"
    with pytest.raises(ValueError, match="'frame' must be one of"):
        slices.with_poses(slices.poses, "world")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"'poses' must have shape \(4, 4, 4\)"):
        slices.with_poses(slices.poses[:, :3])
    with pytest.raises(ValueError, match=r"'images' must be \(N, H, W\)"):
        SliceSet(**{**slices.__dict__, "images": torch.tensor(0.0)})


def _voxel_centroid(stack: Stack, planes: list[int]) -> tuple[torch.Tensor, int]:
    """World centroid of a stack's mask voxels on the given planes (the affine's, no slices)."""
    idx = torch.nonzero(stack.mask.data[:, :, planes]).to(F64)
    idx[:, 2] = torch.tensor(planes, dtype=F64)[idx[:, 2].long()]
    world = idx @ stack.image.affine[:3, :3].T + stack.image.affine[:3, 3]
    return world.mean(dim=0), len(idx)


def test_mask_centre_is_the_mask_voxels_centroid_weighted_by_voxel_volume(stacks):
    slices = extract_slices(stacks)
    (a, na), (c, nc) = _voxel_centroid(stacks[0], [0, 2]), _voxel_centroid(stacks[2], [0, 1])
    # Voxel volumes: stack a 1 x 1.5 mm pixels, stack c 1 x 2 mm, both 2.5 mm thick.
    wa, wc = na * 1.5 * 2.5, nc * 2.0 * 2.5
    torch.testing.assert_close(mask_centre(slices), (wa * a + wc * c) / (wa + wc))
    torch.testing.assert_close(mask_centre(slices, slices.stack_ids == 2), c)
    # The centre moves with the poses: every slice turned and shifted moves it alike.
    turn = torch.eye(4, dtype=F64)
    turn[:3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    turn[:3, 3] = torch.tensor([4.0, -3.0, 2.0], dtype=F64)
    moved = slices.with_poses(turn @ slices.poses)
    torch.testing.assert_close(mask_centre(moved), turn[:3, :3] @ mask_centre(slices) + turn[:3, 3])
    with pytest.raises(ValueError, match="no mask pixel"):
        mask_centre(slices, torch.zeros(len(slices), dtype=torch.bool))
    with pytest.raises(ValueError, match=r"'keep' must have shape \(4,\)"):
        mask_centre(slices, torch.ones(3, dtype=torch.bool))


def test_moved_from_stack_is_zero_for_a_rigid_stack_and_the_turn_of_a_slice_that_moved_alone():
    stack = make_stack("a.nii.gz", (6, 6, 7), list(range(7)), (0, 0), 0, (6, 6), AFFINE_A)
    slices = extract_slices([stack])
    rigid = torch.eye(4, dtype=F64)
    rigid[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.4, -0.3, 1.1]).as_matrix())
    rigid[:3, 3] = torch.tensor([3.0, -2.0, 7.0], dtype=F64)
    poses = rigid @ slices.poses.double()
    assert moved_from_stack(slices.with_poses(poses, "canonical")).abs().max() < 1e-6
    # One slice turns 12 degrees more (about its own centre): only it moved, by 12 degrees.
    turn = torch.eye(4, dtype=F64)
    turn[:3, :3] = torch.from_numpy(Rotation.from_euler("y", 12, degrees=True).as_matrix())
    poses[3] = poses[3] @ turn
    moved = moved_from_stack(slices.with_poses(poses, "canonical"))
    assert moved[3].item() == pytest.approx(12.0, abs=1e-6)
    assert torch.cat([moved[:3], moved[4:]]).abs().max() < 1e-6
