"""A reconstruction says whether its volume and its frame can be trusted; the frame's evidence."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from scipy.spatial.transform import Rotation
from synthetic import ellipsoid_brain
from test_recon_slices import AFFINE_C, make_stack

from svr.errors import ConfigFieldError
from svr.geometry import half_turns, rotation_angle, se3_compose
from svr.image import Image
from svr.models.stack_pose import StackPoseConfig, StackPoseNet
from svr.reconstruction.initialisation import stack_pose
from svr.reconstruction.midplane import level_to_midplane, mirror_plane_line
from svr.reconstruction.pipeline import _judged, _mirror_plane
from svr.reconstruction.result import ReconstructionResult, relabelled
from svr.reconstruction.slices import extract_slices
from svr.reconstruction.verdict import Verdict, VerdictConfig, assess
from svr.timing import PhaseTimer

F64 = torch.float64


def result_with(ncc: list[float], frame: str = "scanner", **fields) -> ReconstructionResult:
    """A result of two stacks of 2 slices each, with the given slice NCCs."""
    stacks = [
        make_stack("a.nii.gz", (4, 5, 2), [0, 1], (0, 0), 0, (4, 5), AFFINE_C),
        make_stack("b.nii.gz", (4, 5, 2), [0, 1], (0, 0), 0, (4, 5), AFFINE_C),
    ]
    slices = extract_slices(stacks)
    slices = slices.with_poses(slices.poses, frame)  # type: ignore[arg-type]
    volume = Image(torch.ones(4, 4, 4), torch.eye(4, dtype=F64))
    base = ReconstructionResult(
        volume=volume,
        mask=volume,
        initial_volume=volume,
        slices=slices,
        slice_ncc=torch.tensor(ncc),
        slice_weights=torch.ones(4),
        excluded=torch.zeros(4, dtype=torch.bool),
        initialisation=("stack", "stack"),
        converged=True,
    )
    return dataclasses.replace(base, **fields)


def test_a_good_volume_in_the_scanner_frame_is_ok():
    verdict = assess(result_with([0.95, 0.93, 0.9, 0.92]))
    assert verdict == Verdict("ok", "scanner", ())
    assert verdict.line() == "ok, scanner frame"


def test_a_volume_that_did_not_settle_and_fits_poorly_failed():
    # The whole-uterus case: the rounds ran to their cap and no stack fits the volume.
    verdict = assess(result_with([0.1, -0.04, 0.03, 0.2], converged=False))
    assert verdict.status == "failed"
    assert verdict.reasons[0] == "not converged"
    assert any("fit the volume poorly" in r for r in verdict.reasons)
    assert any("stacks disagree" in r and "a.nii.gz" in r for r in verdict.reasons)
    assert verdict.line().startswith("failed, scanner frame: not converged; ")


def test_one_sign_alone_is_a_warning():
    assert assess(result_with([0.95, 0.93, 0.9, 0.92], converged=False)).status == "warning"
    stack_apart = assess(result_with([0.95, 0.95, 0.55, 0.4]))
    assert stack_apart.status == "warning" and "b.nii.gz" in stack_apart.reasons[-1]
    most_excluded = result_with([0.95, 0.9, 0.9, 0.9], excluded=torch.tensor([1, 1, 1, 0]).bool())
    assert assess(most_excluded).status == "failed"


@pytest.mark.parametrize(
    ("frame_margin", "atlas_margin", "trust"),
    [
        (8.0, None, "trusted"),
        (None, 0.1, "trusted"),
        (1.0, 0.01, "uncertain"),
        (-2.0, 0.01, "uncertain"),
        (-2.0, 0.0, "untrusted"),
        (None, None, "uncertain"),
        (0.0, -0.01, "untrusted"),
    ],
)
def test_a_canonical_frame_is_trusted_only_on_evidence(frame_margin, atlas_margin, trust):
    result = result_with(
        [0.95] * 4, "canonical", frame_margin=frame_margin, atlas_margin=atlas_margin
    )
    verdict = assess(result)
    assert verdict.frame == trust
    assert (verdict.status == "ok") == (trust == "trusted")
    if trust != "trusted":
        assert "evidence" in verdict.reasons[-1]


@pytest.mark.parametrize(
    ("turn", "kept", "trust"), [(33.0, False, "uncertain"), (12.0, True, "trusted")]
)
def test_a_learned_frame_the_atlas_fit_would_turn_far_is_uncertain(turn, kept, trust):
    # The real scan with automatic masks: the learned frame has a clear margin, the atlas fit
    # wanted a 33 deg turn and was refused; the atlas does not confirm the frame.
    result = result_with(
        [0.95] * 4,
        "canonical",
        frame_margin=5.5,
        atlas_margin=0.0,
        atlas_turn_deg=turn,
        atlas_turn_applied=kept,
    )
    verdict = assess(result)
    assert verdict.frame == trust
    if trust == "uncertain":
        assert verdict.status == "warning"
        assert verdict.reasons == (
            "the atlas fit disagrees: it would turn the frame by 33 deg (not applied) "
            "(stack-pose margin 5.5, atlas-fit margin 0.000)",
        )


def test_verdict_thresholds_are_checked():
    with pytest.raises(ConfigFieldError, match="'frame_margin'"):
        VerdictConfig(frame_margin=-1.0)
    with pytest.raises(ConfigFieldError, match="'max_excluded'"):
        VerdictConfig(max_excluded=1.5)


def test_relabelling_moves_every_pose_and_affine_and_the_scanner_transform():
    result = result_with([0.9] * 4, "canonical", from_scanner=torch.eye(4, dtype=F64))
    turn = torch.eye(4, dtype=F64)
    turn[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix())
    turn[:3, 3] = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    moved = relabelled(result, turn, "scanner")
    assert moved.slices.frame == "scanner"
    torch.testing.assert_close(moved.volume.affine, turn @ result.volume.affine)
    torch.testing.assert_close(moved.slices.poses, turn @ result.slices.poses)
    torch.testing.assert_close(moved.from_scanner, turn)
    assert torch.equal(moved.volume.data, result.volume.data)


def test_a_brain_is_levelled_onto_its_own_mirror_plane():
    # A left-right symmetric ellipsoid brain (symmetric texture), then turned: the levelled
    # result's mirror plane is x = 0 again.
    volume, mask = ellipsoid_brain(33, 2.0, (20.0, 26.0, 18.0), seed=3, texture=1.0)
    data = volume.data
    data = 0.5 * (data + torch.flip(data, dims=[0]))  # mirror-symmetric about x = 0
    centre = torch.eye(4, dtype=F64)
    centre[:3, 3] = -(torch.tensor(data.shape, dtype=F64) - 1) / 2 * 2.0
    affine = centre @ torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0], dtype=F64))
    affine = centre.clone()
    affine[:3, :3] = 2.0 * torch.eye(3, dtype=F64)
    turn = torch.eye(4, dtype=F64)
    turn[:3, :3] = torch.from_numpy(
        Rotation.from_euler("yz", [8.0, -6.0], degrees=True).as_matrix()
    )
    image = Image(data, turn @ affine)
    result = result_with(
        [0.95] * 4, "canonical", volume=image, mask=Image(mask.data.float(), turn @ affine)
    )
    levelled, tilt = level_to_midplane(result)
    assert tilt is not None and abs(tilt - 10.0) < 1.5
    # The levelled frame undoes the turn's roll and yaw (about y and z) to within a degree.
    residual = levelled.volume.affine[:3, :3] / 2.0
    assert math.degrees(rotation_angle(residual, torch.eye(3, dtype=F64))) < 1.0
    assert levelled.midplane_tilt_deg == tilt
    # An asymmetric brain is left as it is.
    lopsided = result_with(
        [0.95] * 4, "canonical", volume=volume, mask=Image(mask.data.float(), affine)
    )
    noise = torch.rand(volume.data.shape, generator=torch.Generator().manual_seed(0))
    lopsided = dataclasses.replace(lopsided, volume=Image(noise * mask.data, affine))
    same, none = level_to_midplane(lopsided)
    assert none is None and same.volume is lopsided.volume and same.slices is lopsided.slices
    # ... and its best plane in any orientation is recorded for the verdict: none is clear.
    assert same.mirror_correlation is not None and same.mirror_correlation < 0.4
    assert same.mirror_tilt_deg is not None
    assert levelled.mirror_correlation is not None and levelled.mirror_correlation > 0.9
    # Given poses keep their frame (reconstruct_from_poses): the plane is only measured.
    kept = _mirror_plane(result, PhaseTimer(), level=False)
    assert torch.equal(kept.volume.affine, result.volume.affine)
    assert kept.mirror_tilt_deg is not None and abs(kept.mirror_tilt_deg - 10.0) < 1.5
    assert kept.mirror_correlation is not None and kept.mirror_correlation > 0.9
    moved = _mirror_plane(result, PhaseTimer())
    torch.testing.assert_close(moved.volume.affine, levelled.volume.affine)
    # The log's and QA page's line says which.
    assert mirror_plane_line(levelled) == (
        f"mirror plane: correlation {levelled.mirror_correlation:.2f}, x = 0 (levelled by "
        f"{tilt:.0f} deg)"
    )
    assert mirror_plane_line(kept).endswith(f", {kept.mirror_tilt_deg:.0f} deg from x = 0")
    assert mirror_plane_line(lopsided) is None


@pytest.mark.parametrize(
    ("mirror", "tilt", "converged", "status", "trust"),
    [
        (0.8, 3.0, True, "ok", "trusted"),
        (0.8, 45.0, True, "warning", "untrusted"),  # a clear plane far from x = 0
        (0.15, 80.0, True, "warning", "uncertain"),  # no clear plane: not a brain
        (0.15, 80.0, False, "failed", "uncertain"),  # ... and not converged: failed
        (0.8, 3.0, False, "warning", "trusted"),
    ],
)
def test_the_brains_mirror_plane_checks_the_volume_and_the_frame(
    mirror, tilt, converged, status, trust
):
    # A learned margin that would trust the frame on its own (wu24-severe's: 4.0).
    result = result_with(
        [0.95] * 4,
        "canonical",
        frame_margin=4.0,
        converged=converged,
        mirror_correlation=mirror,
        mirror_tilt_deg=tilt,
    )
    verdict = assess(result)
    assert (verdict.status, verdict.frame) == (status, trust)
    if mirror < 0.4:
        assert any("no clear mirror plane" in r for r in verdict.reasons)
    if trust == "untrusted":
        assert "45 deg from the frame's x = 0" in verdict.reasons[-1]
    # In the scanner frame only the volume is judged by it.
    scanner = dataclasses.replace(
        result, slices=result.slices.with_poses(result.slices.poses, "scanner")
    )
    assert assess(scanner).frame == "scanner"
    assert assess(scanner).status == (
        "failed" if status == "failed" else "warning" if mirror < 0.4 or not converged else "ok"
    )


def test_a_frame_whose_mirror_plane_is_far_off_is_written_in_the_scanner_frame():
    result = result_with(
        [0.95] * 4,
        "canonical",
        frame_margin=8.0,
        from_scanner=torch.eye(4, dtype=F64),
        mirror_correlation=0.8,
        mirror_tilt_deg=45.0,
    )
    judged = _judged(result)
    assert judged.slices.frame == "scanner"
    assert judged.verdict.frame == "scanner"
    assert judged.verdict.reasons[-1] == "written in the scanner frame instead"


def test_the_joint_frame_of_registered_stacks_outvotes_a_twin(monkeypatch):
    """Each hypothesis is scored on every stack and the scores summed: two stacks that prefer
    the right frame outvote one that prefers its twin, and the winner's margin is reported."""
    right = torch.eye(4, dtype=F64)
    twin = half_turns()[0]

    def fake_refine(model, image, fractions, transforms, iterations=3, present=None):
        stack = int(image.data.flatten()[0])
        near_right = rotation_angle(transforms, right.expand_as(transforms)) < 0.5
        scores = torch.where(near_right, 3.0, -3.0)
        if stack == 2:  # the stack that prefers the twin
            scores = torch.where(near_right, -1.0, 2.0)
        return transforms, scores.float()

    monkeypatch.setattr(stack_pose, "refine_transforms", fake_refine)
    monkeypatch.setattr(stack_pose, "coarsen_stack", lambda image, mask, mm: (image, mask.float()))
    stacks = [
        (Image(torch.full((2, 2, 2), float(s)), torch.eye(4, dtype=F64)), torch.ones(2, 2, 2))
        for s in range(3)
    ]
    moves = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    own = torch.stack([right, right, twin])
    net = StackPoseNet(StackPoseConfig(width=4, grid_size=16, grid_spacing_mm=8.0))
    joint = stack_pose.joint_frame(net, stacks, own, moves)
    assert math.degrees(rotation_angle(joint.to_canonical, right)) < 1e-6
    assert joint.score == pytest.approx(3.0 + 3.0 - 1.0)
    assert joint.margin == pytest.approx(joint.score - (-3.0 - 3.0 + 2.0))
    # With its own stacks alone, the twin would have won stack 2.
    assert se3_compose(twin, right).shape == (4, 4)


def test_the_atlas_turn_line_says_whether_the_turn_was_applied():
    from svr.reconstruction.atlas_frame import atlas_turn_line

    assert atlas_turn_line(result_with([0.9] * 4)) == ""
    kept = result_with([0.9] * 4, atlas_turn_deg=4.71, atlas_turn_applied=True)
    assert atlas_turn_line(kept) == "atlas fit: turned 4.7 deg"
    refused = result_with([0.9] * 4, atlas_turn_deg=32.8, atlas_turn_applied=False)
    assert atlas_turn_line(refused) == "atlas fit: would turn 32.8 deg (not applied)"
