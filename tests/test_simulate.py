"""The motion-corrupted stack simulator: geometry round trips, motion, noise, output layout."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import asdict

import numpy as np
import pytest
import torch
from oracles import foreground_cc, truth_poses
from synthetic import ellipsoid_brain

from svr.files import OutputExistsError
from svr.geometry import se3_to_vector
from svr.image import Image, load_nifti
from svr.sampling.motion import load_trajectories, random_walk_motion, trajectory_motion
from svr.sampling.simulate import (
    SimulationConfig,
    acquisition_order,
    simulate_case,
    stack_orientations,
    write_case,
)
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import canonicalize

SMALL = {"in_plane_mm": 2.0, "thickness_mm": 4.0, "margin_mm": 2.0}


@pytest.fixture(scope="module")
def brain():
    # The source frame is not centred on the brain.
    return canonicalize(
        *ellipsoid_brain(36, 1.5, (20, 24, 18), seed=3, texture=3.0, origin_mm=(5.0, -7.0, 3.0))
    )


def test_written_case_round_trips_in_both_frames(brain, tmp_path):
    config = SimulationConfig(
        noise=0.0,
        motion="random_walk",
        random_walk_rotation_deg=10.0,
        random_walk_translation_mm=4.0,
        **SMALL,
    )
    out = write_case(simulate_case(brain, config), tmp_path / "case")
    gt = load_nifti(out / "gt_volume.nii.gz")
    source = Image(brain.image.data, brain.source_affine)
    truth = json.loads((out / "truth_slices.json").read_text())
    assert len(truth["stacks"]) == 3
    for entry in truth["stacks"]:
        stack = load_nifti(out / entry["file"])
        slices = stack.data.permute(2, 0, 1)
        cfg = SliceConfig(size=stack.shape[:2], spacing_mm=2.0, thickness_mm=4.0)
        assert foreground_cc(sample_slices(gt, truth_poses(entry, "scanner"), cfg), slices) > 0.999
        assert (
            foreground_cc(sample_slices(source, truth_poses(entry, "atlas"), cfg), slices) > 0.999
        )
        # motion happened: the true rotations are not the stack's nominal orientation
        orientation = stack.affine[:3, :3] / stack.affine[:3, :3].norm(dim=0)
        rotations = truth_poses(entry, "scanner")[:, :3, :3]
        assert (rotations - orientation).abs().amax(dim=(1, 2)).max() > 0.01


def test_without_motion_the_stack_affine_is_the_truth(brain):
    case = simulate_case(brain, SimulationConfig(noise=0.0, motion="none", **SMALL))
    for stack in case.stacks:
        affine = stack.image.affine
        for k in (0, stack.image.shape[2] - 1):
            ijk = torch.tensor([3.0, 5.0, float(k), 1.0], dtype=torch.float64)
            world = affine @ ijk
            uv = torch.tensor(
                [
                    (3 - (stack.image.shape[0] - 1) / 2) * 2.0,
                    (5 - (stack.image.shape[1] - 1) / 2) * 2.0,
                    0.0,
                    1.0,
                ],
                dtype=torch.float64,
            )
            torch.testing.assert_close(stack.true_poses[k] @ uv, world)


def test_stack_geometry_options(brain):
    gen = torch.Generator().manual_seed(0)
    ortho = stack_orientations(SimulationConfig(num_stacks=3), gen)
    normals = torch.stack([q[:, 2] for q in ortho])
    torch.testing.assert_close(normals @ normals.T, torch.eye(3, dtype=torch.float64))
    oblique = stack_orientations(SimulationConfig(num_stacks=4, orientations="oblique"), gen)
    for q, base in zip(oblique, [*ortho, ortho[0]], strict=True):
        angle = math.acos(float(torch.clamp((q[:, 2] * base[:, 2]).sum(), -1, 1)))
        assert angle <= math.radians(30.0) + 1e-9
    gap = simulate_case(brain, SimulationConfig(motion="none", spacing_mm=8.0, **SMALL))
    overlap = simulate_case(brain, SimulationConfig(motion="none", spacing_mm=2.0, **SMALL))
    assert gap.stacks[0].image.shape[2] < overlap.stacks[0].image.shape[2]
    assert float(gap.stacks[0].image.spacing[2]) == pytest.approx(8.0)


def test_interleaved_acquisition_order():
    assert acquisition_order(5, 2).tolist() == [0, 3, 1, 4, 2]
    assert acquisition_order(4, 1).tolist() == [0, 1, 2, 3]
    assert sorted(acquisition_order(7, 3).tolist()) == list(range(7))


def test_motion_follows_the_acquisition_order(brain):
    """Slices acquired one after the other differ by one random-walk step; neighbours in space,
    acquired half a stack apart (interleave 2), differ by many."""
    config = SimulationConfig(
        noise=0.0,
        motion="random_walk",
        random_walk_rotation_deg=20.0,
        random_walk_translation_mm=0.0,
        interleave=2,
        **SMALL,
    )
    stack = simulate_case(brain, config).stacks[0]
    rot = se3_to_vector(stack.true_poses)[:, :3]
    by_time = rot[torch.argsort(stack.acquisition_index)]
    step_in_time = (by_time[1:] - by_time[:-1]).norm(dim=1).mean()
    step_in_space = (rot[1:] - rot[:-1]).norm(dim=1).mean()
    assert step_in_space > 2 * step_in_time


def test_random_walk_motion_magnitude():
    gen = torch.Generator().manual_seed(1)
    ends = torch.stack(
        [se3_to_vector(random_walk_motion(20, gen, 5.0, 2.0))[-1] for _ in range(400)]
    )
    assert torch.allclose(
        se3_to_vector(random_walk_motion(5, gen, 5.0, 2.0))[0], torch.zeros(6, dtype=torch.float64)
    )
    std = ends.std(0)
    assert std[:3].rad2deg().mean().item() == pytest.approx(5.0, rel=0.15)
    assert std[3:].mean().item() == pytest.approx(2.0, rel=0.15)


def write_trajectories(path, n=3):
    arrays = {}
    t = np.arange(0, 61, dtype=np.float64)
    for i in range(n):
        arrays[f"rot_{i:03d}_x"] = t
        arrays[f"rot_{i:03d}_y"] = np.stack([np.sin(t / 10), 0 * t, 0 * t], 1) * 0.2
        arrays[f"trans_{i:03d}_x"] = t
        arrays[f"trans_{i:03d}_y"] = np.stack([t / 10, 0 * t, 0 * t], 1)
    np.savez(path, **arrays)


def test_trajectories(tmp_path, brain):
    write_trajectories(tmp_path / "motion.npz")
    (trajectory, *_) = load_trajectories(tmp_path / "motion.npz")
    motion = trajectory_motion(trajectory, np.array([0.0, 10.0, 70.0]), start_s=0.0, scale=0.5)
    torch.testing.assert_close(motion[0], torch.eye(4, dtype=torch.float64))
    assert motion[1, 0, 3].item() == pytest.approx(0.5)  # 1 mm at 10 s, scaled by 0.5
    assert motion[2, 0, 3].item() == pytest.approx(0.5)  # wraps: 70 s is 10 s into the replay
    config = SimulationConfig(
        motion="trajectories", motion_path=str(tmp_path / "motion.npz"), noise=0.0, **SMALL
    )
    assert simulate_case(brain, config).stacks[0].true_poses.shape[1:] == (4, 4)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"bad\.npz: not a fetal motion trajectory file"):
        load_trajectories(tmp_path / "bad.npz")
    np.savez(tmp_path / "pickled.npz", rot_000_x=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match=r"pickled\.npz"):
        load_trajectories(tmp_path / "pickled.npz")


def test_real_trajectories_load(shared_data):
    trajectories = load_trajectories(shared_data / "motion" / "svort_fetal_motion_trajectories.npz")
    assert len(trajectories) == 154
    assert all(t.duration_s > 0 for t in trajectories)


def test_noise_bias_and_voids_change_the_slices(brain):
    clean = simulate_case(brain, SimulationConfig(noise=0.0, motion="none", seed=4, **SMALL))
    noisy = simulate_case(
        brain,
        SimulationConfig(
            noise=0.05, bias_field=0.3, signal_void_probability=1.0, motion="none", seed=4, **SMALL
        ),
    )
    a, b = clean.stacks[0].image.data, noisy.stacks[0].image.data
    assert (b >= 0).all()
    background = clean.stacks[0].mask.data < 0.5
    assert b[background & (a == 0)].mean() > 0.01  # Rician floor in the background
    assert 0.6 < foreground_cc(a, b) < 0.999


def test_determinism_and_seeds(brain):
    config = SimulationConfig(**SMALL)
    a = simulate_case(brain, config).stacks[1].image.data
    torch.testing.assert_close(simulate_case(brain, config).stacks[1].image.data, a)
    other = simulate_case(brain, SimulationConfig(seed=9, **SMALL)).stacks[1].image.data
    assert a.shape != other.shape or not torch.equal(a, other)


def test_write_case_refuses_to_overwrite(brain, tmp_path):
    case = simulate_case(brain, SimulationConfig(num_stacks=1, motion="none", **SMALL))
    out = write_case(case, tmp_path / "c", source="synthetic")
    assert sorted(p.name for p in out.iterdir()) == [
        "case.json",
        "gt_mask.nii.gz",
        "gt_volume.nii.gz",
        "masks",
        "stacks",
        "truth_slices.json",
    ]
    info = json.loads((out / "case.json").read_text())
    assert info["source"] == "synthetic" and info["thickness"] == [4.0]
    with pytest.raises(OutputExistsError, match="output exists"):
        write_case(case, out)
    write_case(case, out, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c"]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"num_stacks": 0}, "'num_stacks'"),
        ({"thickness_mm": 0.0}, "'thickness_mm'"),
        ({"spacing_mm": -1.0}, "'spacing_mm'"),
        ({"noise": -0.1}, "'noise'"),
        ({"signal_void_probability": 2.0}, "'signal_void_probability'"),
        ({"orientations": "diagonal"}, "'orientations'"),
        ({"motion": "trajectories"}, "'motion_path'"),
        ({"mask_fraction": 0.0}, "'mask_fraction'"),
        ({"mask_fraction": 1.0}, "'mask_fraction'"),
        ({"mask_fraction": float("nan")}, "'mask_fraction'"),
        ({"mask_fraction": True}, "'mask_fraction'"),
        ({"mask_fraction": 0.2, "grazing_ratio": 0.0}, "'grazing_ratio'"),
        ({"mask_fraction": 0.2, "grazing_ratio": 1.5}, "'grazing_ratio'"),
        ({"mask_fraction": 0.2, "grazing_ratio": float("nan")}, "'grazing_ratio'"),
        ({"grazing_ratio": 0.5}, "'grazing_ratio' must be None without 'mask_fraction'"),
    ],
)
def test_config_validation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SimulationConfig(**kwargs)


def test_partial_volume_masks_hold_the_slices_grazing_the_brain(brain):
    """With ``mask_fraction`` a slice's mask holds the brain wherever that fraction of its
    through-plane profile is brain: a superset of the centre-plane mask (where the centre node
    alone, weight 0.53 of 5 Gauss-Hermite nodes, is brain the fraction is above 0.2), larger
    at the brain's ends; the images are the same."""
    config = SimulationConfig(noise=0.0, motion="none", **SMALL)
    thin = simulate_case(brain, config)
    thick = simulate_case(brain, SimulationConfig(**{**asdict(config), "mask_fraction": 0.2}))
    grown = 0
    for a, b in zip(thin.stacks, thick.stacks, strict=True):
        assert torch.equal(a.image.data, b.image.data)
        assert bool((b.mask.data >= a.mask.data).all())  # a superset
        grown += int((b.mask.data > a.mask.data).sum())
        per_slice = a.mask.data.flatten(0, 1).sum(0), b.mask.data.flatten(0, 1).sum(0)
        assert bool((per_slice[1] >= per_slice[0]).all())
    assert grown > 0.03 * sum(int(s.mask.data.sum()) for s in thin.stacks)
    strict = simulate_case(brain, SimulationConfig(**{**asdict(config), "mask_fraction": 0.9}))
    for a, b in zip(thin.stacks, strict.stacks, strict=True):
        assert int(b.mask.data.sum()) < int(a.mask.data.sum())  # a high fraction shrinks it


def test_grazing_ratio_gives_the_partial_volume_mask_only_to_slices_grazing_the_brain(brain):
    """With ``grazing_ratio`` each slice's mask is either its centre-plane mask or its
    partial-volume mask, the latter exactly where the centre-plane one is under that fraction of
    it: the slices at the brain's ends take it, the middle slices (whose partial-volume outline
    is wider too) keep the centre plane's."""
    config = SimulationConfig(noise=0.0, motion="none", **SMALL)
    thin = simulate_case(brain, config)
    thick = simulate_case(brain, dataclasses.replace(config, mask_fraction=0.2))
    ratio = 0.5
    graze = simulate_case(
        brain, dataclasses.replace(config, mask_fraction=0.2, grazing_ratio=ratio)
    )
    taken = kept_narrower = 0
    for a, b, c in zip(thin.stacks, thick.stacks, graze.stacks, strict=True):
        assert torch.equal(a.image.data, c.image.data)
        area_a, area_b = a.mask.data.flatten(0, 1).sum(0), b.mask.data.flatten(0, 1).sum(0)
        for k in range(a.mask.shape[2]):
            if area_a[k] < ratio * area_b[k]:
                assert torch.equal(c.mask.data[..., k], b.mask.data[..., k])
                taken += 1
            else:
                assert torch.equal(c.mask.data[..., k], a.mask.data[..., k])
                kept_narrower += int(area_b[k] > area_a[k] > 0)
        through = torch.nonzero(area_b > 0)[:, 0]
        ends = through.min(), through.max()
        grazing = area_a < ratio * area_b
        assert bool(grazing[ends[0]] or grazing[ends[1]])  # an end slice takes it
        assert not bool(grazing[(ends[0] + ends[1]) // 2])  # the middle one keeps its own
    assert taken > 0 and kept_narrower > 0
