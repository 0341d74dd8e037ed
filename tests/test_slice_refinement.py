"""Every slice refined against the atlas: input planes, the keep rule, the shipped stages."""

from __future__ import annotations

import dataclasses
import logging
import math

import pytest
import torch
from test_recon_init import make_scene, true_array_poses

from svr.geometry import rotation_angle, se3_compose, se3_inverse, se3_to_vector, so3_exp
from svr.image import Image
from svr.models.backbones import BackboneConfig
from svr.models.network import loss_function
from svr.models.pretrained import MAX_MODEL_BYTES, SLICE_REFINER_STAGES, slice_refiner_paths
from svr.models.slice_refiner import SliceRefinerConfig, SliceRefinerNet, shipped_slice_refiners
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation import slice_refinement
from svr.reconstruction.initialisation.choice import Start
from svr.reconstruction.initialisation.learned import refined_slices
from svr.reconstruction.initialisation.slice_refinement import (
    atlas_reference,
    place_slices,
    refine_poses,
    refiner_inputs,
    slices_on_grid,
)
from svr.reconstruction.trajectory import SMOOTHNESS_GRID, cross_validated_trajectory
from svr.sampling.poses import pose_labels
from svr.sampling.volume import CanonicalVolume

F64 = torch.float64


def tiny_config(size: tuple[int, int] = (16, 16), spacing: float = 2.0) -> SliceRefinerConfig:
    return SliceRefinerConfig(
        size=size,
        spacing_mm=spacing,
        plane_offsets_mm=(-4.0, 0.0, 4.0),
        backbone=BackboneConfig(width=8, depth=2),
        head="coords",
    )


def rigid(rotvec: tuple[float, float, float], shift: tuple[float, float, float]) -> torch.Tensor:
    out = torch.eye(4, dtype=F64)
    out[:3, :3] = so3_exp(torch.tensor(rotvec, dtype=F64))
    out[:3, 3] = torch.tensor(shift, dtype=F64)
    return out


class ConstantRefiner(torch.nn.Module):
    """A stand-in refiner that predicts the same residual ``D`` for every slice."""

    def __init__(self, residual: torch.Tensor, config: SliceRefinerConfig) -> None:
        super().__init__()
        self.config = config
        self.anchor = torch.nn.Parameter(torch.zeros(1))
        self.residual = se3_to_vector(residual)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.residual.expand(len(inputs), 6)

    def to_pose(self, outputs: torch.Tensor) -> torch.Tensor:
        return outputs


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def _atlas(volume: Image) -> CanonicalVolume:
    mask = volume.data > 0
    return CanonicalVolume(volume, mask, torch.zeros(3, dtype=F64), 1.0)


def test_reference_planes_lie_where_the_pose_and_offsets_put_them():
    """Trilinear sampling is exact on a linear ramp: each channel against hand-placed points."""
    n, spacing = 30, 2.0
    origin = -(n - 1) / 2 * spacing
    affine = torch.diag(torch.tensor([spacing, spacing, spacing, 1.0], dtype=F64))
    affine[:3, 3] = origin
    coefficients = torch.tensor([0.01, 0.02, 0.03], dtype=F64)
    points = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=F64)] * 3, indexing="ij"), -1)
    world = points * spacing + origin
    reference = Image((1.0 + world @ coefficients).float(), affine)
    config = tiny_config()
    net = SliceRefinerNet(config).eval()
    poses = torch.stack(
        [rigid((0.3, -0.5, 0.9), (2.0, -1.0, 3.0)), rigid((-1.2, 0.4, 0.1), (0, 2, -2))]
    )
    images = torch.rand(2, *config.size)
    inputs = refiner_inputs(net, images, reference, poses)
    assert inputs.shape == (2, 4, 16, 16)
    torch.testing.assert_close(inputs[:, 0], images)
    h, w = config.size
    a = (torch.arange(h, dtype=F64) - (h - 1) / 2) * config.spacing_mm
    b = (torch.arange(w, dtype=F64) - (w - 1) / 2) * config.spacing_mm
    for k, offset in enumerate(config.plane_offsets_mm):
        plane = torch.stack(
            (*torch.meshgrid(a, b, indexing="ij"), torch.full((h, w), offset, dtype=F64)), -1
        )
        for i, pose in enumerate(poses):
            expected = 1.0 + (plane @ pose[:3, :3].T + pose[:3, 3]) @ coefficients
            torch.testing.assert_close(inputs[i, k + 1].double(), expected, atol=1e-5, rtol=0)


def test_slices_on_their_own_grid_are_the_masked_slices_normalised(scene):
    _, _, _, slices = scene
    net = SliceRefinerNet(tiny_config(size=slices.size, spacing=float(slices.spacing_mm[0, 0])))
    out = slices_on_grid(slices, net)
    masked = slices.images * slices.masks
    for i in (0, len(slices) // 2, len(slices) - 1):
        brain = masked[i][masked[i] > 0]
        torch.testing.assert_close(out[i], masked[i] / brain.quantile(0.99), atol=1e-4, rtol=1e-3)


@pytest.mark.parametrize(("threshold", "least_kept"), [(None, 0.6), (1.0, 0.9)])
def test_a_right_estimate_is_kept_and_a_wrong_one_is_not(scene, monkeypatch, threshold, least_kept):
    """Every slice 12.8 deg off in its own frame (the start agrees: median NCC 0.62), moved to
    the truth: most moves are kept when judged against the other stacks at their start (the
    default here), nearly all against the other stacks moved (``TRUSTED_START_NCC`` 1: the start
    never trusted); the same move from the truth is kept for no slice but, judged against the
    others at their start, the last of stack 0 (72 brain pixels against a median of 347)."""
    if threshold is not None:
        monkeypatch.setattr(slice_refinement, "TRUSTED_START_NCC", threshold)
    volume, stacks, truth, slices = scene
    true = true_array_poses(slices, truth, stacks)
    atlas = _atlas(volume)
    residual = rigid((0.0, 0.2, 0.1), (1.0, -2.0, 0.5))  # 12.8 deg and 2.3 mm in each slice's frame
    config = tiny_config()
    off = slices.with_poses(se3_compose(true, se3_inverse(residual)[None]), "canonical")
    right = place_slices(off, atlas, [(ConstantRefiner(residual, config), 1)], 2.5)
    assert right.start_trusted == (threshold is None)
    assert right.kept.float().mean() > least_kept
    assert (right.ncc_after > right.ncc_before).float().mean() > least_kept
    angle = torch.rad2deg(rotation_angle(right.poses[right.kept], true[right.kept]))
    assert float(angle.max()) < 1e-6
    on = slices.with_poses(true, "canonical")
    wrong = place_slices(on, atlas, [(ConstantRefiner(residual, config), 1)], 2.5)
    assert int(wrong.kept.sum()) <= (1 if threshold is None else 0)
    torch.testing.assert_close(wrong.poses[~wrong.kept], true[~wrong.kept])


def test_a_pull_every_slice_shares_is_not_kept_where_the_start_agrees(scene, monkeypatch):
    """Slices scattered 3 deg about the truth, "refined" by one turn of the whole brain (10 deg,
    as an atlas's anatomy pulls every slice alike): the moved slices agree with each other better
    than the scattered start does, so judged against the other stacks moved the pull is kept;
    judged against the other stacks at their start (the default where the start agrees) it is
    not."""
    volume, stacks, truth, slices = scene
    true = true_array_poses(slices, truth, stacks)
    generator = torch.Generator().manual_seed(3)
    axes = torch.nn.functional.normalize(torch.randn(len(true), 3, generator=generator, dtype=F64))
    scatter = torch.eye(4, dtype=F64).repeat(len(true), 1, 1)
    scatter[:, :3, :3] = so3_exp(axes * math.radians(3.0))
    start = slices.with_poses(se3_compose(true, scatter), "canonical")
    pull = se3_compose(rigid((math.radians(10.0), 0.0, 0.0), (0.0, 0.0, 0.0))[None], true)
    monkeypatch.setattr(slice_refinement, "refine_poses", lambda *_: pull.clone())
    stages = [(ConstantRefiner(torch.eye(4, dtype=F64), tiny_config()), 1)]
    placed = place_slices(start, _atlas(volume), stages, 2.5)
    assert placed.start_trusted
    assert placed.kept.float().mean() < 0.1
    monkeypatch.setattr(slice_refinement, "TRUSTED_START_NCC", 1.0)
    moved = place_slices(start, _atlas(volume), stages, 2.5)
    assert not moved.start_trusted
    assert moved.kept.float().mean() > 0.5


def test_with_packets_a_calm_heads_slices_are_put_on_their_trajectories(scene, monkeypatch):
    volume, stacks, truth, slices = scene
    true = true_array_poses(slices, truth, stacks)
    residual = rigid((0.0, 0.2, 0.1), (1.0, -2.0, 0.5))
    off = slices.with_poses(se3_compose(true, se3_inverse(residual)[None]), "canonical")
    stages = [(ConstantRefiner(residual, tiny_config()), 1)]
    plain = place_slices(off, _atlas(volume), stages, 2.5)
    assert plain.smoothness is None and not plain.on_trajectory
    fit, smoothness, _ = cross_validated_trajectory(off.with_poses(plain.poses), 2)
    for chosen, calm in (
        (smoothness, smoothness == max(SMOOTHNESS_GRID)),
        (3.0, True),
        (0.3, False),
    ):
        monkeypatch.setattr(
            slice_refinement, "cross_validated_trajectory", lambda *_, c=chosen: (fit, c, None)
        )
        placed = place_slices(off, _atlas(volume), stages, 2.5, packets=2)
        assert placed.smoothness == chosen and placed.on_trajectory == calm
        assert torch.equal(placed.kept, plain.kept)
        torch.testing.assert_close(placed.poses, fit.poses if calm else plain.poses)


def test_one_stack_has_nothing_to_agree_with(scene):
    """Even the exact correction is not kept: no other stack can say it agrees better."""
    volume, stacks, truth, slices = scene
    true = true_array_poses(slices, truth, stacks)
    residual = rigid((0.0, 0.2, 0.1), (1.0, -2.0, 0.5))
    mine = slices.stack_ids == 0
    one = slices.subset(mine).with_poses(
        se3_compose(true[mine], se3_inverse(residual)[None]), "canonical"
    )
    one = type(one)(**{**one.__dict__, "stack_names": one.stack_names[:1]})
    config = tiny_config()
    placed = place_slices(one, _atlas(volume), [(ConstantRefiner(residual, config), 1)], 2.5)
    assert not bool(placed.kept.any())


def test_the_shipped_stages_load_and_the_start_says_what_moved(scene, caplog):
    paths = slice_refiner_paths()
    assert [p.name for p in paths] == list(SLICE_REFINER_STAGES)
    for path in paths:
        assert sum(f.stat().st_size for f in path.iterdir()) <= MAX_MODEL_BYTES
    nets = shipped_slice_refiners()
    assert all(net.config.context == "none" and not net.training for net in nets)
    volume, stacks, truth, slices = scene
    true = true_array_poses(slices, truth, stacks)
    start = Start(slices.with_poses(true, "canonical"), ("packets",) * len(stacks))
    learned = ReconstructionConfig.preset("learned")
    on = dataclasses.replace(learned.initialisation, slice_trajectory=True)
    config = dataclasses.replace(learned, initialisation=on)
    refined = refined_slices(start, _atlas(volume), config)
    assert len(refined.notes) == len(stacks)
    assert all("slice refiner:" in note for note in refined.notes)
    # The log says whether the slices were put on their packets' trajectories, and why.
    with caplog.at_level(logging.INFO, logger="svr.reconstruction"):
        refined_slices(start, _atlas(volume), config)
    assert "slice trajectories: the " in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="svr.reconstruction"):
        plain = refined_slices(start, _atlas(volume), learned)  # the default: off
    assert "slice trajectories" not in caplog.text
    assert not any("trajectories" in note for note in plain.notes)
    moved = torch.rad2deg(rotation_angle(refined.slices.poses, true))
    assert math.isfinite(float(moved.max()))


def test_a_tiny_refiner_learns_a_residual_and_refine_poses_applies_it_on_the_right_side(scene):
    """Trained with the SE(3) loss on ``D = T_current^-1 o T_true``; applied as ``T o D``."""
    volume, stacks, truth, slices = scene
    true = true_array_poses(slices, truth, stacks)
    residual = rigid((0.1, -0.08, 0.06), (0.0, 0.0, 0.0))  # 8.1 deg about the slice centre
    torch.manual_seed(0)
    config = SliceRefinerConfig(
        size=(16, 16),
        spacing_mm=4.0,
        plane_offsets_mm=(-6.0, 0.0, 6.0),
        backbone=BackboneConfig(width=8, depth=2),
        head="regress",
        hidden=16,
    )
    net = SliceRefinerNet(config)
    off = slices.with_poses(se3_compose(true, se3_inverse(residual)[None]), "canonical")
    reference = atlas_reference(_atlas(volume))
    inputs = refiner_inputs(net, slices_on_grid(off, net), reference, off.poses)
    labels = pose_labels(se3_to_vector(residual)[None], "se3").float().expand(len(inputs), -1)
    loss_of = loss_function("se3")
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-2)
    first = float(loss_of(net(inputs), labels).detach())
    for _ in range(150):
        optimiser.zero_grad()
        loss = loss_of(net(inputs), labels)
        loss.backward()
        optimiser.step()
    assert float(loss.detach()) < first / 20
    net.eval()
    moved = refine_poses([(net, 1)], off, reference)
    before = torch.rad2deg(rotation_angle(off.poses, true))
    after = torch.rad2deg(rotation_angle(moved, true))
    assert float(before.median()) == pytest.approx(8.1, abs=0.05)
    assert float(after.median()) < 1.0
