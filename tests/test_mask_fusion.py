"""Brain masks of several stacks of one fetus made to agree (svr.masking.fuse)."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from scipy import ndimage
from scipy.spatial.transform import Rotation

from svr.image import Image, stack_slice_poses
from svr.masking.fuse import (
    MaskFusionConfig,
    all_plane_poses,
    fuse_masks,
    fuse_stack_masks,
    leave_one_out_votes,
)
from svr.reconstruction.slices import extract_slices
from svr.reconstruction.stacks import prepare_stacks

SEMI_AXES = np.array([30.0, 24.0, 20.0])  # mm, the "brain" ellipsoid centred at the origin
SLICE_MM, PIXEL_MM, SIZE, PLANES = 4.0, 2.0, 48, 16


def _rigid(rotvec_deg, shift_mm) -> torch.Tensor:
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = torch.from_numpy(Rotation.from_rotvec(rotvec_deg, degrees=True).as_matrix())
    out[:3, 3] = torch.tensor(shift_mm, dtype=torch.float64)
    return out


def _stack(
    rotation: np.ndarray, offset_mm: float = 0.0, size: tuple[int, int] = (SIZE, SIZE)
) -> tuple[Image, torch.Tensor]:
    """A stack through the ellipsoid (axes: the columns of ``rotation``) and its true mask.

    The true mask holds the voxels whose centre lies inside the ellipsoid; the image is bright
    there, with a faint background.
    """
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] = torch.from_numpy(rotation * np.array([PIXEL_MM, PIXEL_MM, SLICE_MM]))
    centre = np.array([(size[0] - 1) / 2, (size[1] - 1) / 2, (PLANES - 1) / 2])
    affine[:3, 3] = torch.from_numpy(-rotation @ (centre * [PIXEL_MM, PIXEL_MM, SLICE_MM]))
    affine[:3, 3] += torch.tensor([0.0, 0.0, offset_mm], dtype=torch.float64)
    index = np.stack(np.indices((*size, PLANES)), axis=-1).reshape(-1, 3)
    world = index @ affine[:3, :3].numpy().T + affine[:3, 3].numpy()
    inside = (((world / SEMI_AXES) ** 2).sum(axis=1) <= 1).reshape(*size, PLANES)
    data = np.where(inside, 1.0, 0.1).astype(np.float32)
    return Image(torch.from_numpy(data), affine), torch.from_numpy(inside)


# axial, coronal, sagittal, and (in the fixture) a smaller second axial stack shifted by half a
# slice
ORIENTATIONS = [
    np.eye(3),
    np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]),
]


@pytest.fixture(scope="module")
def stacks():
    made = [_stack(r) for r in ORIENTATIONS] + [_stack(np.eye(3), SLICE_MM / 2, (40, 44))]
    return [image for image, _ in made], [mask for _, mask in made]


def _scanner_slices(images, masks):
    """The stacks' slices at their scanner poses (registration would leave them there)."""
    prepared = prepare_stacks(
        images, [Image(m.float(), i.affine) for m, i in zip(masks, images, strict=True)], SLICE_MM
    )
    return extract_slices(prepared)


def dice(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(2 * (a & b).sum() / (a.sum() + b.sum()))


def test_planes_take_their_registered_pose_or_their_nearest_neighbours_motion():
    image, mask = _stack(ORIENTATIONS[1])
    own = torch.zeros_like(mask)
    own[:, :, 4] = mask[:, :, 4]
    own[:, :, 8] = mask[:, :, 8]  # registered planes 4 and 8 only
    slices = _scanner_slices([image], [own])
    assert slices.slice_indices.tolist() == [4, 8]
    motion = {4: _rigid([3.0, -2.0, 5.0], [1.0, 2.0, -3.0]), 8: _rigid([-4.0, 1.0, 0.0], [0, 1, 2])}
    moved = torch.stack([motion[4] @ slices.poses[0], motion[8] @ slices.poses[1]])
    (poses,) = all_plane_poses(slices.with_poses(moved), [image])
    scanner = stack_slice_poses(image)
    assert poses.shape == (PLANES, 4, 4)
    for k in range(PLANES):
        nearest = 4 if k <= 6 else 8  # plane 6 is as near to 4 as to 8: the lower one wins
        torch.testing.assert_close(poses[k], motion[nearest] @ scanner[k])


def test_all_plane_poses_name_a_mismatch(stacks):
    images, masks = stacks
    slices = _scanner_slices(images[:2], masks[:2])
    with pytest.raises(ValueError, match="'slices' holds 2 stacks, 'stacks' 3"):
        all_plane_poses(slices, images[:3])


def test_fusion_mends_the_end_slices_and_a_leak_of_one_stack(stacks):
    images, truth = stacks
    own = [m.clone() for m in truth]
    ends = torch.nonzero(truth[0].any(dim=0).any(dim=0)).flatten()
    own[0][:, :, ends[0]] = False  # lost both end slices of the head
    own[0][:, :, ends[-1]] = False
    own[0][40:47, 16:32, 5:11] = True  # and took in a pocket next to it
    result = fuse_masks(images, own, _scanner_slices(images, own), [SLICE_MM] * 4)
    assert not any(result.kept_own)
    assert dice(own[0], truth[0]) < 0.9
    assert dice(result.masks[0], truth[0]) > 0.95
    for fused, mask in zip(result.masks, truth, strict=True):
        assert fused.shape == mask.shape and fused.dtype == torch.bool
        assert dice(fused, mask) > 0.95
    assert result.agreement[0] == pytest.approx(dice(result.masks[0], own[0]))


@pytest.mark.parametrize("margin", [0.0, 0.15, 0.3])
def test_the_own_mask_decides_where_the_vote_is_near_the_threshold(stacks, margin):
    from svr.masking import clean_up_mask

    images, truth = stacks
    own = [m.clone() for m in truth]
    own[1][20:28, 30:40, 4:12] = True  # a pocket that one stack of four takes in
    config = MaskFusionConfig(own_margin=margin)
    result = fuse_masks(images, own, _scanner_slices(images, own), [SLICE_MM] * 4, config)
    for mask, vote, mine, image, true in zip(
        result.masks, result.votes, own, images, truth, strict=True
    ):
        spacing = image.spacing.double().numpy()
        assert vote.shape == mine.shape and float(vote.min()) >= 0 and float(vote.max()) <= 1.01
        deep = torch.from_numpy(ndimage.distance_transform_edt(true.numpy(), sampling=spacing) > 8)
        assert float(vote[deep].min()) > 0.99  # all four agree well inside the brain
        brain = (vote > 0.5 + margin) | (mine & (vote > 0.5 - margin))
        expected = clean_up_mask(brain.numpy(), spacing)
        assert torch.equal(mask, torch.from_numpy(expected))
    pocket = torch.zeros_like(own[1])
    pocket[20:28, 30:40, 4:12] = True
    outside = ndimage.distance_transform_edt(
        ~truth[1].numpy(), sampling=[PIXEL_MM] * 2 + [SLICE_MM]
    )
    pocket &= torch.from_numpy(outside > 4)  # (nearer the brain the PSF blurs the vote)
    assert pocket.sum() > 50
    assert float(result.votes[1][pocket].max()) < 0.5  # out-voted by the other three
    outvoted = pocket & (result.votes[1] < 0.5 - margin)
    assert outvoted.sum() > 0 and not bool((result.masks[1] & outvoted).any())


def test_leave_one_out_votes_see_each_stack_through_the_others_only(stacks):
    images, truth = stacks
    own = [m.clone() for m in truth]
    own[0][40:47, 16:32, 5:11] = True  # a pocket only stack 0 takes in
    slices = _scanner_slices(images, own)
    votes = leave_one_out_votes(images, own, slices, [SLICE_MM] * 4)
    pocket = torch.zeros_like(own[0])
    pocket[40:47, 16:32, 5:11] = True
    pocket &= ~truth[0]
    assert float(votes[0][pocket].max()) < 0.5  # its own pocket has no say on its planes
    for vote, mask in zip(votes, truth, strict=True):
        assert dice(vote > 0.5, mask) > 0.95
    fused = fuse_masks(images, own, slices, [SLICE_MM] * 4, MaskFusionConfig(own_margin=0.0))
    assert float(fused.votes[0][pocket].max()) > float(votes[0][pocket].max())


def test_a_stack_that_disagrees_keeps_its_own_mask_and_has_no_vote(stacks, caplog):
    images, truth = stacks
    own = [m.clone() for m in truth]
    own[3] = torch.roll(truth[3], shifts=22, dims=0)  # a mask on the wrong object
    slices = _scanner_slices(images, own)
    with caplog.at_level(logging.WARNING):
        result = fuse_masks(images, own, slices, [SLICE_MM] * 4, names=list("abcd"))
    assert result.kept_own == [False, False, False, True]
    assert torch.equal(result.masks[3], own[3])
    assert "d: its mask disagrees with the other stacks'" in caplog.text
    three = fuse_masks(images[:3], own[:3], _scanner_slices(images[:3], own[:3]), [SLICE_MM] * 3)
    for a, b in zip(result.masks[:3], three.masks, strict=True):
        assert torch.equal(a, b)


def test_with_too_few_stacks_in_agreement_every_stack_keeps_its_own(stacks):
    images, truth = stacks
    own = [m.clone() for m in truth[:3]]
    own[2] = torch.roll(truth[2], shifts=22, dims=1)
    result = fuse_masks(images[:3], own, _scanner_slices(images[:3], own), [SLICE_MM] * 3)
    assert result.kept_own == [True] * 3
    assert all(torch.equal(a, b) for a, b in zip(result.masks, own, strict=True))


def test_registered_fusion_finds_a_moved_stack(stacks):
    """One stack's header is off by a rigid motion: registration undoes it before the vote."""
    images, truth = stacks
    motion = _rigid([0.0, 0.0, 6.0], [4.0, -3.0, 0.0])
    moved = Image(images[1].data, motion @ images[1].affine)
    own = [m.clone() for m in truth]
    ends = torch.nonzero(truth[0].any(dim=0).any(dim=0)).flatten()
    own[0][:, :, ends[-1]] = False
    inputs = [images[0], moved, images[2], images[3]]
    unregistered = fuse_masks(inputs, own, _scanner_slices(inputs, own), [SLICE_MM] * 4)
    result = fuse_stack_masks(inputs, own, SLICE_MM)
    # The moved stack's mask is voted in its own place (unregistered, its votes land 6 mm off:
    # Dice 0.94) and the others' stay good. The first stack's mask with and without registration
    # differ by float noise (Dice 0.9849 against 0.9850 on one CPU, the other way round on
    # another), so they are not compared.
    assert dice(result.masks[1], truth[1]) > dice(unregistered.masks[1], truth[1]) + 0.03
    assert dice(result.masks[1], truth[1]) > 0.95
    assert all(dice(m, t) > 0.95 for m, t in zip(result.masks, truth, strict=True))


def _world(image: Image) -> np.ndarray:
    """(I, J, K, 3) world coordinates of the voxel centres, mm."""
    index = np.stack(np.indices(tuple(image.shape)), axis=-1).astype(np.float64)
    affine = image.affine.numpy()
    return index @ affine[:3, :3].T + affine[:3, 3]


def test_soft_votes_are_the_probabilities_through_the_same_acquisition_model(stacks):
    images, truth = stacks
    slices = _scanner_slices(images, truth)
    hard = fuse_masks(images, truth, slices, [SLICE_MM] * 4)
    same = fuse_masks(images, truth, slices, [SLICE_MM] * 4, probabilities=[m * 1.0 for m in truth])
    for a, b, u, v in zip(hard.masks, same.masks, hard.votes, same.votes, strict=True):
        assert torch.equal(a, b)
        torch.testing.assert_close(u, v)
    # the vote is linear in what the stacks say: probabilities 0.8 inside the masks give 0.8x
    scaled = fuse_masks(
        images, truth, slices, [SLICE_MM] * 4, probabilities=[0.8 * m for m in truth]
    )
    for u, v in zip(hard.votes, scaled.votes, strict=True):
        torch.testing.assert_close(v, 0.8 * u, atol=1e-5, rtol=1e-4)


def test_soft_votes_take_in_what_the_network_was_unsure_of_in_two_stacks_of_four(stacks):
    """Two stacks' masks lose the top of the head, where their network said 0.45.

    Voting with the masks, the vote there is 0.5 and each stack's own mask decides, so those two
    keep missing it; voting with the probabilities, it is (1 + 1 + 0.45 + 0.45) / 4 = 0.725
    away from the head's surface and the cut (which the PSF blurs) and within the coronal
    stack's footprint (10 mm beyond its mask's outline: z < 14 mm).
    """
    images, truth = stacks
    heights = [_world(image)[..., 2] for image in images]
    top = [torch.from_numpy(z > 4.0) & m for z, m in zip(heights, truth, strict=True)]
    own = [m & ~t if n < 2 else m.clone() for n, (m, t) in enumerate(zip(truth, top, strict=True))]
    probabilities = [m.float() + 0.45 * (t & ~m).float() for m, t in zip(own, top, strict=True)]
    slices = _scanner_slices(images, own)
    hard = fuse_masks(images, own, slices, [SLICE_MM] * 4)
    soft = fuse_masks(images, own, slices, [SLICE_MM] * 4, probabilities=probabilities)
    for n in range(2):
        spacing = images[n].spacing.double().numpy()
        depth = ndimage.distance_transform_edt(truth[n].numpy(), sampling=spacing)
        inner = (depth > 5) & (heights[n] > 6.0) & (heights[n] < 14.0)
        deep = top[n] & torch.from_numpy(inner)
        assert deep.sum() > 100
        torch.testing.assert_close(
            soft.votes[n][deep], torch.full((int(deep.sum()),), 0.725), atol=0.01, rtol=0
        )
        assert not bool(hard.masks[n][top[n]].any())
        assert bool(soft.masks[n][deep].all())
        assert dice(soft.masks[n], truth[n]) > 0.9 > 0.8 > dice(hard.masks[n], truth[n])


def test_fusion_refuses_probabilities_that_do_not_fit(stacks):
    images, truth = stacks
    slices = _scanner_slices(images[:3], truth[:3])
    good = [m.float() for m in truth[:3]]
    with pytest.raises(ValueError, match="got 2 probabilities for 3 stacks"):
        fuse_masks(images[:3], truth[:3], slices, [SLICE_MM] * 3, probabilities=good[:2])
    with pytest.raises(ValueError, match=r"the probabilities of b have shape \(48, 48, 15\)"):
        bad = [good[0], good[1][:, :, :-1], good[2]]
        fuse_masks(
            images[:3], truth[:3], slices, [SLICE_MM] * 3, names=list("abc"), probabilities=bad
        )
    for value in (1.5, math.nan):
        bad = [good[0], good[1], good[2] * value]
        with pytest.raises(ValueError, match="the probabilities of c must be finite and in"):
            fuse_masks(
                images[:3], truth[:3], slices, [SLICE_MM] * 3, names=list("abc"), probabilities=bad
            )
    with pytest.raises(ValueError, match=r"fuse_stack_masks\(\): got 1 probabilities for 3"):
        fuse_stack_masks(images[:3], truth[:3], SLICE_MM, probabilities=good[:1])


def test_fusion_refuses_too_few_stacks_and_masks_off_their_grid(stacks):
    images, truth = stacks
    slices = _scanner_slices(images[:2], truth[:2])
    with pytest.raises(ValueError, match="at least 3 stacks of one fetus, got 2"):
        fuse_masks(images[:2], truth[:2], slices, [SLICE_MM] * 2)
    with pytest.raises(ValueError, match="at least 3 stacks of one fetus, got 2"):
        fuse_stack_masks(images[:2], truth[:2], SLICE_MM)
    slices = _scanner_slices(images[:3], truth[:3])
    with pytest.raises(ValueError, match=r"the mask of c has shape \(48, 48, 15\)"):
        bad = [truth[0], truth[1], truth[2][:, :, :-1]]
        fuse_masks(images[:3], bad, slices, [SLICE_MM] * 3, names=list("abc"))
    with pytest.raises(ValueError, match="got 2 thicknesses for 3 stacks"):
        fuse_masks(images[:3], truth[:3], slices, [SLICE_MM] * 2)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("resolution_mm", 0.0, "'resolution_mm' must be a finite number > 0"),
        ("registration_mm", math.inf, "'registration_mm' must be a finite number > 0"),
        ("footprint_mm", -1.0, "'footprint_mm' must be a finite number >= 0"),
        ("threshold", 1.0, r"'threshold' must be in \(0, 1\)"),
        ("min_agreement", 1.5, r"'min_agreement' must be in \[0, 1\]"),
        ("own_margin", 0.5, r"'own_margin' must be in \[0, min\(threshold, 1 - threshold\)\)"),
        ("psf_samples", 4, "'psf_samples' must be an odd integer >= 1"),
        ("threshold", "0.5", r"'threshold' must be in \(0, 1\), got '0.5'"),
        ("psf_samples", 3.0, "'psf_samples' must be an odd integer >= 1"),
    ],
)
def test_config_names_the_bad_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        MaskFusionConfig(**{field: value})
