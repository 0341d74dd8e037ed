"""Stack frames, blocks, mask-axis hypotheses and the stack-pose network (fast, synthetic)."""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from synthetic import ellipsoid_brain

from svr.geometry import ANCHOR_HALF_SIZE_MM, se3_compose, se3_inverse, se3_to_vector, so3_exp
from svr.image import Image, sample_world, stack_slice_poses, voxel_to_world
from svr.models.checkpoint import CheckpointError, save_checkpoint
from svr.models.stack_pose import (
    STACK_POSE_MODEL,
    StackPoseConfig,
    StackPoseNet,
    StackPoseOutput,
    load_stack_pose_model,
)
from svr.models.stack_pose_batches import draw_samples, simulate_batch, step_seed
from svr.models.stack_pose_loss import stack_pose_loss
from svr.models.stack_pose_train import StackPoseTrainingConfig, train_stack_pose
from svr.reconstruction.initialisation.stack_pose import (
    estimate_packet_poses,
    estimate_stack_pose,
    mask_axis_hypotheses,
    restart_transforms,
)
from svr.representation_registry import REPRESENTATIONS
from svr.sampling.blocks import (
    BlockGrid,
    TrainingStackConfig,
    block_inputs,
    coarsen_stack,
    implied_stack_poses,
    packet_index,
    simulate_training_stack,
    stack_frame,
    stack_pose_from_slices,
)
from svr.sampling.simulate import SimulationConfig, simulate_case
from svr.sampling.volume import canonicalize, downsample_volume


def _volume(semi_axes=(30.0, 40.0, 24.0)):
    image, mask = ellipsoid_brain(48, 2.0, semi_axes, seed=1, origin_mm=(-47.0, -47.0, -47.0))
    return canonicalize(image, mask)


def _still_case(seed: int):
    """The test volume and a one-stack case cut from it at a random orientation, without motion."""
    volume = _volume()
    config = SimulationConfig(
        num_stacks=1, orientations="random", motion="none", in_plane_mm=2.0, seed=seed
    )
    return volume, simulate_case(volume, config)


def _rotation(seed: int) -> torch.Tensor:
    return torch.from_numpy(Rotation.random(random_state=seed).as_matrix())


def test_stack_frame_is_the_centre_slice_pose_for_an_odd_stack() -> None:
    volume = _volume()
    case = simulate_case(
        volume,
        SimulationConfig(
            num_stacks=1,
            orientations="random",
            motion="none",
            in_plane_mm=2.0,
            thickness_mm=3.0,
            seed=3,
        ),
    )
    stack = case.stacks[0].image
    poses = stack_slice_poses(stack)
    frame = stack_frame(stack)
    assert torch.allclose(frame[:3, :3], poses[0, :3, :3])
    assert torch.allclose(frame[:3, 3], poses[:, :3, 3].mean(0))
    # slices sit along the frame's z axis
    local = se3_compose(se3_inverse(frame)[None], poses)
    assert torch.allclose(
        local[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(len(poses), 3, 3), atol=1e-12
    )
    assert torch.allclose(
        local[:, :2, 3], torch.zeros(len(poses), 2, dtype=torch.float64), atol=1e-9
    )


def test_stack_pose_from_slices_agrees_with_the_slice_sampler_without_motion() -> None:
    volume, case = _still_case(4)
    stack = case.stacks[0]
    to_canonical = torch.eye(4, dtype=torch.float64)
    to_canonical[:3, 3] = -volume.centre_mm
    slice_poses = se3_compose(to_canonical[None], stack.atlas_poses)
    pose = stack_pose_from_slices(slice_poses, stack.image)
    # Without motion every slice is the stack pose moved along its normal by its offset.
    local = se3_compose(se3_inverse(stack_frame(stack.image))[None], stack_slice_poses(stack.image))
    assert torch.allclose(se3_compose(pose[None], local), slice_poses, atol=1e-6)
    # ... so every slice implies that same stack pose.
    implied = implied_stack_poses(slice_poses, stack.image)
    assert torch.allclose(implied, pose.expand_as(implied), atol=1e-6)
    with pytest.raises(ValueError, match="one pose per slice"):
        stack_pose_from_slices(slice_poses[:-1], stack.image)


def test_block_at_the_true_frame_shows_the_canonical_brain() -> None:
    volume = _volume()
    case = simulate_case(
        volume,
        SimulationConfig(
            num_stacks=1,
            orientations="random",
            motion="none",
            in_plane_mm=2.0,
            thickness_mm=2.0,
            noise=0.0,
            seed=5,
        ),
    )
    stack = case.stacks[0]
    to_canonical = torch.eye(4, dtype=torch.float64)
    to_canonical[:3, 3] = -volume.centre_mm
    pose = stack_pose_from_slices(se3_compose(to_canonical[None], stack.atlas_poses), stack.image)
    true_frame = se3_compose(pose, se3_inverse(stack_frame(stack.image)))
    grid = BlockGrid(size=24, spacing_mm=4.0)
    wrong = true_frame.clone()
    wrong[:3, :3] = (
        so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64)) @ wrong[:3, :3]
    )
    blocks = block_inputs(stack.image, stack.mask.data, torch.stack([true_frame, wrong]), grid)
    assert blocks.shape == (2, 3, 24, 24, 24)
    truth = sample_world(volume.image, grid.points().float())

    def ncc(a, b):
        a, b = a.flatten() - a.mean(), b.flatten() - b.mean()
        return float((a * b).sum() / (a.norm() * b.norm()))

    assert ncc(blocks[0, 0], truth) > 0.9
    assert ncc(blocks[1, 0], truth) < ncc(blocks[0, 0], truth) - 0.1
    assert blocks[:, 2].max() <= 1.0 + 1e-6


def test_block_of_a_subset_is_not_darker() -> None:
    volume = _volume()
    case = simulate_case(
        volume,
        SimulationConfig(
            num_stacks=1,
            orientations="orthogonal",
            random_placement=False,
            motion="none",
            in_plane_mm=2.0,
            thickness_mm=4.0,
            noise=0.0,
            seed=6,
        ),
    )
    stack = case.stacks[0]
    frame = torch.eye(4, dtype=torch.float64)
    present = torch.zeros(stack.image.shape[2], dtype=torch.bool)
    present[::2] = True
    grid = BlockGrid(size=16, spacing_mm=4.0)
    full = block_inputs(stack.image, stack.mask.data, frame[None], grid)
    half = block_inputs(stack.image, stack.mask.data, frame[None], grid, present, scale=1.0)
    full1 = block_inputs(stack.image, stack.mask.data, frame[None], grid, scale=1.0)
    seen = half[0, 2] > 0.5
    assert 0.3 < float(half[0, 2].mean()) / float(full[0, 2].mean()) < 0.8
    assert torch.allclose(half[0, 0][seen].mean(), full1[0, 0][seen].mean(), rtol=0.15)


def test_coarsen_stack_keeps_world_positions() -> None:
    image, mask = ellipsoid_brain(24, 1.0, (8.0, 6.0, 5.0), seed=2, origin_mm=(3.0, -2.0, 1.0))
    coarse, _fractions = coarsen_stack(image, mask.data, 2.0)
    assert coarse.shape == (12, 12, 24)
    centre_fine = voxel_to_world(image.affine, torch.tensor([[0.5, 0.5, 3.0]], dtype=torch.float64))
    centre_coarse = voxel_to_world(
        coarse.affine, torch.tensor([[0.0, 0.0, 3.0]], dtype=torch.float64)
    )
    assert torch.allclose(centre_fine, centre_coarse)
    assert torch.allclose(coarse.data[0, 0, 3], image.data[:2, :2, 3].mean())
    same, _ = coarsen_stack(image, mask.data, 1.0)
    assert same is image


def test_mask_axis_hypotheses_contain_the_true_frame() -> None:
    # An ellipsoid with semi-axes LR 30, AP 40, SI 24 mm placed at a known rotation and shift.
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, size=(20000, 3))
    points = points[(points**2).sum(1) < 1] * np.array([30.0, 40.0, 24.0])
    rotation, shift = _rotation(11), torch.tensor([5.0, -3.0, 8.0], dtype=torch.float64)
    scanner = torch.from_numpy(points) @ rotation.T + shift
    frames = mask_axis_hypotheses(scanner)
    assert frames.shape == (8, 4, 4)
    assert torch.allclose(torch.linalg.det(frames[:, :3, :3]), torch.ones(8, dtype=torch.float64))
    truth = torch.eye(4, dtype=torch.float64)
    truth[:3, :3], truth[:3, 3] = rotation.T, -rotation.T @ shift
    angles = [
        math.degrees(float(Rotation.from_matrix((f[:3, :3].T @ truth[:3, :3]).numpy()).magnitude()))
        for f in frames
    ]
    best = int(np.argmin(angles))
    assert angles[best] < 2.0
    assert best < 4  # the default axis order (x = middle, z = shortest)
    assert torch.allclose(frames[best, :3, 3], truth[:3, 3], atol=0.5)
    assert sorted(angles)[1] > 85  # the other hypotheses are far off (x-z swaps: 90 deg)
    with pytest.raises(ValueError, match="'points'"):
        mask_axis_hypotheses(torch.zeros(3, 3))


def _tiny_training():
    model = StackPoseConfig(width=4, grid_size=16, grid_spacing_mm=6.0)
    training = StackPoseTrainingConfig(
        steps=60,
        stacks_per_step=1,
        samples_per_stack=4,
        learning_rate=3e-3,
        checkpoint_every=30,
        fine_tune_steps=0,
        stacks=TrainingStackConfig(thickness_mm=(3.0, 4.0), in_plane_mm=3.0),
    )
    return model, training


@pytest.mark.parametrize(
    ("head", "representation"),
    [
        ("regress", "se3"),
        ("coords", "se3"),
        ("regress", "quat_translation"),
        ("regress", "anchor_points"),
        ("regress", "rotation6d_translation"),
    ],
)
def test_draws_and_loss_are_consistent(head: str, representation: str) -> None:
    model_config, training = _tiny_training()
    model_config = StackPoseConfig(
        **{**model_config.to_dict(), "head": head, "representation": representation}
    )
    volume = downsample_volume(_volume(), 1)
    stack = simulate_training_stack(volume, training.stacks, torch.Generator().manual_seed(0), None)
    blocks, starts, target, labels = draw_samples(
        stack, model_config, training, torch.Generator().manual_seed(1)
    )
    assert blocks.shape == (4, 3, 16, 16, 16)
    net = StackPoseNet(model_config)
    output = net(blocks)
    assert output.residual.shape == (4, 4, 4) and output.score.shape == (4,)
    entry = REPRESENTATIONS[representation]

    def as_output(residual: torch.Tensor) -> StackPoseOutput:
        raw = None
        if head == "regress":
            raw = entry.encode(se3_to_vector(residual.double()), ANCHOR_HALF_SIZE_MM).float()
        return output._replace(residual=residual.float(), raw=raw)

    # An untrained network predicts the identity residual.
    assert torch.allclose(output.residual, torch.eye(4).expand(4, 4, 4), atol=1e-5)
    # The true residual gives a zero pose loss; the start's own error gives a positive one.
    true_residual = se3_compose(target.expand(4, 4, 4), torch.linalg.inv(starts))
    cells = getattr(net, "cells", None)
    within = labels.clamp(min=1)
    zero, zero_parts = stack_pose_loss(
        as_output(true_residual),
        starts,
        target.expand(4, 4, 4),
        within,
        training,
        cells,
        representation,
    )
    ident, parts = stack_pose_loss(
        as_output(torch.eye(4, dtype=torch.float64).expand(4, 4, 4))._replace(coords=None),
        starts,
        target.expand(4, 4, 4),
        within,
        training,
        None,
        representation,
    )
    assert zero_parts["pose"] < 1e-6
    assert parts["pose"] > 0.005
    assert float(zero.detach()) < float(ident.detach())
    loss, _ = stack_pose_loss(
        output, starts, target.expand(4, 4, 4), labels, training, cells, representation
    )
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
    if representation != "se3":
        with pytest.raises(ValueError, match="regress head"):
            stack_pose_loss(
                output._replace(raw=None),
                starts,
                target.expand(4, 4, 4),
                labels,
                training,
                None,
                representation,
            )


def test_a_baseline_representation_is_rejected_with_the_coords_head() -> None:
    with pytest.raises(ValueError, match="'representation' must be se3"):
        StackPoseConfig(head="coords", representation="anchor_points")
    with pytest.raises(ValueError, match="representation"):
        StackPoseConfig(representation="euler")


def test_checkpoints_from_before_the_pose_head_load() -> None:
    net = StackPoseNet(StackPoseConfig(width=4, grid_size=16))
    state = net.state_dict()
    expected = state.pop("pose.linear.weight") + 1.0
    state["pose.weight"] = expected.clone()
    state["pose.bias"] = state.pop("pose.linear.bias")
    fresh = StackPoseNet(StackPoseConfig(width=4, grid_size=16))
    fresh.load_state_dict(state)
    assert torch.equal(fresh.pose.linear.weight, expected)


def test_models_from_before_the_hidden_norm_load_without_it(tmp_path) -> None:
    """A config without ``hidden_norm`` (the shipped model's) builds the hidden layer without
    batch normalisation, so its weights load exactly; new models have it."""
    old = StackPoseNet(StackPoseConfig(width=4, grid_size=16, hidden_norm=False))
    model = old.config.to_dict()
    del model["hidden_norm"]
    save_checkpoint(
        tmp_path / "m", old.state_dict(), {"architecture": "stack_pose", "model": model}
    )
    loaded = load_stack_pose_model(tmp_path / "m")
    assert loaded.config.hidden_norm is False
    assert [type(m) for m in loaded.fc] == [torch.nn.Flatten, torch.nn.Linear, torch.nn.ReLU]
    for a, b in zip(loaded.state_dict().values(), old.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    assert load_stack_pose_model(STACK_POSE_MODEL).config.hidden_norm is False
    new = StackPoseNet(StackPoseConfig(width=4, grid_size=16))
    assert isinstance(new.fc[2], torch.nn.BatchNorm1d)
    config = {"architecture": "stack_pose", "model": new.config.to_dict()}
    save_checkpoint(tmp_path / "n", new.state_dict(), config)
    assert load_stack_pose_model(tmp_path / "n").config.hidden_norm is True
    with pytest.raises(ValueError, match="'hidden_norm'"):
        StackPoseConfig(hidden_norm=1)  # type: ignore[arg-type]
    # Batch normalisation needs two blocks per step.
    model_config, training = _tiny_training()
    single = dataclasses.replace(training, steps=1, samples_per_stack=1)
    with pytest.raises(ValueError, match="'config' must give >= 2 blocks per step"):
        train_stack_pose([_volume()], None, model_config, single)


def test_a_tiny_model_learns_and_resumes(tmp_path) -> None:
    model_config, training = _tiny_training()
    volume = _volume()
    net = train_stack_pose([volume], None, model_config, training, folder=tmp_path / "run")
    assert (tmp_path / "run" / "step_000000060").is_dir()
    loaded = load_stack_pose_model(tmp_path / "run")
    for a, b in zip(net.state_dict().values(), loaded.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    # Resuming a finished run changes nothing.
    again = train_stack_pose([volume], None, model_config, training, folder=tmp_path / "run")
    for a, b in zip(net.state_dict().values(), again.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def test_worker_processes_train_the_same_network_for_any_count_and_resume(tmp_path) -> None:
    """--workers N: the step's seed fixes its stacks, so N = 1 and N = 2 agree, and a run stopped
    after one step and resumed ends as the run straight through; N = 0 is the single stream."""
    from svr.models.stack_pose_batches import StepBatches

    model_config, training = _tiny_training()
    training = dataclasses.replace(training, steps=3, checkpoint_every=3)
    volume = _volume()

    def run(workers: int, **kwargs) -> list[torch.Tensor]:
        net = train_stack_pose([volume], None, model_config, training, workers=workers, **kwargs)
        return list(net.state_dict().values())

    def same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
        return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))

    one = run(1)
    assert same(run(2), one)
    assert not same(run(0), one)
    # Each step's batch is the in-process simulation from the step's seed.
    phases = (([volume], None), ([volume], None))
    dataset = StepBatches(phases, training.steps, None, model_config, training)
    for step in (0, 2):
        generator = torch.Generator().manual_seed(step_seed(training.seed, step))
        expected = simulate_batch([volume], None, model_config, training, generator)
        assert all(torch.equal(a, b) for a, b in zip(dataset[step], expected, strict=True))
    # Out of time after the first step (checkpoint 1), then resumed with another count.
    run(2, folder=tmp_path / "run", time_limit_s=0.0)
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["step_000000001"]
    assert same(run(1, folder=tmp_path / "run"), one)
    with pytest.raises(ValueError, match="'workers'"):
        run(-1)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_weighted_training_runs_on_cuda_and_its_checkpoint_loads_on_the_cpu(tmp_path) -> None:
    """The GPU recipe's path: simulation workers, per-brain weights in both phases, the network
    on CUDA; the checkpoint it writes loads on the CPU and estimates as the CUDA network does."""
    model_config, training = _tiny_training()
    training = dataclasses.replace(training, steps=6, checkpoint_every=3, fine_tune_steps=3)
    first, extra = _volume(), _volume((28.0, 38.0, 26.0))
    net = train_stack_pose(
        [first],
        None,
        model_config,
        training,
        folder=tmp_path / "run",
        device="cuda",
        workers=1,
        fine_tune_volumes=[extra],
        volume_weights=[1.0],
        fine_tune_weights=[2.0],
    )
    assert all(p.is_cuda and bool(torch.isfinite(p).all()) for p in net.parameters())
    loaded = load_stack_pose_model(tmp_path / "run")
    assert not next(loaded.parameters()).is_cuda
    for a, b in zip(net.state_dict().values(), loaded.state_dict().values(), strict=True):
        assert torch.equal(a.cpu(), b)
    blocks = simulate_batch(
        [first], None, model_config, training, torch.Generator().manual_seed(5)
    )[0]
    with torch.no_grad():
        on_gpu = net(blocks.cuda())
        on_cpu = loaded(blocks)
    for name in ("residual", "score"):
        torch.testing.assert_close(
            getattr(on_gpu, name).cpu(), getattr(on_cpu, name), rtol=1e-3, atol=1e-4
        )


def test_a_block_flipped_along_x_is_the_stack_in_the_mirrored_frame() -> None:
    # Flipping a block's first axis is sampling the stack at M o E, M the reflection x -> -x of
    # the canonical frame (the premise of benchmarks/experiments/stack_pose_mirror.py).
    _, case = _still_case(4)
    stack = case.stacks[0]
    frame = torch.eye(4, dtype=torch.float64)
    frame[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix())
    frame[:3, 3] = torch.tensor([4.0, -3.0, 7.0], dtype=torch.float64)
    reflect = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=torch.float64))
    grid = BlockGrid(size=16, spacing_mm=5.0)
    blocks = block_inputs(stack.image, stack.mask.data, torch.stack([frame, reflect @ frame]), grid)
    assert blocks[0].abs().sum() > 0
    assert torch.allclose(blocks[0].flip(1), blocks[1], atol=1e-5)


def test_estimate_returns_a_rigid_pose_for_every_hypothesis() -> None:
    model_config, _ = _tiny_training()
    net = StackPoseNet(model_config)
    _, case = _still_case(7)
    estimate = estimate_stack_pose(
        net, case.stacks[0].image, case.stacks[0].mask.data, iterations=1
    )
    assert estimate.hypotheses.shape == (8, 4, 4)
    assert estimate.scores.shape == (8,)
    assert torch.allclose(
        torch.linalg.det(estimate.pose[:3, :3]), torch.tensor(1.0, dtype=torch.float64)
    )
    assert torch.allclose(
        estimate.pose, se3_compose(estimate.to_canonical, stack_frame(case.stacks[0].image))
    )
    with pytest.raises(ValueError, match="fewer than 4"):
        estimate_stack_pose(net, case.stacks[0].image, torch.zeros(case.stacks[0].image.shape))


def test_restart_frames_turn_about_each_canonical_axis() -> None:
    """Against scipy: the six copies are the frame turned by +-angle about x, y and z."""
    frame = torch.tensor(
        [[0.0, -1.0, 0.0, 4.0], [1.0, 0.0, 0.0, -2.0], [0.0, 0.0, 1.0, 7.0], [0, 0, 0, 1]],
        dtype=torch.float64,
    )
    frames = restart_transforms(frame, 12.0)
    assert frames.shape == (7, 4, 4) and frames.dtype == torch.float64
    assert torch.equal(frames[0], frame)
    for i, (axis, sign) in enumerate([(a, s) for a in range(3) for s in (1, -1)], start=1):
        vector = np.zeros(3)
        vector[axis] = sign * math.radians(12.0)
        turn = Rotation.from_rotvec(vector).as_matrix()
        np.testing.assert_allclose(frames[i, :3, :3], turn @ frame[:3, :3].numpy(), atol=1e-12)
        np.testing.assert_allclose(frames[i, :3, 3], turn @ frame[:3, 3].numpy(), atol=1e-12)
    assert torch.allclose(restart_transforms(frame, 0.0), frame.expand(7, 4, 4))
    with pytest.raises(ValueError, match="'turn_deg'"):
        restart_transforms(frame, -1.0)
    with pytest.raises(ValueError, match="'to_canonical'"):
        restart_transforms(frame[:3], 10.0)


def test_the_chosen_frame_is_the_robust_mean_of_its_restarts(monkeypatch) -> None:
    """The best-scored hypothesis is refined again from 7 starts; their robust mean is kept."""
    import svr.reconstruction.initialisation.stack_pose as stack_pose

    model_config, _ = _tiny_training()
    net = StackPoseNet(model_config)
    _, case = _still_case(7)
    stack = case.stacks[0]
    target = torch.eye(4, dtype=torch.float64)
    target[:3, :3] = so3_exp(torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64))
    target[:3, 3] = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    outlier = se3_compose(
        torch.tensor(
            [[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=torch.float64
        ),
        target,
    )
    calls = []

    def fake_refine(model, image, mask, frames, iterations=3, present=None):
        calls.append(frames.clone())
        scores = torch.zeros(frames.shape[0])
        if len(calls) == 1:  # the 8 hypotheses: the third scores best, refined as it is
            scores[2] = 1.0
            return frames + 0.0, scores
        # the restarts: two land on a frame turned 90 degrees from the target, five on it
        return torch.stack([outlier] * 2 + [target] * 5), scores

    monkeypatch.setattr(stack_pose, "refine_transforms", fake_refine)
    estimate = stack_pose.estimate_stack_pose(
        net, stack.image, stack.mask.data, iterations=2, restart_deg=10.0
    )
    assert [c.shape[0] for c in calls] == [8, 7]
    assert torch.allclose(calls[1], restart_transforms(calls[0][2], 10.0))
    assert torch.allclose(estimate.to_canonical, target, atol=1e-6)
    assert torch.equal(estimate.hypotheses, calls[0])
    calls.clear()
    plain = stack_pose.estimate_stack_pose(
        net, stack.image, stack.mask.data, iterations=2, restart_deg=0.0
    )
    assert len(calls) == 1 and torch.equal(plain.to_canonical, calls[0][2])


def test_each_packet_keeps_its_best_scored_candidate(monkeypatch) -> None:
    """The stack's frame and the packet's own 8 hypotheses compete on the packet's slices."""
    import svr.reconstruction.initialisation.stack_pose as stack_pose

    model_config, _ = _tiny_training()
    net = StackPoseNet(model_config)
    _, case = _still_case(7)
    stack = case.stacks[0]
    k = stack.image.shape[2]
    packet_of = torch.arange(k) % 2
    image, fractions = coarsen_stack(stack.image, stack.mask.data, model_config.in_plane_mm)
    idx = torch.nonzero((fractions > 0.5) & (packet_of == 1)[None, None, :]).double()
    own = mask_axis_hypotheses(voxel_to_world(image.affine, idx))  # packet 1's own hypotheses
    seen = []

    def fake_refine(model, image, mask, frames, iterations=3, present=None):
        # Packet 0 likes the stack's frame (the first candidate), packet 1 its 6th candidate.
        seen.append((frames.shape[0], present.clone()))
        scores = torch.zeros(frames.shape[0])
        scores[0 if bool(present[0]) else 5] = 1.0
        return frames + 0.0, scores

    def turned(frame: torch.Tensor, deg: float) -> torch.Tensor:
        out = frame.clone()
        out[:3, :3] = (
            so3_exp(torch.tensor([math.radians(deg), 0.0, 0.0], dtype=torch.float64))
            @ (frame[:3, :3])
        )
        return out

    monkeypatch.setattr(stack_pose, "refine_transforms", fake_refine)
    # The stack's frame 30 degrees from packet 1's own choice: each packet keeps its choice.
    near = turned(own[4], 30.0)
    estimate = stack_pose.estimate_packet_poses(net, stack.image, stack.mask.data, near, packet_of)
    assert [n for n, _ in seen] == [9, 9]
    assert torch.equal(seen[0][1], packet_of == 0)
    assert torch.equal(seen[1][1], packet_of == 1)
    assert estimate.own.tolist() == [False, True]
    assert torch.equal(estimate.to_canonical[0], near)
    assert torch.allclose(estimate.to_canonical[1], own[4])
    # 150 degrees apart (a twin): every packet keeps the stack's frame refined on its slices.
    far = turned(own[4], 150.0)
    estimate = stack_pose.estimate_packet_poses(net, stack.image, stack.mask.data, far, packet_of)
    assert estimate.own.tolist() == [False, False]
    assert torch.equal(estimate.to_canonical, far.expand(2, 4, 4))
    allowed = stack_pose.estimate_packet_poses(
        net, stack.image, stack.mask.data, far, packet_of, max_apart_deg=180.0
    )
    assert allowed.own.tolist() == [False, True]
    with pytest.raises(ValueError, match="'packet_of'"):
        stack_pose.estimate_packet_poses(net, stack.image, stack.mask.data, near, packet_of[:-1])


def test_packet_poses_from_a_real_network_are_rigid() -> None:
    model_config, _ = _tiny_training()
    net = StackPoseNet(model_config)
    _, case = _still_case(3)
    stack = case.stacks[0]
    k = stack.image.shape[2]
    estimate = estimate_packet_poses(
        net,
        stack.image,
        stack.mask.data,
        torch.eye(4, dtype=torch.float64),
        torch.arange(k) % 3,
        iterations=1,
    )
    assert estimate.to_canonical.shape == (3, 4, 4)
    assert estimate.scores.shape == (3,)
    dets = torch.linalg.det(estimate.to_canonical[:, :3, :3])
    assert torch.allclose(dets, torch.ones(3, dtype=torch.float64))
    # A packet with no plane in the stack (cropped away) keeps the stack's frame, score NaN.
    frame = torch.eye(4, dtype=torch.float64)
    frame[:3, 3] = torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
    gap = estimate_packet_poses(
        net, stack.image, stack.mask.data, frame, torch.arange(k) % 3 * 2, iterations=1
    )
    assert gap.to_canonical.shape == (5, 4, 4)
    assert torch.equal(gap.to_canonical[1], frame) and torch.equal(gap.to_canonical[3], frame)
    assert bool(gap.scores[1].isnan()) and not bool(gap.scores[0].isnan())
    assert gap.own[1].item() is False


def test_loading_a_model_of_another_kind_fails_cleanly(tmp_path) -> None:
    save_checkpoint(tmp_path / "m", {"w": torch.zeros(2)}, {"architecture": "brain_unet"})
    with pytest.raises(CheckpointError, match="not a stack-pose model"):
        load_stack_pose_model(tmp_path / "m")
    save_checkpoint(
        tmp_path / "n",
        {"w": torch.zeros(2)},
        {"architecture": "stack_pose", "model": {"head": "x"}},
    )
    with pytest.raises(CheckpointError, match="bad 'model'"):
        load_stack_pose_model(tmp_path / "n")


def test_config_errors_name_the_field() -> None:
    with pytest.raises(ValueError, match="'head'"):
        StackPoseConfig(head="mlp")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'grid_size'"):
        StackPoseConfig(grid_size=20)
    with pytest.raises(ValueError, match="'steps'"):
        StackPoseTrainingConfig(steps=0)
    with pytest.raises(ValueError, match="'size'"):
        BlockGrid(size=True)  # type: ignore[arg-type]


def _one_age_atlas(tmp_path) -> Path:
    """An atlas folder of one synthetic brain (``atlas/GA30/srr.nii.gz`` + ``mask.nii.gz``)."""
    from svr.image import save_nifti

    image, mask = ellipsoid_brain(40, 2.0, (24.0, 30.0, 20.0), seed=4, origin_mm=(-39.0,) * 3)
    folder = tmp_path / "atlas" / "GA30"
    folder.mkdir(parents=True)
    save_nifti(image, folder / "srr.nii.gz")
    save_nifti(mask, folder / "mask.nii.gz")
    return folder


def _library_run(folder, model_config, training, init=None):
    """The library's training on one core (as the command trains), for comparison."""
    from svr.sampling.volume import load_canonical_volume

    volume = load_canonical_volume(folder / "srr.nii.gz", folder / "mask.nii.gz")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return train_stack_pose([volume], None, model_config, training, init=init)
    finally:
        torch.set_num_threads(threads)


def test_the_training_command_is_the_library_recipe(tmp_path) -> None:
    """The command trains what the library does: its defaults (the second phase as a new run,
    fine_tune_seed 2), --fine-tune-seed N and --no-fine-tune-seed (the warm restart)."""
    from svr.cli import main
    from svr.models.stack_pose import load_stack_pose_model

    folder = _one_age_atlas(tmp_path)
    threads = torch.get_num_threads()
    for name, options, training in (
        ("run", [], StackPoseTrainingConfig(steps=3, fine_tune_steps=1, checkpoint_every=1)),
        ("new-run", ["--fine-tune-seed", "5"],
         StackPoseTrainingConfig(steps=3, fine_tune_steps=1, fine_tune_seed=5)),
        ("warm", ["--no-fine-tune-seed"],
         StackPoseTrainingConfig(steps=3, fine_tune_steps=1, fine_tune_seed=None)),
    ):  # fmt: skip
        code = main(
            [
                "train-stack-pose", "--atlas-dir", str(tmp_path / "atlas"), "--output-dir",
                str(tmp_path / name), "--steps", "3", "--fine-tune-steps", "1", "--phantoms", "0",
                "--checkpoint-every", "1", "--width", "4", "--volume-downsample", "1", "--quiet",
                *options,
            ]
        )  # fmt: skip
        assert code == 0
        assert torch.get_num_threads() == threads  # trained on one, the caller's count restored
        trained = load_stack_pose_model(tmp_path / name)
        library = _library_run(folder, StackPoseConfig(width=4), training)
        for a, b in zip(trained.state_dict().values(), library.state_dict().values(), strict=True):
            assert torch.equal(a, b), name


def test_the_training_command_fine_tunes_and_trains_the_baselines(tmp_path, capsys) -> None:
    from svr.cli import main
    from svr.models.stack_pose import load_stack_pose_model

    folder = _one_age_atlas(tmp_path)
    common = [
        "--atlas-dir", str(tmp_path / "atlas"), "--steps", "2", "--fine-tune-steps", "0",
        "--phantoms", "0", "--checkpoint-every", "1", "--volume-downsample", "1", "--quiet",
    ]  # fmt: skip
    assert main(["train-stack-pose", "--output-dir", str(tmp_path / "a"), "--loss", "anchor",
                 "--width", "4", *common]) == 0  # fmt: skip
    baseline = load_stack_pose_model(tmp_path / "a")
    assert baseline.config.representation == "anchor_points"
    tune = [
        "train-stack-pose", "--output-dir", str(tmp_path / "ft"),
        "--init-from", str(tmp_path / "a"), "--learning-rate", "1e-4", "--seed", "1",
    ]  # fmt: skip
    assert main([*tune, *common]) == 0
    tuned = load_stack_pose_model(tmp_path / "ft")
    library = _library_run(
        folder,
        baseline.config,
        StackPoseTrainingConfig(
            steps=2, fine_tune_steps=0, checkpoint_every=1, learning_rate=1e-4, seed=1
        ),
        init=baseline.state_dict(),
    )
    for a, b in zip(tuned.state_dict().values(), library.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    assert not all(
        torch.equal(a, b)
        for a, b in zip(tuned.state_dict().values(), baseline.state_dict().values(), strict=True)
    )
    capsys.readouterr()
    # A network setting that contradicts the starting weights is refused in one line.
    code = main(["train-stack-pose", "--output-dir", str(tmp_path / "bad"), "--init-from",
                 str(tmp_path / "a"), "--loss", "se3", *common])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1
    assert "--loss se3 differs from the --init-from model's anchor_points" in err
    code = main(["train-stack-pose", "--output-dir", str(tmp_path / "bad3"), "--init-from",
                 str(tmp_path / "a"), "--no-hidden-norm", *common])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1
    assert "--no-hidden-norm differs from the --init-from model's network" in err
    # --no-hidden-norm: the network of the models trained before the option (the shipped one).
    assert main(["train-stack-pose", "--output-dir", str(tmp_path / "plain"), "--width", "4",
                 "--no-hidden-norm", *common]) == 0  # fmt: skip
    assert load_stack_pose_model(tmp_path / "plain").config.hidden_norm is False
    assert baseline.config.hidden_norm is True
    code = main(["train-stack-pose", "--output-dir", str(tmp_path / "bad2"), "--init-from",
                 str(tmp_path / "missing"), *common])  # fmt: skip
    assert code != 0 and "--init-from" in capsys.readouterr().err


def test_simulated_fetus_turns_between_stacks_within_the_range() -> None:
    volume = _volume()
    config = SimulationConfig(
        num_stacks=3, motion="none", in_plane_mm=3.0, thickness_mm=4.0, stack_turn_deg=(60.0, 90.0)
    )
    case = simulate_case(volume, config)
    still = simulate_case(
        volume, SimulationConfig(num_stacks=3, motion="none", in_plane_mm=3.0, thickness_mm=4.0)
    )
    assert torch.equal(case.stacks[0].true_poses, still.stacks[0].true_poses)
    for moved, fixed in zip(case.stacks[1:], still.stacks[1:], strict=True):
        relative = moved.atlas_poses[0, :3, :3] @ fixed.atlas_poses[0, :3, :3].T
        angle = math.degrees(math.acos((float(relative.trace()) - 1) / 2))
        assert 60.0 - 1e-6 <= angle <= 90.0 + 1e-6
    with pytest.raises(ValueError, match="'stack_turn_deg'"):
        SimulationConfig(stack_turn_deg=(90.0, 30.0))


def test_a_tiny_network_learns_a_known_rotation_of_a_synthetic_brain() -> None:
    # Blocks of one stack seen in frames turned by +-10 and +-20 degrees about z (and nothing
    # else): the network must learn to undo the turn from the image alone, through the SE(3) loss.
    torch.manual_seed(0)
    volume = _volume()
    case = simulate_case(
        volume,
        SimulationConfig(
            num_stacks=1, orientations="random", motion="none", in_plane_mm=3.0, noise=0.0, seed=8
        ),
    )
    stack = case.stacks[0]
    to_canonical = torch.eye(4, dtype=torch.float64)
    to_canonical[:3, 3] = -volume.centre_mm
    truth = stack_pose_from_slices(se3_compose(to_canonical[None], stack.atlas_poses), stack.image)
    true_frame = se3_compose(truth, se3_inverse(stack_frame(stack.image)))
    degrees = (20.0, -20.0, 10.0, -10.0)
    turns = torch.eye(4, dtype=torch.float64).repeat(len(degrees), 1, 1)
    for i, angle in enumerate(degrees):
        turns[i, :3, :3] = so3_exp(torch.tensor([0.0, 0.0, math.radians(angle)]).double())
    n = len(degrees)
    frames = se3_compose(turns, true_frame.expand(n, 4, 4))
    config = StackPoseConfig(width=4, grid_size=16, grid_spacing_mm=6.0)
    blocks = block_inputs(stack.image, stack.mask.data, frames, config.grid)
    starts = se3_compose(frames, stack_frame(stack.image).expand(n, 4, 4))
    targets = truth.expand(n, 4, 4)
    net = StackPoseNet(config)
    optimiser = torch.optim.Adam(net.parameters(), lr=3e-3)
    training = StackPoseTrainingConfig()
    for _ in range(150):
        loss, _parts = stack_pose_loss(net(blocks), starts, targets, torch.ones(n), training)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    net.eval()
    with torch.no_grad():
        residual = net(blocks).residual
    refined = se3_compose(residual.double(), starts)
    for pose in refined:
        angle = math.degrees(
            float(Rotation.from_matrix((pose[:3, :3].T @ truth[:3, :3]).numpy()).magnitude())
        )
        assert angle < 5.0  # from 20 degrees


def test_stack_pose_from_slices_undoes_each_slice_offset_under_motion() -> None:
    # Slices that turned about the stack's own centre line by angles symmetric in their offset:
    # the stack pose is the unturned one, whatever the offsets (each slice's own offset undone).
    image, _ = ellipsoid_brain(16, 2.0, (8.0, 8.0, 8.0), seed=1)
    stack = Image(image.data[:, :, :9].contiguous(), image.affine.clone())
    local = se3_compose(se3_inverse(stack_frame(stack))[None], stack_slice_poses(stack))
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3], pose[:3, 3] = _rotation(3), torch.tensor([4.0, -2.0, 7.0], dtype=torch.float64)
    offsets = torch.arange(9, dtype=torch.float64) - 4
    turns = torch.eye(4, dtype=torch.float64).repeat(9, 1, 1)
    turns[:, :3, :3] = so3_exp(
        torch.stack([0.05 * offsets, torch.zeros(9), torch.zeros(9)], -1).double()
    )
    # slice k sits at the stack pose, turned about the frame's origin, then moved to its offset
    slices = se3_compose(se3_compose(pose[None], turns), local)
    found = stack_pose_from_slices(slices, stack)
    assert torch.allclose(found, pose, atol=1e-6)


def _two_pose_stack():
    """A 9-slice stack whose slices 0-3 sit at one pose and 4-8 at another (20 deg apart)."""
    image, _ = ellipsoid_brain(16, 2.0, (8.0, 8.0, 8.0), seed=1)
    stack = Image(image.data[:, :, :9].contiguous(), image.affine.clone())
    local = se3_compose(se3_inverse(stack_frame(stack))[None], stack_slice_poses(stack))
    first, second = torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    first[:3, :3], first[:3, 3] = _rotation(3), torch.tensor([4.0, -2.0, 7.0], dtype=torch.float64)
    turn = torch.from_numpy(Rotation.from_rotvec([0.0, math.radians(20.0), 0.0]).as_matrix())
    second[:3, :3], second[:3, 3] = turn @ first[:3, :3], first[:3, 3] + 3.0
    poses = torch.stack([first] * 4 + [second] * 5)
    return stack, se3_compose(poses, local), first, second


def test_stack_pose_from_slices_of_the_present_slices_only() -> None:
    stack, slices, first, second = _two_pose_stack()
    present = torch.zeros(9, dtype=torch.bool)
    present[:4] = True
    assert torch.allclose(stack_pose_from_slices(slices, stack, present), first, atol=1e-6)
    assert torch.allclose(stack_pose_from_slices(slices, stack, ~present), second, atol=1e-6)
    # All of them: the geodesic median, nearer the five than the four.
    both = stack_pose_from_slices(slices, stack)
    assert torch.equal(both, stack_pose_from_slices(slices, stack, torch.ones(9, dtype=torch.bool)))
    angle = Rotation.from_matrix((both[:3, :3].T @ second[:3, :3]).numpy()).magnitude()
    assert math.degrees(angle) < 10.0
    with pytest.raises(ValueError, match="'present' must be \\(9,\\) bool"):
        stack_pose_from_slices(slices, stack, present[:5])
    with pytest.raises(ValueError, match="'present' must be"):
        stack_pose_from_slices(slices, stack, present.long())
    with pytest.raises(ValueError, match="selects no slice"):
        stack_pose_from_slices(slices, stack, torch.zeros(9, dtype=torch.bool))


def test_packet_index_follows_the_sweeps() -> None:
    # Interleave 2: slices 0, 2, 4, 6, 8 acquired first, then 1, 3, 5, 7.
    found = packet_index(torch.tensor([0, 5, 1, 6, 2, 7, 3, 8, 4]))
    assert found.tolist() == [0, 1, 0, 1, 0, 1, 0, 1, 0]
    # Interleave 3, odd then even counts, and one sweep.
    assert packet_index(torch.tensor([0, 3, 5, 1, 4, 6, 2])).tolist() == [0, 1, 2, 0, 1, 2, 0]
    assert packet_index(torch.arange(5)).tolist() == [0] * 5


def test_the_shipped_model_loads_and_estimates() -> None:
    from svr.models.pretrained import MAX_MODEL_BYTES, stack_pose_model_path

    folder = stack_pose_model_path()
    assert sum(f.stat().st_size for f in folder.iterdir()) <= MAX_MODEL_BYTES
    assert (folder / "README.md").is_file()
    model = load_stack_pose_model(STACK_POSE_MODEL)
    assert not model.training
    volume = _volume()
    case = simulate_case(
        volume,
        SimulationConfig(num_stacks=1, orientations="random", motion="none", in_plane_mm=2.0),
    )
    estimate = estimate_stack_pose(model, case.stacks[0].image, case.stacks[0].mask.data)
    assert estimate.method == "learned"
    assert torch.isfinite(estimate.pose).all()


def test_training_phantoms_never_use_the_benchmarks_phantom() -> None:
    from svr.cli.stack_pose_brains import phantom_sources

    assert phantom_sources(0) == []
    for count in (1, 2, 5):
        sources = phantom_sources(count)
        assert len(sources) == count
        assert sorted(seed for _, seed in sources) == list(range(1, count + 1))
        assert all(22.0 <= weeks <= 36.0 for weeks, _ in sources)


def test_the_training_command_adds_phantoms(tmp_path) -> None:
    from svr.cli import main
    from svr.models.checkpoint import latest_checkpoint, load_checkpoint

    _one_age_atlas(tmp_path)
    code = main(
        [
            "train-stack-pose", "--atlas-dir", str(tmp_path / "atlas"), "--output-dir",
            str(tmp_path / "run"), "--steps", "2", "--fine-tune-steps", "1", "--width", "4",
            "--phantoms", "1", "--quiet",
        ]
    )  # fmt: skip
    assert code == 0
    config = load_checkpoint(latest_checkpoint(tmp_path / "run")).config
    assert config["data"]["phantoms"] == [{"weeks": 29.0, "seed": 1}]
    assert config["train"]["fine_tune_steps"] == 1


def test_the_training_command_names_a_second_phase_longer_than_the_run(tmp_path, capsys) -> None:
    from svr.cli import main

    _one_age_atlas(tmp_path)
    code = main(
        [
            "train-stack-pose", "--atlas-dir", str(tmp_path / "atlas"), "--output-dir",
            str(tmp_path / "run"), "--steps", "200", "--phantoms", "0", "--quiet",
        ]
    )  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1
    assert "--fine-tune-steps must be < steps (200; 0 for one phase), got 9000" in err
    with pytest.raises(ValueError, match="'fine_tune_steps'"):
        StackPoseTrainingConfig(steps=10, fine_tune_steps=10)
    with pytest.raises(ValueError, match="'fine_tune_learning_rate'"):
        StackPoseTrainingConfig(fine_tune_learning_rate=0.0)


def test_the_learning_rate_restarts_for_the_second_phase() -> None:
    from svr.models.resume import cosine_schedule

    def rates(**kwargs) -> list[float]:
        optimiser = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
        schedule = cosine_schedule(optimiser, 10, **kwargs)
        out = []
        for _ in range(10):
            out.append(optimiser.param_groups[0]["lr"])
            optimiser.step()
            schedule.step()
        return out

    one = rates()
    assert one[0] == pytest.approx(1.0) and one[5] == pytest.approx(0.525)
    two = rates(restart_at=6, restart_scale=0.3)
    # First phase: the cosine from 1 to 0.05 over 6 steps; second: from 0.3 to 0.015 over 4.
    for s in range(6):
        assert two[s] == pytest.approx(0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * s / 6)))
    for s in range(6, 10):
        expected = 0.3 * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * (s - 6) / 4)))
        assert two[s] == pytest.approx(expected)
    assert two[6] == pytest.approx(0.3)
    for bad in (0, 10, 2.5):
        with pytest.raises(ValueError, match="'restart_at'"):
            rates(restart_at=bad)
    with pytest.raises(ValueError, match="'restart_scale'"):
        rates(restart_at=5, restart_scale=0.0)


def test_the_fine_tune_brains_join_for_the_second_phase_only(monkeypatch) -> None:
    import svr.models.stack_pose_batches as batches
    import svr.models.stack_pose_train as module

    model_config, training = _tiny_training()
    training = dataclasses.replace(
        training,
        steps=5,
        fine_tune_steps=2,
        checkpoint_every=5,
        fine_tune_learning_rate=6e-4,
        fine_tune_seed=None,  # the warm restart's rate
    )
    volume, phantom = _volume(), _volume()
    seen: list[int] = []
    simulate = module.simulate_batch

    def counting(volumes, *args):
        seen.append(len(volumes))
        assert volumes[0] is volume
        return simulate(volumes, *args)

    restarts = []
    schedule = module.cosine_schedule

    def recording(optimiser, steps, **kwargs):
        restarts.append((steps, kwargs))
        return schedule(optimiser, steps, **kwargs)

    monkeypatch.setattr(module, "simulate_batch", counting)
    monkeypatch.setattr(batches, "simulate_batch", counting)
    monkeypatch.setattr(module, "cosine_schedule", recording)
    train_stack_pose([volume], None, model_config, training, fine_tune_volumes=[phantom])
    assert seen == [1, 1, 1, 2, 2]
    assert restarts == [(5, {"restart_at": 3, "restart_scale": pytest.approx(0.2)})]
    # One phase: the fine-tune brains are there from the first step.
    seen.clear()
    one = dataclasses.replace(training, fine_tune_steps=0)
    train_stack_pose([volume], None, model_config, one, fine_tune_volumes=[phantom])
    assert seen == [2] * 5 and restarts[-1][1]["restart_at"] is None
    # Worker processes see the same phases.
    phases = (([volume], None), ([volume, phantom], None))
    dataset = batches.StepBatches(phases, 3, None, model_config, training)
    seen.clear()
    dataset[2], dataset[3]
    assert seen == [1, 2]


def test_brains_are_drawn_by_their_weights(monkeypatch) -> None:
    import svr.models.stack_pose_batches as module

    model_config, training = _tiny_training()
    volumes = [_volume(), _volume()]
    drawn: list[int] = []

    def fake_stack(volume, *args):
        drawn.append(next(i for i, v in enumerate(volumes) if v is volume))
        return None

    def fake_samples(stack, *args):
        return torch.zeros(1), torch.eye(4)[None], torch.eye(4), torch.ones(1)

    monkeypatch.setattr(module, "simulate_training_stack", fake_stack)
    monkeypatch.setattr(module, "draw_samples", fake_samples)
    many = dataclasses.replace(training, stacks_per_step=4000)
    simulate_batch(volumes, None, model_config, many, torch.Generator().manual_seed(0))
    assert sum(drawn) / len(drawn) == pytest.approx(0.5, abs=0.03)  # alike
    # Without weights, the draws are the uniform integers they always were.
    expected = torch.randint(2, (4000,), generator=torch.Generator().manual_seed(0))
    assert drawn == expected.tolist()
    for weights, share in (([1.0, 3.0], 0.75), ([4.0, 1.0], 0.2), ([1.0, 0.0], 0.0)):
        drawn.clear()
        simulate_batch(
            volumes,
            None,
            model_config,
            many,
            torch.Generator().manual_seed(1),
            torch.tensor(weights, dtype=torch.float64),
        )
        assert sum(drawn) / len(drawn) == pytest.approx(share, abs=0.03), weights


def test_the_training_weights_follow_the_phases(monkeypatch) -> None:
    import svr.models.stack_pose_train as module

    model_config, training = _tiny_training()
    training = dataclasses.replace(training, steps=4, fine_tune_steps=2, checkpoint_every=4)
    a, b, c = _volume(), _volume(), _volume()
    seen: list[tuple[int, list[float] | None]] = []
    simulate = module.simulate_batch

    def recording(volumes, trajectories, model, config, generator, weights=None):
        seen.append((len(volumes), None if weights is None else weights.tolist()))
        return simulate(volumes, trajectories, model, config, generator, weights)

    monkeypatch.setattr(module, "simulate_batch", recording)
    train_stack_pose([a, b], None, model_config, training, fine_tune_volumes=[c])
    assert seen == [(2, None)] * 2 + [(3, None)] * 2  # alike: no weights
    seen.clear()
    train_stack_pose(
        [a, b], None, model_config, training, fine_tune_volumes=[c], fine_tune_weights=[2.5]
    )
    assert seen == [(2, [1.0, 1.0])] * 2 + [(3, [1.0, 1.0, 2.5])] * 2
    seen.clear()
    one = dataclasses.replace(training, fine_tune_steps=0)
    train_stack_pose(
        [a, b], None, model_config, one, fine_tune_volumes=[c], volume_weights=[1.0, 0.5]
    )
    assert seen == [(3, [1.0, 0.5, 1.0])] * 4
    for name, weights, volumes in (
        ("volume_weights", [1.0], [a, b]),
        ("volume_weights", [1.0, 0.0], [a, b]),
        ("volume_weights", [1.0, float("nan")], [a, b]),
        ("fine_tune_weights", [1.0, 1.0], [c]),
    ):
        kwargs = {name: weights}
        with pytest.raises(ValueError, match=f"'{name}' must be {len(volumes)} numbers > 0"):
            train_stack_pose([a, b], None, model_config, training, fine_tune_volumes=[c], **kwargs)


def test_the_training_command_adds_anatomy_variants(tmp_path, capsys, monkeypatch) -> None:
    from svr.cli import main
    from svr.image import Image, load_nifti, save_nifti
    from svr.models.checkpoint import latest_checkpoint, load_checkpoint
    from svr.models.stack_pose import load_stack_pose_model
    from svr.sampling.anatomy import anatomy_variant
    from svr.sampling.volume import canonicalize, load_canonical_volume

    folder = _one_age_atlas(tmp_path)
    command = [
        "train-stack-pose", "--atlas-dir", str(tmp_path / "atlas"), "--output-dir",
        str(tmp_path / "run"), "--steps", "2", "--fine-tune-steps", "0", "--width", "4",
        "--phantoms", "0", "--anatomy-variants", "1", "--volume-downsample", "1", "--quiet",
    ]  # fmt: skip
    # Without the tissue labels: one line naming the missing file.
    assert main(command) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "parcellation.nii.gz is missing" in err
    volume, mask = load_nifti(folder / "srr.nii.gz"), load_nifti(folder / "mask.nii.gz")
    # Labels on another grid: one line naming the file.
    save_nifti(Image(torch.ones(3, 3, 3), volume.affine), folder / "parcellation.nii.gz")
    assert main(command) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "parcellation.nii.gz: anatomy_variant(): 'labels'" in err
    labels = (mask.data > 0.5).float() + (volume.data > volume.data[mask.data > 0.5].median())
    save_nifti(Image(labels, volume.affine), folder / "parcellation.nii.gz", overwrite=True)
    assert main(command) == 0
    config = load_checkpoint(latest_checkpoint(tmp_path / "run")).config
    assert config["data"]["anatomy_variants"] == 1
    # The command trains on the brain and its variant (seed 0), as the library does.
    brain = mask.data > 0.5
    variant = canonicalize(
        anatomy_variant(volume, brain, labels, seed=0), Image(brain.float(), volume.affine)
    )
    original = load_canonical_volume(folder / "srr.nii.gz", folder / "mask.nii.gz")

    def assert_library_run(run: str, volumes, steps: int, fine_tune_steps: int, **kwargs) -> None:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            library = train_stack_pose(
                volumes,
                None,
                StackPoseConfig(width=4),
                StackPoseTrainingConfig(steps=steps, fine_tune_steps=fine_tune_steps),
                **kwargs,
            )
        finally:
            torch.set_num_threads(threads)
        trained = load_stack_pose_model(tmp_path / run).state_dict().values()
        for a, b in zip(trained, library.state_dict().values(), strict=True):
            assert torch.equal(a, b)

    assert_library_run("run", [original, variant], 2, 0)
    # --variants-phase second: the variant joins for the second phase only, as the phantoms do.
    second = [
        *command[:4], str(tmp_path / "second"), "--steps", "3", "--fine-tune-steps", "1",
        *command[9:], "--variants-phase", "second",
    ]  # fmt: skip
    assert main(second) == 0
    assert (
        load_checkpoint(latest_checkpoint(tmp_path / "second")).config["data"]["variants_phase"]
        == "second"
    )
    assert_library_run("second", [original], 3, 1, fine_tune_volumes=[variant])
    # --variants-weight: the variant drawn at that weight, relative to the atlas brain.
    weighted = [
        *second[:4], str(tmp_path / "weighted"), *second[5:], "--variants-weight", "0.25",
    ]  # fmt: skip
    assert main(weighted) == 0
    data = load_checkpoint(latest_checkpoint(tmp_path / "weighted")).config["data"]
    assert (data["variants_weight"], data["phantoms_weight"]) == (0.25, 1.0)
    assert_library_run(
        "weighted",
        [original],
        3,
        1,
        fine_tune_volumes=[variant],
        volume_weights=[1.0],
        fine_tune_weights=[0.25],
    )
    # Each brain's weight beside it, in either phase, with the phantoms'.
    import svr.models.stack_pose_train as module

    calls = []
    monkeypatch.setattr(module, "train_stack_pose", lambda *args, **kwargs: calls.append(kwargs))
    options = ["--variants-weight", "0.5", "--phantoms-weight", "3", "--phantoms", "2"]
    assert main([*command[:4], str(tmp_path / "w1"), *command[5:], *options]) == 0
    assert main([*second[:4], str(tmp_path / "w2"), *second[5:], *options]) == 0
    assert [(c["volume_weights"], c["fine_tune_weights"]) for c in calls] == [
        ([1.0, 0.5], [3.0, 3.0]),
        ([1.0], [0.5, 3.0, 3.0]),
    ]
    assert [len(c["fine_tune_volumes"]) for c in calls] == [2, 3]


def test_a_second_phase_run_as_a_new_run_is_the_two_command_recipe(tmp_path) -> None:
    """fine_tune_seed: one run of 5 steps (2 in the second phase) ends bit for bit where a 3-step
    run and a 2-step fine-tuning run of its weights (seed 7, the second phase's rate) end, and
    resumed from the turn; worker processes seed the second phase as that run's steps."""
    model_config, training = _tiny_training()
    first = dataclasses.replace(training, steps=3, checkpoint_every=3)
    volume, phantom = _volume(), _volume(semi_axes=(26.0, 36.0, 22.0))

    def values(net) -> list[torch.Tensor]:
        return list(net.state_dict().values())

    def same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
        return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))

    one_run = dataclasses.replace(
        training, steps=5, fine_tune_steps=2, fine_tune_learning_rate=1e-3, fine_tune_seed=7
    )
    second = dataclasses.replace(training, steps=2, learning_rate=1e-3, seed=7, checkpoint_every=2)
    weights = train_stack_pose([volume], None, model_config, first)
    two = train_stack_pose([volume, phantom], None, model_config, second, init=weights.state_dict())
    one = values(
        train_stack_pose([volume], None, model_config, one_run, fine_tune_volumes=[phantom])
    )
    assert same(one, values(two))
    # Worker processes: the second phase's steps are seeded as the second run's 0, 1, ...
    from svr.models.stack_pose_batches import StepBatches

    dataset = StepBatches(
        (([volume], None), ([volume, phantom], None)), 3, None, model_config, one_run
    )
    for step, seed, index, brains in ((1, 0, 1, [volume]), (4, 7, 1, [volume, phantom])):
        generator = torch.Generator().manual_seed(step_seed(seed, index))
        expected = simulate_batch(brains, None, model_config, one_run, generator)
        assert all(torch.equal(a, b) for a, b in zip(dataset[step], expected, strict=True))
    # Without the seed the second phase continues the stream and the moments: another network.
    warm = dataclasses.replace(one_run, fine_tune_seed=None)
    assert not same(
        values(train_stack_pose([volume], None, model_config, warm, fine_tune_volumes=[phantom])),
        one,
    )
    # Stopped at the turn (checkpoint 3), resumed: the same network.
    resumable = dataclasses.replace(one_run, checkpoint_every=3)
    folder = tmp_path / "run"
    train_stack_pose(
        [volume], None, model_config, resumable, folder=folder, fine_tune_volumes=[phantom]
    )
    shutil.rmtree(folder / "step_000000005")
    resumed = train_stack_pose(
        [volume], None, model_config, resumable, folder=folder, fine_tune_volumes=[phantom]
    )
    assert same(values(resumed), one)
    with pytest.raises(ValueError, match="'fine_tune_seed'"):
        StackPoseTrainingConfig(fine_tune_seed=1.5)  # type: ignore[arg-type]


def _labelled_volume(semi_axes=(30.0, 40.0, 24.0)):
    """The test brain with three nested tissue labels (for synthesis)."""
    image, mask = ellipsoid_brain(48, 2.0, semi_axes, seed=1, origin_mm=(-47.0, -47.0, -47.0))
    grid = (torch.from_numpy(np.indices((48, 48, 48))).double() - 23.5) * 2.0
    radius = sum((g / a) ** 2 for g, a in zip(grid, semi_axes, strict=True)).sqrt()
    labels = 1.0 + (radius > 0.5).double() + (radius > 0.8).double()
    from svr.image import Image

    return canonicalize(image, mask, labels=Image(labels.float(), image.affine))


def test_synthetic_brains_train_deterministically_and_resume(tmp_path) -> None:
    """With synthesis a share of the stacks comes from synthetic copies of the labelled brains:
    the run is a function of its seed, resumes exactly and differs from the run without."""
    from svr.models.stack_pose_batches import training_brain
    from svr.sampling.synthesis import SynthesisConfig

    model_config, training = _tiny_training()
    plain = dataclasses.replace(training, steps=3, checkpoint_every=3)
    synthetic = dataclasses.replace(
        plain, synthesis=SynthesisConfig(mode="labels"), synthesis_fraction=1.0
    )
    volume = _labelled_volume()

    def values(config, **kwargs) -> list[torch.Tensor]:
        net = train_stack_pose([volume], None, model_config, config, **kwargs)
        return list(net.state_dict().values())

    def same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
        return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))

    one = values(synthetic)
    assert same(values(synthetic), one)
    assert not same(values(plain), one)
    # Without synthesis nothing more is drawn: the labels change nothing.
    unlabelled = dataclasses.replace(volume, labels=None)
    assert same(
        list(train_stack_pose([unlabelled], None, model_config, plain).state_dict().values()),
        values(plain),
    )
    # Stopped after the first step and resumed: the run straight through.
    resumable = dataclasses.replace(synthetic, checkpoint_every=1)
    values(resumable, folder=tmp_path / "run", time_limit_s=0.0)
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["step_000000001"]
    assert same(values(resumable, folder=tmp_path / "run"), one)
    # Which brain a stack comes from: a synthetic copy (same mask and labels, another image),
    # the brain itself without labels or without synthesis (and then nothing is drawn).
    generator = torch.Generator().manual_seed(3)
    copy = training_brain(volume, synthetic, generator)
    assert copy is not volume and copy.mask is volume.mask and copy.labels is volume.labels
    assert not torch.equal(copy.image.data, volume.image.data)
    assert training_brain(unlabelled, synthetic, generator) is unlabelled
    state = generator.get_state()
    assert training_brain(volume, plain, generator) is volume
    assert torch.equal(generator.get_state(), state)
    none = dataclasses.replace(synthetic, synthesis_fraction=0.0)
    assert training_brain(volume, none, generator) is volume
    for name, value in (("synthesis", "labels"), ("synthesis_fraction", 1.5)):
        with pytest.raises(ValueError, match=f"'{name}'"):
            StackPoseTrainingConfig(**{name: value})


def test_the_training_command_takes_several_atlas_folders_and_synthesis(tmp_path, capsys) -> None:
    from svr.cli import main
    from svr.image import Image, load_nifti, save_nifti
    from svr.models.checkpoint import latest_checkpoint, load_checkpoint
    from svr.models.stack_pose import load_stack_pose_model
    from svr.sampling.synthesis import SynthesisConfig
    from svr.sampling.volume import load_canonical_volume

    first = _one_age_atlas(tmp_path)
    second = tmp_path / "other" / "GA31"
    shutil.copytree(first, second)
    shutil.copytree(first, tmp_path / "other" / "GA24")
    command = [
        "train-stack-pose", "--atlas-dir", str(tmp_path / "atlas"), str(tmp_path / "other"),
        "--hold-out", "24", "--output-dir", str(tmp_path / "run"), "--steps", "2",
        "--fine-tune-steps", "0", "--width", "4", "--phantoms", "0", "--volume-downsample", "1",
        "--quiet", "--synthesis", "labels", "--synthesis-fraction", "1",
    ]  # fmt: skip
    # Without the tissue labels: one line naming the missing file.
    assert main(command) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--synthesis:" in err and "parcellation.nii.gz" in err
    for folder in (first, second, tmp_path / "other" / "GA24"):
        mask = load_nifti(folder / "mask.nii.gz")
        labels = Image((mask.data > 0.5).float() * 2, mask.affine)
        save_nifti(labels, folder / "parcellation.nii.gz")
    assert main(command) == 0
    config = load_checkpoint(latest_checkpoint(tmp_path / "run")).config
    assert config["data"]["atlas_dirs"] == [str(tmp_path / "atlas"), str(tmp_path / "other")]
    assert config["data"]["volumes"] == [str(first / "srr.nii.gz"), str(second / "srr.nii.gz")]
    assert config["data"]["synthesis"] == "labels"
    assert config["train"]["synthesis"]["mode"] == "labels"
    assert config["train"]["synthesis_fraction"] == 1.0
    # The command trains what the library does on both folders' brains (GA 24 held out).
    brains = [
        load_canonical_volume(
            f / "srr.nii.gz", f / "mask.nii.gz", labels_path=f / "parcellation.nii.gz"
        )
        for f in (first, second)
    ]
    training = StackPoseTrainingConfig(
        steps=2,
        fine_tune_steps=0,
        synthesis=SynthesisConfig(mode="labels"),
        synthesis_fraction=1.0,
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        library = train_stack_pose(brains, None, StackPoseConfig(width=4), training)
    finally:
        torch.set_num_threads(threads)
    trained = load_stack_pose_model(tmp_path / "run").state_dict().values()
    for a, b in zip(trained, library.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    code = main([*command[:-4], "--synthesis", "labels", "--synthesis-fraction", "2",
                 "--output-dir", str(tmp_path / "bad")])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "--synthesis-fraction" in err
