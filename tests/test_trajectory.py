"""Slice poses as one smooth motion per interleaved packet (svr.reconstruction.trajectory)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from svr.errors import ConfigFieldError
from svr.reconstruction import trajectory
from svr.reconstruction.slices import SliceSet
from svr.reconstruction.trajectory import (
    SMOOTHNESS_GRID,
    TrajectoryConfig,
    cross_validated_trajectory,
    fit_slice_trajectory,
    fit_trajectory,
    packet_times,
)

F64 = torch.float64
SPACING_MM = 3.0
# The smoothing spline (order 2) for the smooth motions of these tests; the default (order 1, a
# random walk) is measured on the severe random-walk motion of benchmarks/bench_trajectory.py.
SMOOTH = TrajectoryConfig(penalty_order=2, smoothness=10.0)


def nominal_poses(
    n: int, stack_rotvec: tuple[float, float, float] = (0.3, -0.2, 0.1)
) -> np.ndarray:
    """(n, 4, 4) slice poses of a stack without motion: slice k at z = k * spacing."""
    R = Rotation.from_rotvec(stack_rotvec).as_matrix()
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = R
    z = (np.arange(n) - (n - 1) / 2) * SPACING_MM
    out[:, :3, 3] = np.array([4.0, -2.0, 7.0]) + z[:, None] * R[:, 2]
    return out


def smooth_motion(time: np.ndarray, span: float) -> np.ndarray:
    """(n, 4, 4) head motions: a turn about a fixed axis growing smoothly to 40 deg, a drift."""
    s = time / span
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    angle = np.radians(40.0) * (3 * s**2 - 2 * s**3)
    out = np.tile(np.eye(4), (len(time), 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(axis * angle[:, None]).as_matrix()
    out[:, :3, 3] = np.stack([6 * np.sin(np.pi * s), 3 * s, -4 * s**2], axis=1)
    return out


def perturbed(poses: np.ndarray, rng: np.random.Generator, deg: float, mm: float) -> np.ndarray:
    """Each pose turned by ``deg`` about a random axis through the slice centre, shifted ``mm``."""
    n = len(poses)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    shift = rng.normal(size=(n, 3))
    shift /= np.linalg.norm(shift, axis=1, keepdims=True)
    out = poses.copy()
    out[:, :3, :3] = poses[:, :3, :3] @ Rotation.from_rotvec(axis * np.radians(deg)).as_matrix()
    out[:, :3, 3] += mm * shift
    return out


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Oracle: (n,) rotation angles between the rotation parts (scipy)."""
    rel = np.swapaxes(a[:, :3, :3], 1, 2) @ b[:, :3, :3]
    return np.degrees(Rotation.from_matrix(rel).magnitude())


def shift_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)


def one_packet(n: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth ``M(t) o N`` of a packet of n slices, its nominal poses and times 0..n-1."""
    time = np.arange(n, dtype=float)
    nominal = nominal_poses(n)
    return smooth_motion(time, n - 1) @ nominal, nominal, time


def fit(poses, nominal, time, config=SMOOTH, packet=None, known=None):
    n = len(poses)
    return fit_trajectory(
        torch.from_numpy(poses),
        torch.zeros(n, dtype=torch.int64) if packet is None else torch.from_numpy(packet),
        torch.from_numpy(time),
        config,
        known=None if known is None else torch.from_numpy(known),
        nominal=None if nominal is None else torch.from_numpy(nominal),
    )


def slice_set(poses: np.ndarray, nominal: np.ndarray, stack_ids, ks) -> SliceSet:
    """A SliceSet with 1 x 1 dummy images (only the poses and the bookkeeping matter)."""
    n = len(poses)
    return SliceSet(
        images=torch.zeros(n, 1, 1),
        masks=torch.ones(n, 1, 1, dtype=torch.bool),
        spacing_mm=torch.ones(n, 2, dtype=F64),
        thickness_mm=torch.full((n,), SPACING_MM, dtype=F64),
        poses=torch.from_numpy(poses),
        frame="scanner",
        stack_ids=torch.as_tensor(stack_ids, dtype=torch.int64),
        slice_indices=torch.as_tensor(ks, dtype=torch.int64),
        plane_offsets_mm=torch.zeros(n, 2, dtype=F64),
        scanner_poses=torch.from_numpy(nominal),
        stack_names=tuple(f"s{i}" for i in range(int(max(stack_ids)) + 1)),
    )


@pytest.mark.parametrize(
    ("config", "gain"), [(SMOOTH, 0.6), (TrajectoryConfig(), 0.95)], ids=["smooth", "default"]
)
def test_recovers_a_smooth_motion_from_noisy_poses(config, gain):
    truth, nominal, time = one_packet()
    rng = np.random.default_rng(3)
    noisy = perturbed(truth, rng, deg=6.0, mm=1.5)
    result = fit(noisy, nominal, time, config)
    out = result.poses.numpy()
    before, after = angle_deg(noisy, truth), angle_deg(out, truth)
    assert np.median(after) < gain * np.median(before)
    assert np.median(shift_mm(out, truth)) < gain * np.median(shift_mm(noisy, truth))
    assert not result.outlier.any()
    # The residuals are the oracle's angles and distances between input and fit.
    np.testing.assert_allclose(result.residual_deg.numpy(), angle_deg(out, noisy), atol=1e-6)
    np.testing.assert_allclose(result.residual_mm.numpy(), shift_mm(out, noisy), atol=1e-9)


def test_recovers_the_motion_without_nominal_poses():
    truth, _, time = one_packet()
    noisy = perturbed(truth, np.random.default_rng(4), deg=6.0, mm=1.5)
    out = fit(noisy, None, time).poses.numpy()
    assert np.median(angle_deg(out, truth)) < 0.6 * 6.0


def test_planted_outliers_are_flagged_and_do_not_bend_the_fit():
    truth, nominal, time = one_packet()
    rng = np.random.default_rng(5)
    noisy = perturbed(truth, rng, deg=1.0, mm=0.3)
    planted = np.array([7, 15, 22])
    for index, deg in zip(planted, (30.0, 45.0, 60.0), strict=True):
        noisy[index] = perturbed(noisy[index : index + 1], rng, deg=deg, mm=0.0)[0]
    result = fit(noisy, nominal, time)
    assert np.flatnonzero(result.outlier.numpy()).tolist() == planted.tolist()
    assert (result.weights.numpy()[planted] == 0).all()
    out = result.poses.numpy()
    neighbours = np.concatenate([planted - 1, planted + 1])
    assert angle_deg(out, truth)[neighbours].max() < 1.0
    assert angle_deg(out, truth)[planted].max() < 1.0  # the outliers sit on the trajectory
    assert result.residual_deg.numpy()[planted].min() > 25.0


def test_unknown_slices_get_the_trajectory_at_their_time():
    truth, nominal, time = one_packet()
    noisy = perturbed(truth, np.random.default_rng(6), deg=1.0, mm=0.3)
    unknown = np.array([4, 5, 13, 21])
    noisy[unknown] = np.eye(4)  # no estimate: any pose
    known = np.ones(len(truth), dtype=bool)
    known[unknown] = False
    result = fit(noisy, nominal, time, known=known)
    out = result.poses.numpy()
    assert angle_deg(out, truth)[unknown].max() < 1.0
    assert shift_mm(out, truth)[unknown].max() < 0.5
    assert torch.isnan(result.residual_deg[unknown]).all()
    assert torch.isnan(result.residual_mm[unknown]).all()
    assert not result.outlier[unknown].any()
    assert (result.weights[unknown] == 0).all()
    assert int(result.known_slices[0]) == len(truth) - len(unknown)


def two_stacks(n: int = 24) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Truth and nominal poses of two stacks of n slices, 2 interleaved packets each."""
    ks = np.arange(n)
    order = np.r_[ks[0::2], ks[1::2]]  # acquisition: even k, then odd k
    t = np.argsort(order).astype(float)  # each slice's time in its stack
    truth, nominal = [], []
    for rotvec, phase in (((0.3, -0.2, 0.1), 0.0), ((1.2, 0.4, -0.5), 0.5)):
        N = nominal_poses(n, rotvec)
        nominal.append(N)
        truth.append(smooth_motion(t + phase * n, 2 * n - 1) @ N)
    stack_ids = np.repeat([0, 1], n)
    return np.concatenate(truth), np.concatenate(nominal), stack_ids, np.tile(ks, 2)


def test_packet_times_follow_the_interleaving():
    truth, nominal, stack_ids, ks = two_stacks(7)
    packet, time = packet_times(slice_set(truth, nominal, stack_ids, ks), 2)
    assert packet.tolist() == [0, 1, 0, 1, 0, 1, 0, 2, 3, 2, 3, 2, 3, 2]
    assert time.dtype == F64
    assert time.tolist() == [0, 0, 1, 1, 2, 2, 3] * 2
    given = torch.linspace(0, 1, 14, dtype=torch.float32)
    assert packet_times(slice_set(truth, nominal, stack_ids, ks), 2, given)[1].dtype == F64
    with pytest.raises(ValueError, match="'times'"):
        packet_times(slice_set(truth, nominal, stack_ids, ks), 2, given[:5])
    with pytest.raises(ValueError, match="'packets'"):
        packet_times(slice_set(truth, nominal, stack_ids, ks), 0)


def test_packets_are_fitted_independently():
    truth, nominal, stack_ids, ks = two_stacks()
    noisy = perturbed(truth, np.random.default_rng(7), deg=2.0, mm=0.5)
    clean = fit_slice_trajectory(slice_set(noisy, nominal, stack_ids, ks), 2, SMOOTH)
    spoilt = noisy.copy()
    spoilt[4] = perturbed(spoilt[4:5], np.random.default_rng(8), deg=60.0, mm=10.0)[0]  # packet 0
    result = fit_slice_trajectory(slice_set(spoilt, nominal, stack_ids, ks), 2, SMOOTH)
    assert result.packets.tolist() == [0, 1, 2, 3]
    assert result.fitted.all()
    assert np.flatnonzero(result.outlier.numpy()).tolist() == [4]
    other = result.packet_index != 0
    torch.testing.assert_close(result.poses[other], clean.poses[other], rtol=0, atol=1e-12)
    # Each packet alone gives the same fit as all together.
    alone = stack_ids == 1
    single = fit_slice_trajectory(
        slice_set(noisy[alone], nominal[alone], stack_ids[alone] * 0, ks[alone]), 2, SMOOTH
    )
    torch.testing.assert_close(single.poses, clean.poses[alone], rtol=0, atol=1e-9)
    assert np.median(angle_deg(result.poses.numpy(), truth)) < 2.0


def test_packets_with_too_few_known_slices_fall_back():
    truth, nominal, stack_ids, ks = two_stacks(12)
    packet = (stack_ids * 2 + ks % 2).astype(np.int64)
    time = (ks // 2).astype(float)
    known = np.ones(len(truth), dtype=bool)
    known[(packet == 1) & (ks > 3)] = False  # packet 1: 2 known slices, fewer than min_slices
    known[packet == 2] = False  # packet 2: none known
    result = fit(truth, nominal, time, TrajectoryConfig(), packet=packet, known=known)
    assert result.fitted.tolist() == [True, False, False, True]
    assert result.known_slices.tolist() == [6, 2, 0, 6]
    out, kept = result.poses.numpy(), (packet == 1) & known
    np.testing.assert_allclose(out[kept], truth[kept], atol=1e-12)
    assert (result.residual_deg.numpy()[kept] == 0).all()
    np.testing.assert_allclose(out[packet == 2], truth[packet == 2], atol=0)
    torch.testing.assert_close(result.references[2], torch.eye(4, dtype=F64))
    # The unknown slices of packet 1 take the known ones' mean motion at their nominal places.
    mean = result.references[1].numpy()
    G = trajectory.robust_mean_pose(torch.from_numpy(nominal[packet == 1])).numpy()
    expected = mean @ np.linalg.inv(G) @ nominal[(packet == 1) & ~known]
    np.testing.assert_allclose(out[(packet == 1) & ~known], expected, atol=1e-9)
    assert not result.outlier[(packet == 1) | (packet == 2)].any()


@pytest.mark.parametrize(
    ("config", "with_nominal"),
    [(TrajectoryConfig(), True), (SMOOTH, True), (SMOOTH, False)],
    ids=["default", "order2", "order2-no-nominal"],
)
def test_no_motion_returns_the_inputs(config, with_nominal):
    _, nominal, stack_ids, ks = two_stacks()
    for motion in (np.eye(4), smooth_motion(np.array([5.0]), 10.0)[0]):  # none, a constant one
        poses = motion @ nominal
        s = slice_set(poses, nominal if with_nominal else np.tile(np.eye(4), (len(ks), 1, 1)),
                      stack_ids, ks)  # fmt: skip
        packet, time = packet_times(s, 2)
        result = fit_trajectory(
            s.poses, packet, time, config, nominal=s.scanner_poses if with_nominal else None
        )
        np.testing.assert_allclose(result.poses.numpy(), poses, atol=1e-9)
        assert float(result.residual_deg.max()) < 1e-6
        assert not result.outlier.any()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("knot_spacing", 0.0),
        ("smoothness", -1.0),
        ("smoothness", math.nan),
        ("outlier_deg", 0.0),
        ("outlier_deg", 200.0),
        ("outlier_mm", -1.0),
        ("irls_iterations", -1),
        ("irls_iterations", 2.5),
        ("min_slices", 1),
        ("penalty_order", 3),
        ("penalty_order", True),
    ],
)
def test_bad_config_values_are_named(field, value):
    with pytest.raises(ConfigFieldError, match=f"TrajectoryConfig: '{field}'") as info:
        TrajectoryConfig(**{field: value})
    assert info.value.field == field


def test_bad_arguments_are_named():
    truth, _, time = one_packet(8)
    poses, t = torch.from_numpy(truth), torch.from_numpy(time)
    packet = torch.zeros(8, dtype=torch.int64)
    cases = [
        ("poses", dict(poses=poses[:, :3])),
        ("packet", dict(packet=packet[:5])),
        ("packet", dict(packet=packet.double())),
        ("time", dict(time=t[:, None])),
        ("time", dict(time=t.clone().fill_(math.inf))),
        ("known", dict(known=torch.ones(8))),
        ("nominal", dict(nominal=poses[:4])),
        ("poses", dict(poses=poses.clone().fill_(math.nan))),
    ]
    for name, change in cases:
        args = {"poses": poses, "packet": packet, "time": t, **change}
        with pytest.raises(ValueError, match=f"'{name}'"):
            fit_trajectory(**args)


def test_float64_cpu_and_batched_over_packets(monkeypatch):
    truth, nominal, stack_ids, ks = two_stacks()
    s = slice_set(truth, nominal, stack_ids, ks)
    result = fit_slice_trajectory(s.with_poses(s.poses.float()), 2)  # float32 poses are read too
    for name in ("poses", "residual_deg", "residual_mm", "weights", "references"):
        assert getattr(result, name).dtype == F64
        assert getattr(result, name).device.type == "cpu"
    assert result.outlier.dtype == torch.bool
    assert tuple(result.poses.shape) == (len(ks), 4, 4)

    # One linear solve per IRLS step and two robust means, however many packets.
    calls = {"solve": 0, "mean": 0}
    solve, mean = torch.linalg.solve, trajectory.robust_mean_pose

    def counting_solve(*args, **kwargs):
        calls["solve"] += 1
        return solve(*args, **kwargs)

    def counting_mean(*args, **kwargs):
        calls["mean"] += 1
        return mean(*args, **kwargs)

    monkeypatch.setattr(torch.linalg, "solve", counting_solve)
    monkeypatch.setattr(trajectory, "robust_mean_pose", counting_mean)
    config = TrajectoryConfig(irls_iterations=4)
    many = fit_slice_trajectory(s, 6, config)  # 12 packets
    assert len(many.packets) == 12
    assert calls == {"solve": config.irls_iterations + 1, "mean": 2}


def random_walk(n: int, rng: np.random.Generator, step_deg: float, step_mm: float) -> np.ndarray:
    """(n, 4, 4) head motions of a random walk: each slice's turn ``step_deg`` from the last."""
    out = np.tile(np.eye(4), (n, 1, 1))
    for i in range(1, n):
        axis = rng.normal(size=3)
        step = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(step_deg))
        out[i, :3, :3] = step.as_matrix() @ out[i - 1, :3, :3]
        out[i, :3, 3] = out[i - 1, :3, 3] + step_mm * rng.normal(size=3) / np.sqrt(3)
    return out


def packets_of(motion_of, n: int = 40) -> tuple[np.ndarray, SliceSet]:
    """Truth of two stacks of n slices (2 packets each) moved per packet by ``motion_of(m)``."""
    _, nominal, stack_ids, ks = two_stacks(n)
    truth = nominal.copy()
    for stack in (0, 1):
        for packet in (0, 1):
            rows = np.flatnonzero((stack_ids == stack) & (ks % 2 == packet))
            truth[rows] = motion_of(len(rows)) @ nominal[rows]
    return truth, slice_set(truth, nominal, stack_ids, ks)


def test_cross_validation_averages_a_calm_head_more_than_a_moving_one():
    rng = np.random.default_rng(5)
    # A calm head: every packet still, the estimates scattered by 6 deg / 1.5 mm.
    truth, slices = packets_of(lambda m: np.tile(np.eye(4), (m, 1, 1)))
    noisy = slices.with_poses(torch.from_numpy(perturbed(truth, rng, deg=6.0, mm=1.5)))
    fit, calm, errors = cross_validated_trajectory(noisy, 2)
    assert calm >= 1.0 and errors.shape == (len(SMOOTHNESS_GRID),)
    assert calm == SMOOTHNESS_GRID[int(errors.argmin())]
    after = np.median(angle_deg(fit.poses.numpy(), truth))
    assert after < 0.5 * np.median(angle_deg(noisy.poses.numpy(), truth))
    # A head that turns 8 deg from one slice to the next, estimated within 0.5 deg: a less stiff
    # trajectory, although not the least stiff (predicting a left-out slice of a random walk
    # favours some smoothing: 2.9 deg from the truth here, 0.6 at the grid's least smoothness).
    truth, slices = packets_of(lambda m: random_walk(m, rng, 8.0, 1.0))
    close = slices.with_poses(torch.from_numpy(perturbed(truth, rng, deg=0.5, mm=0.1)))
    fit, moving, _ = cross_validated_trajectory(close, 2)
    assert moving < calm
    stiff = fit_slice_trajectory(close, 2, TrajectoryConfig(smoothness=SMOOTHNESS_GRID[-1]))
    followed = np.median(angle_deg(fit.poses.numpy(), truth))
    assert followed < 0.6 * np.median(angle_deg(stiff.poses.numpy(), truth))


def test_cross_validation_of_one_value_is_the_fit_at_that_value():
    truth, slices = packets_of(lambda m: np.tile(np.eye(4), (m, 1, 1)))
    noisy = slices.with_poses(
        torch.from_numpy(perturbed(truth, np.random.default_rng(1), 4.0, 1.0))
    )
    fit, smoothness, errors = cross_validated_trajectory(noisy, 2, grid=(0.3,))
    assert smoothness == 0.3 and errors.shape == (1,) and float(errors[0]) > 0
    expected = fit_slice_trajectory(noisy, 2, TrajectoryConfig(smoothness=0.3))
    torch.testing.assert_close(fit.poses, expected.poses, rtol=0, atol=0)
    with pytest.raises(ValueError, match="'grid' must hold at least one value"):
        cross_validated_trajectory(noisy, 2, grid=())
