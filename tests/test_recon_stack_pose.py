"""Per-stack canonical placement in reconstruction, its safe fallback, and the atlas frame."""

from __future__ import annotations

import math

import pytest
import torch
from recon_settings import recon_config
from synthetic import ellipsoid_brain
from test_recon_init import oblique_stack

from svr.geometry import se3_compose, so3_exp
from svr.image import Image
from svr.models.stack_pose import StackPoseConfig, StackPoseNet
from svr.reconstruction.atlas_fit import KEEP_MARGIN, preferred_atlas
from svr.reconstruction.atlas_frame import align_to_atlas, atlas_transform, best_atlas_transform
from svr.reconstruction.initialisation.atlas import atlas_start
from svr.reconstruction.initialisation.choice import agreeing_stacks
from svr.reconstruction.initialisation.learned import learned_start
from svr.reconstruction.initialisation.stack_pose import estimate_stack_pose
from svr.reconstruction.result import ReconstructionResult
from svr.reconstruction.slices import extract_slices, mask_centre
from svr.sampling.blocks import stack_pose_from_slices
from svr.sampling.volume import as_atlases, canonicalize

F64 = torch.float64


def _brain():
    # Front-back (y) longest, then left-right (x), then top-bottom (z), as fetal brains are.
    n, sp = 40, 2.5
    volume, mask = ellipsoid_brain(
        n, sp, (24.0, 30.0, 20.0), seed=3, texture=3.0, origin_mm=(-(n - 1) / 2 * sp,) * 3
    )
    return volume, mask, canonicalize(volume, mask)


@pytest.fixture(scope="module")
def turned_scene():
    """Three stacks at very different oblique orientations of one brain, each placed alone."""
    volume, mask, atlas = _brain()
    specs = [
        ("a.nii.gz", (0.2, -0.1, 0.3), (40, 36), 14, 4.0),
        ("b.nii.gz", (1.4, 0.2, -0.2), (33, 38), 13, 4.0),
        ("c.nii.gz", (0.3, 1.5, 0.4), (36, 31), 13, 4.0),
    ]
    stacks, truths = [], []
    for name, rotvec, size, planes, thickness in specs:
        stack, canonical = oblique_stack(volume, mask, name, rotvec, size, planes, thickness, 0)
        stacks.append(stack)
        truths.append(stack_pose_from_slices(canonical, stack.image))
    return atlas, stacks, truths


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    r = a[:3, :3].T @ b[:3, :3]
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(r.trace()) - 1) / 2))))


def test_the_atlas_chain_places_each_stack_from_its_own_data(turned_scene) -> None:
    atlas, stacks, truths = turned_scene
    for stack, truth in zip(stacks, truths, strict=True):
        estimate = estimate_stack_pose(None, stack.image, stack.mask.data > 0.5, atlas=atlas)
        assert estimate.method == "axes+atlas"
        assert _angle_deg(estimate.pose, truth) < 4.0
        assert float((estimate.pose[:3, 3] - truth[:3, 3]).norm()) < 3.0


def test_stack_pose_initialisation_keeps_good_per_stack_poses(turned_scene) -> None:
    atlas, stacks, _truths = turned_scene
    slices = extract_slices(stacks)
    config = recon_config(resolution_mm=2.5)
    start, kept, notes, *_ = atlas_start(slices, stacks, [atlas], config)
    assert start.frame == "canonical"
    assert "cnn" in kept
    assert all("axes+atlas" in n for n in notes)


def test_a_wrong_model_falls_back_to_stack_registration(turned_scene) -> None:
    _, stacks, _ = turned_scene
    slices = extract_slices(stacks)
    net = StackPoseNet(StackPoseConfig(width=4, grid_size=16, grid_spacing_mm=8.0))
    with torch.no_grad():
        # Residuals of about 70 degrees about a different axis for every stack's block.
        net.pose.linear.weight.normal_(0.0, 0.5)
        net.pose.linear.bias.copy_(torch.tensor([1.2, -0.6, 0.3, 0.5, 0.0, 0.0]))
    config = recon_config(resolution_mm=2.5)
    start, kept, _, *_ = learned_start(slices, stacks, net, config)
    assert kept == ("stack", "stack", "stack")
    assert start.frame == "canonical"


def test_each_start_estimates_a_stack_its_own_way(turned_scene, monkeypatch) -> None:
    """The learned start: the model's pose, no atlas, the configured restarts (0 by default);
    the atlas start: no model, the atlas per stack."""
    import svr.reconstruction.initialisation.atlas as atlas_module
    import svr.reconstruction.initialisation.learned as learned_module

    atlas, stacks, _ = turned_scene
    slices = extract_slices(stacks)
    seen = []
    original = learned_module.estimate_stack_pose

    def recording(model, image, mask, atlas=None, levels=None, **kwargs):
        seen.append((model is None, atlas is None, levels is None, kwargs.get("restart_deg")))
        return original(model, image, mask, atlas=atlas, levels=levels, **kwargs)

    monkeypatch.setattr(learned_module, "estimate_stack_pose", recording)
    monkeypatch.setattr(atlas_module, "estimate_stack_pose", recording)
    net = StackPoseNet(StackPoseConfig(width=4, grid_size=16, grid_spacing_mm=8.0))
    config = recon_config(resolution_mm=2.5, packets=1)
    learned_start(slices, stacks, net, config)
    assert seen == [(False, True, True, 0.0)] * len(stacks)
    seen.clear()
    learned_start(slices, stacks, net, recon_config(resolution_mm=2.5, packets=1, restart_deg=5.0))
    assert seen == [(False, True, True, 5.0)] * len(stacks)
    seen.clear()
    atlas_start(slices, stacks, [atlas], config)
    assert seen == [(True, False, False, None)] * len(stacks)


@pytest.mark.parametrize(
    "rotvec",
    [
        (0.05, -0.08, math.pi - 0.1),  # a half turn and a tilt: a flip of the frame it is in
        (1.1, -0.9, 0.6),  # 90 degrees about an oblique axis: no flip is near it
    ],
)
def test_atlas_transform_recovers_the_frame_from_any_start(rotvec) -> None:
    _volume, _mask, atlas = _brain()
    turn = torch.eye(4, dtype=F64)
    turn[:3, :3] = so3_exp(torch.tensor(rotvec, dtype=F64))
    turn[:3, 3] = torch.tensor([3.0, -2.0, 4.0], dtype=F64)
    # The same brain, its world frame turned: world' = turn o canonical.
    moved = Image(atlas.image.data, turn @ atlas.image.affine)
    found = atlas_transform(moved, atlas.mask, atlas)
    assert set(found.scores) == {"none", "x", "y", "z", *(f"axes{i}" for i in range(8))}
    assert found.start != "none" and found.final[found.start] == max(found.final.values())
    assert found.final[found.start] > found.final["none"] + KEEP_MARGIN
    residual = se3_compose(found.transform, turn)  # should be the identity
    assert _angle_deg(residual, torch.eye(4, dtype=F64)) < 1.0
    assert float(residual[:3, 3].norm()) < 1.0


def test_atlas_transform_keeps_the_volumes_own_frame_unless_another_fits_clearly_better() -> None:
    _volume, _mask, atlas = _brain()
    # Turned by 10 degrees: the volume's own frame fits back to the right one.
    small = torch.eye(4, dtype=F64)
    small[:3, :3] = so3_exp(torch.tensor([0.1, 0.12, -0.08], dtype=F64))
    found = atlas_transform(Image(atlas.image.data, small @ atlas.image.affine), atlas.mask, atlas)
    assert found.start == "none" and len(found.final) == 3
    assert _angle_deg(se3_compose(found.transform, small), torch.eye(4, dtype=F64)) < 1.0
    # A half turn: the own frame fits worse; with a margin no fit can clear, it is kept anyway.
    half = torch.eye(4, dtype=F64)
    half[:3, :3] = so3_exp(torch.tensor([0.05, -0.08, math.pi - 0.1], dtype=F64))
    turned = Image(atlas.image.data, half @ atlas.image.affine)
    kept = atlas_transform(turned, atlas.mask, atlas, keep_margin=2.0, alternatives=1)
    assert kept.start == "none" and len(kept.final) == 2
    assert _angle_deg(se3_compose(kept.transform, half), torch.eye(4, dtype=F64)) > 30.0
    with pytest.raises(ValueError, match="'keep_margin' must be >= 0"):
        atlas_transform(turned, atlas.mask, atlas, keep_margin=-0.1)
    with pytest.raises(ValueError, match="'alternatives' must be >= 1"):
        atlas_transform(turned, atlas.mask, atlas, alternatives=0)


def test_atlas_transform_puts_the_given_centre_at_the_origin() -> None:
    _volume, _mask, atlas = _brain()
    small = torch.eye(4, dtype=F64)
    small[:3, :3] = so3_exp(torch.tensor([0.1, 0.12, -0.08], dtype=F64))
    moved = Image(atlas.image.data, small @ atlas.image.affine)
    centre = torch.tensor([2.0, -5.0, 3.0], dtype=F64)
    own = atlas_transform(moved, atlas.mask, atlas, alternatives=1)
    given = atlas_transform(moved, atlas.mask, atlas, alternatives=1, centre=centre)
    torch.testing.assert_close(given.transform[:3, :3], own.transform[:3, :3])
    torch.testing.assert_close(
        given.transform[:3, :3] @ centre + given.transform[:3, 3], torch.zeros(3, dtype=F64)
    )
    # Without one, the mask's centroid goes to the origin (the volume's world frame's origin).
    assert float(own.transform[:3, 3].norm()) < 1.0


def test_best_atlas_transform_takes_the_frame_of_the_atlas_the_volume_fits_best() -> None:
    _volume, _mask, atlas = _brain()
    # Another brain of the same shape, its texture unlike the volume's: a neighbouring age that
    # does not match.
    n, sp = 40, 2.5
    other_volume, other_mask = ellipsoid_brain(
        n, sp, (24.0, 30.0, 20.0), seed=11, texture=3.0, origin_mm=(-(n - 1) / 2 * sp,) * 3
    )
    other = canonicalize(other_volume, other_mask)
    small = torch.eye(4, dtype=F64)
    small[:3, :3] = so3_exp(torch.tensor([0.1, 0.12, -0.08], dtype=F64))
    moved = Image(atlas.image.data, small @ atlas.image.affine)
    to_other = atlas_transform(moved, atlas.mask, other).final["none"]
    for atlases, right in (([other, atlas], 1), ([atlas, other], 0)):
        index, found, ncc = best_atlas_transform(moved, atlas.mask, atlases)
        assert index == right and ncc[right] == max(ncc) == found.final[found.start]
        assert _angle_deg(se3_compose(found.transform, small), torch.eye(4, dtype=F64)) < 1.0
        assert found.final[found.start] > to_other
    # The first atlas is kept unless another fits better by more than the margin.
    index, found, ncc = best_atlas_transform(moved, atlas.mask, [other, atlas], keep_margin=2.0)
    assert index == 0 and ncc[1] > ncc[0]
    assert _angle_deg(se3_compose(found.transform, small), torch.eye(4, dtype=F64)) > 0.0
    with pytest.raises(ValueError, match="'keep_margin' must be >= 0"):
        best_atlas_transform(moved, atlas.mask, [other, atlas], keep_margin=-0.1)
    # One atlas: the same as atlas_transform.
    index, found, ncc = best_atlas_transform(moved, atlas.mask, atlas)
    assert index == 0 and len(ncc) == 1
    torch.testing.assert_close(found.transform, atlas_transform(moved, atlas.mask, atlas).transform)
    with pytest.raises(ValueError, match="'atlases' must hold at least one atlas"):
        best_atlas_transform(moved, atlas.mask, [])


def test_preferred_atlas_keeps_the_first_unless_another_is_clearly_better() -> None:
    assert preferred_atlas([0.327, 0.336, 0.331]) == 0  # the real scan's: within noise
    assert preferred_atlas([0.559, 0.632]) == 1  # ga23: GA 24 first, GA 22 clearly better
    assert preferred_atlas([0.5, 0.56, 0.58]) == 2  # the best of the others
    assert preferred_atlas([0.5, 0.55]) == 0 and preferred_atlas([0.5, 0.55], 0.0) == 1
    assert preferred_atlas([0.4]) == 0
    with pytest.raises(ValueError, match="'ncc' must hold at least one value"):
        preferred_atlas([])
    with pytest.raises(ValueError, match="'keep_margin' must be >= 0"):
        preferred_atlas([0.5, 0.6], -0.01)


def test_as_atlases_names_the_argument_and_what_it_expected() -> None:
    _volume, _mask, atlas = _brain()
    assert as_atlases(atlas, "f") == (atlas,)
    assert as_atlases([atlas, atlas], "f") == (atlas, atlas)
    with pytest.raises(TypeError, match=r"f\(\): 'atlas' must be a CanonicalVolume or a sequence"):
        as_atlases("GA28/srr.nii.gz", "f")
    with pytest.raises(TypeError, match=r"f\(\): 'atlas\[1\]' must be a CanonicalVolume, got int"):
        as_atlases([atlas, 3], "f")
    with pytest.raises(ValueError, match=r"f\(\): 'atlas' must hold at least one atlas"):
        as_atlases((), "f")


def test_align_to_atlas_turns_everything_and_centres_the_kept_slices_masks(turned_scene) -> None:
    atlas, stacks, _ = turned_scene
    small = torch.eye(4, dtype=F64)
    small[:3, :3] = so3_exp(torch.tensor([0.1, 0.12, -0.08], dtype=F64))
    volume = Image(atlas.image.data, small @ atlas.image.affine)
    mask = Image(atlas.mask.float(), volume.affine.clone())
    slices = extract_slices(stacks)
    excluded = torch.zeros(len(slices), dtype=torch.bool)
    excluded[:5] = True
    far = slices.poses.clone()
    far[:5, :3, 3] += 500.0  # excluded slices far away: they must not move the centre
    slices = slices.with_poses(far, "canonical")
    n = len(slices)
    result = ReconstructionResult(
        volume, mask, volume, slices, torch.ones(n), torch.ones(n), excluded, ("cnn",) * 3
    )
    aligned = align_to_atlas(result, atlas)
    transform = aligned.volume.affine @ torch.linalg.inv(volume.affine)
    # The volume comes back to the atlas's frame (it was turned by `small`) ...
    assert _angle_deg(se3_compose(transform, small), torch.eye(4, dtype=F64)) < 1.0
    # ... and everything moved by the same transform.
    torch.testing.assert_close(aligned.mask.affine, transform @ mask.affine)
    torch.testing.assert_close(aligned.slices.poses, transform @ slices.poses)
    # The kept slices' masks' centre is the new origin.
    centre = mask_centre(aligned.slices, ~excluded)
    torch.testing.assert_close(centre, torch.zeros(3, dtype=F64), atol=1e-6, rtol=0)
    turn = aligned.atlas_turn_deg
    assert (
        aligned.atlas_turn_applied is True
        and abs(turn - _angle_deg(small, torch.eye(4, dtype=F64))) < 1.0
    )
    # A turn over the limit is refused and recorded: only the centring is applied.
    refused = align_to_atlas(result, atlas, max_turn_deg=turn / 2)
    assert refused.atlas_turn_applied is False and refused.atlas_turn_deg == pytest.approx(turn)
    only_shift = refused.volume.affine @ torch.linalg.inv(volume.affine)
    torch.testing.assert_close(only_shift[:3, :3], torch.eye(3, dtype=F64))


def test_fit_to_atlas_takes_precomputed_levels_and_checks_their_number() -> None:
    from svr.reconstruction.atlas_fit import AtlasFitConfig, atlas_levels, fit_to_atlas

    _volume, _mask, atlas = _brain()
    turn = torch.eye(4, dtype=F64)
    turn[:3, :3] = so3_exp(torch.tensor([0.1, -0.05, 0.08], dtype=F64))
    moved = Image(atlas.image.data, turn @ atlas.image.affine)
    config = AtlasFitConfig(iterations=10, max_points=2000)
    levels = atlas_levels(atlas, config)
    given = fit_to_atlas(moved, atlas.mask, torch.eye(4, dtype=F64), atlas, config, levels)
    made = fit_to_atlas(moved, atlas.mask, torch.eye(4, dtype=F64), atlas, config)
    torch.testing.assert_close(given[0], made[0])
    assert given[1] == made[1]
    with pytest.raises(ValueError, match="'levels' must have 2 images"):
        fit_to_atlas(moved, atlas.mask, torch.eye(4, dtype=F64), atlas, config, levels[:1])


def test_estimate_stack_pose_passes_precomputed_levels_to_the_atlas_fit(turned_scene) -> None:
    from svr.reconstruction.atlas_fit import atlas_levels

    atlas, stacks, _truths = turned_scene
    stack = stacks[0]
    inside = stack.mask.data > 0.5
    levels = atlas_levels(atlas)
    given = estimate_stack_pose(None, stack.image, inside, atlas=atlas, levels=levels)
    made = estimate_stack_pose(None, stack.image, inside, atlas=atlas)
    torch.testing.assert_close(given.pose, made.pose)
    with pytest.raises(ValueError, match="'levels' must have 2 images"):
        estimate_stack_pose(None, stack.image, inside, atlas=atlas, levels=levels[:1])


def test_a_stack_whose_packets_turned_apart_starts_from_its_packets(monkeypatch) -> None:
    """Per-packet frames are a third candidate; a stack whose second packet turned keeps them."""
    import svr.reconstruction.initialisation.learned as learned_module
    from svr.reconstruction.initialisation.stack_pose import PacketPoseEstimate, StackPoseEstimate
    from svr.sampling.blocks import implied_stack_poses, stack_frame

    volume, mask, _atlas = _brain()
    specs = [
        ("a.nii.gz", (0.2, -0.1, 0.3), (40, 36), 14, 4.0),
        ("b.nii.gz", (1.4, 0.2, -0.2), (33, 38), 14, 4.0),
    ]
    turn = torch.eye(4, dtype=F64)
    turn[:3, :3] = so3_exp(torch.tensor([0.0, 0.0, math.radians(50.0)], dtype=F64))
    stacks, packet_frames = [], []
    for index, (name, rotvec, size, planes, thickness) in enumerate(specs):
        _, still = oblique_stack(volume, mask, name, rotvec, size, planes, thickness, 0)
        motion = None
        if index == 1:  # the odd planes (the second packet) turned 50 degrees about the brain
            motion = torch.eye(4, dtype=F64).repeat(planes, 1, 1)
            odd = slice(1, None, 2)
            motion[odd] = se3_compose(torch.linalg.inv(still[odd]), se3_compose(turn, still[odd]))
        stack, canonical = oblique_stack(
            volume, mask, name, rotvec, size, planes, thickness, 0, motion
        )
        stacks.append(stack)
        implied = implied_stack_poses(canonical, stack.image)
        to_frame = torch.linalg.inv(stack_frame(stack.image))
        packet_frames.append(torch.stack([implied[0] @ to_frame, implied[1] @ to_frame]))
    slices = extract_slices(stacks)
    calls = []

    def oracle_stack(model, image, inside, atlas=None, levels=None, **kwargs):
        sid = next(i for i, s in enumerate(stacks) if s.image is image)
        frame = packet_frames[sid][0]  # the first packet's frame: the second packet is off
        return StackPoseEstimate(
            frame @ stack_frame(image), frame, 5.0, frame[None], torch.ones(1), "learned"
        )

    def oracle_packets(model, image, inside, to_canonical, packet_of, iterations=3):
        sid = next(i for i, s in enumerate(stacks) if s.image is image)
        calls.append(packet_of.tolist())
        return PacketPoseEstimate(packet_frames[sid], torch.ones(2), torch.tensor([False, True]))

    monkeypatch.setattr(learned_module, "estimate_stack_pose", oracle_stack)
    monkeypatch.setattr(learned_module, "estimate_packet_poses", oracle_packets)
    net = StackPoseNet(StackPoseConfig(width=4, grid_size=16, grid_spacing_mm=8.0))
    config = recon_config(resolution_mm=2.5)
    start, kept, notes, *_ = learned_start(slices, stacks, net, config)
    assert calls == [[k % 2 for k in range(14)]] * 2
    assert kept[1] == "packets", notes
    assert "packets 0 deg, 50 deg" in notes[1]
    # The turned stack's packets start 50 degrees apart, as they were acquired.
    ids, ks = slices.stack_ids, slices.slice_indices
    even = start.poses[(ids == 1) & (ks % 2 == 0)][0].double()
    odd = start.poses[(ids == 1) & (ks % 2 == 1)][0].double()
    assert abs(_angle_deg(even, odd) - 50.0) < 2.0
    # With one packet per stack there is no packet candidate.
    calls.clear()
    _, kept, _, *_ = learned_start(slices, stacks, net, recon_config(resolution_mm=2.5, packets=1))
    assert calls == [] and "packets" not in kept


def test_stack_ncc_with_leave_out_scores_each_stack_against_the_others(turned_scene) -> None:
    from svr.reconstruction.registration import stack_ncc

    _, stacks, _ = turned_scene
    slices = extract_slices(stacks)  # at their scanner poses: every stack in place
    right = stack_ncc(slices, 2.5, leave_out=True)
    # Stack 1 turned half round about its slices' centre: its twin.
    members = slices.stack_ids == 1
    poses = slices.poses.to(F64).clone()
    centre = poses[members, :3, 3].mean(0)
    turn = torch.eye(4, dtype=F64)
    turn[:3, :3] = so3_exp(torch.tensor([0.0, 0.0, math.pi], dtype=F64))
    turn[:3, 3] = centre - turn[:3, :3] @ centre
    poses[members] = turn @ poses[members]
    wrong = slices.with_poses(poses.to(slices.poses))
    alone = stack_ncc(wrong, 2.5)
    apart = stack_ncc(wrong, 2.5, leave_out=True)
    assert float(apart[1]) < float(right[1]) - 0.2
    # Scored against a volume that holds its own slices, the twin hides part of its misfit.
    assert float(apart[1]) < float(alone[1]) - 0.1
    # With one stack there is nothing to leave it out from: the plain score.
    single = extract_slices(stacks[:1])
    torch.testing.assert_close(stack_ncc(single, 2.5, leave_out=True), stack_ncc(single, 2.5))


def test_slice_agreement_is_each_slice_against_an_explicit_volume_of_the_other_stacks(
    turned_scene,
) -> None:
    """The leave-one-stack-out sums give what a volume made of the other stacks alone gives."""
    from svr.reconstruction.operators import SliceProjector
    from svr.reconstruction.registration import (
        SVR_PSF_SAMPLES,
        _sda,
        slice_agreement,
        slice_ncc,
        stack_ncc,
    )
    from svr.reconstruction.superres import output_grid

    _, stacks, _ = turned_scene
    slices = extract_slices(stacks)
    got = slice_agreement(slices, 2.5, leave_out=True)
    grid = output_grid(slices, 2.5)
    for sid in range(len(slices.stack_names)):
        mine, others = (
            slices.subset(slices.stack_ids == sid),
            slices.subset(slices.stack_ids != sid),
        )
        volume = _sda(others, grid)  # a volume of the other stacks' slices alone
        own = SliceProjector(grid, mine, psf_samples=SVR_PSF_SAMPLES)
        simulated = own.forward(volume, own.grid_points(mine.poses))
        expected = slice_ncc(own, simulated, own.gather(mine.images))
        torch.testing.assert_close(got[slices.stack_ids == sid], expected, atol=1e-4, rtol=0)
    means = torch.stack([got[slices.stack_ids == s].mean() for s in range(len(stacks))])
    torch.testing.assert_close(stack_ncc(slices, 2.5, leave_out=True), means)


def test_slice_agreement_at_other_poses_scores_them_against_the_volume_as_it_is(turned_scene):
    """``at``: the slices scored at other poses, the other stacks' volume made at their own."""
    from svr.geometry import so3_exp
    from svr.reconstruction.registration import SliceAgreement, slice_agreement

    _, stacks, _ = turned_scene
    slices = extract_slices(stacks)
    own = slice_agreement(slices, 2.5, leave_out=True)
    torch.testing.assert_close(slice_agreement(slices, 2.5, True, at=slices.poses), own)
    turn = torch.eye(4, dtype=slices.poses.dtype)
    turn[:3, :3] = so3_exp(torch.tensor([0.0, 0.0, 0.3], dtype=turn.dtype))
    first = slices.stack_ids == 0
    moved = slices.poses.clone()
    moved[first] = moved[first] @ turn  # stack 0's slices turned 17 deg in their planes
    got = slice_agreement(slices, 2.5, True, at=moved)
    # The other stacks are scored where they are, against a volume that does not move with
    # stack 0's scores (they come from their own stacks' sums at their own poses).
    torch.testing.assert_close(got[~first], own[~first])
    assert float(got[first].mean()) < float(own[first].mean()) - 0.05
    with pytest.raises(ValueError, match="'at' must be"):
        slice_agreement(slices, 2.5, at=slices.poses[:2])
    # One set of volumes scores both, exactly as two calls do.
    volumes = SliceAgreement(slices, 2.5, leave_out=True)
    assert torch.equal(volumes(), own) and torch.equal(volumes(moved), got)


def test_the_output_frame_follows_the_larger_group_of_agreeing_stacks() -> None:
    """Three stacks in a frame and three in its front-back twin: the robust mean of all slices
    lands far from both, so the frame comes from the group with the larger vote."""
    from scipy.spatial.transform import Rotation

    from svr.geometry import rotation_angle
    from svr.geometry.averaging import robust_mean_pose

    def pose(rotvec: list[float], shift: float) -> torch.Tensor:
        out = torch.eye(4, dtype=torch.float64)
        out[:3, :3] = torch.from_numpy(Rotation.from_rotvec(rotvec).as_matrix())
        out[:3, 3] = shift
        return out

    right = [pose([0.02 * s, -0.03, 0.01 * s], s) for s in range(3)]
    twin = [pose([0.01 * s, 0.02, math.pi - 0.02 * s], -s) for s in range(3)]
    per_slice = torch.stack([p for p in right + twin for _ in range(5)])  # 5 slices per stack
    ids = torch.arange(6).repeat_interleave(5)
    mean = robust_mean_pose(per_slice)
    assert min(math.degrees(float(rotation_angle(mean, f[0]))) for f in (right, twin)) > 45
    confident_right = torch.tensor([0.99, 0.98, 0.97, 0.6, 0.7, 0.9], dtype=torch.float64)
    assert agreeing_stacks(per_slice, ids, confident_right).tolist() == [True] * 3 + [False] * 3
    assert agreeing_stacks(per_slice, ids, 1.0 - confident_right + 0.5).tolist() == (
        [False] * 3 + [True] * 3
    )
    # All agreeing: every stack; a stack without slices is never in the group.
    near = torch.stack([p for p in right for _ in range(5)])
    ids3 = torch.arange(3).repeat_interleave(5)
    assert agreeing_stacks(near, ids3, torch.ones(3)).tolist() == [True] * 3
    assert agreeing_stacks(near, ids3, torch.ones(4)).tolist() == [True] * 3 + [False]
