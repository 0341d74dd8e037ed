"""Tests of the pose representations in :mod:`svr.geometry.conversions`.

Oracles: scipy rotations and NumPy float64 re-implementations of the definitions (anchor points
``P = R p + t`` of the plane template, first two matrix columns, Gram-Schmidt).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import np_gram_schmidt
from scipy.spatial.transform import Rotation

import svr.geometry as g

PI = math.pi
F32, F64 = torch.float32, torch.float64
TOL64 = 1e-12


def T(x: np.ndarray, dtype: torch.dtype = F64) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float64)).to(dtype)


def N(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().to(F64).numpy()


def random_poses(gen: np.random.Generator, shape: tuple[int, ...], max_angle: float = PI):
    axes = gen.normal(size=(*shape, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    r = axes * gen.uniform(0.0, max_angle, size=(*shape, 1))
    return np.concatenate([r, gen.normal(size=(*shape, 3)) * 30], axis=-1)


def sp(rotvec: np.ndarray) -> Rotation:
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64).reshape(-1, 3))


def matrices(rotvec: np.ndarray) -> np.ndarray:
    return sp(rotvec).as_matrix().reshape(*rotvec.shape[:-1], 3, 3)


def rotation_angle_between(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    return np.linalg.norm((sp(r_a).inv() * sp(r_b)).as_rotvec(), axis=-1)


def np_anchor_points(pose: np.ndarray, a: float) -> np.ndarray:
    template = np.array([[-a, -a, 0.0], [0.0, 0.0, 0.0], [a, -a, 0.0]])
    m = matrices(pose[..., :3])
    pts = np.einsum("...ij,kj->...ki", m, template) + pose[..., None, 3:]
    return pts.reshape(*pose.shape[:-1], 9)


# Rotation angles that stress the conversions (at pi the axis sign is arbitrary).
ADVERSARIAL_ANGLES = [0.0, 1e-12, 1e-6, PI / 2, PI - 1e-6, PI - 1e-9]


def adversarial_poses(angles: list[float] = ADVERSARIAL_ANGLES) -> np.ndarray:
    axes = np.concatenate([np.eye(3), -np.eye(3), [[0.6, 0.0, -0.8], [0.36, 0.48, 0.8]]])
    r = (np.asarray(angles)[:, None, None] * axes[None]).reshape(-1, 3)
    t = np.random.default_rng(99).normal(size=r.shape) * 30
    return np.concatenate([r, t], axis=-1)


# ------------------------------------------------------------------------------------------------
# Quaternion + translation
# ------------------------------------------------------------------------------------------------


def test_pose_to_quat_translation_matches_scipy():
    pose = random_poses(np.random.default_rng(0), (4, 5), 4 * PI)
    got = N(g.pose_to_quat_translation(T(pose)))
    assert got.shape == (4, 5, 7)
    want_q = sp(pose[..., :3]).as_quat(scalar_first=True, canonical=True).reshape(4, 5, 4)
    np.testing.assert_allclose(got[..., :4], want_q, rtol=0, atol=TOL64)
    np.testing.assert_array_equal(got[..., 4:], pose[..., 3:])
    assert (got[..., 0] >= 0).all()


def test_quat_translation_to_pose_matches_scipy_for_unnormalised_and_negated_quaternions():
    gen = np.random.default_rng(1)
    q = gen.normal(size=(4, 5, 4))
    t = gen.normal(size=(4, 5, 3)) * 30
    want_r = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_rotvec().reshape(4, 5, 3)
    for quat in (q, -q, 7.0 * q):
        got = N(g.quat_translation_to_pose(T(np.concatenate([quat, t], axis=-1))))
        np.testing.assert_allclose(got[..., :3], want_r, rtol=0, atol=TOL64)
        np.testing.assert_array_equal(got[..., 3:], t)


def test_quat_translation_round_trip():
    pose = np.concatenate([random_poses(np.random.default_rng(2), (40,)), adversarial_poses()])
    back = N(g.quat_translation_to_pose(g.pose_to_quat_translation(T(pose))))
    np.testing.assert_allclose(back, pose, rtol=0, atol=TOL64)


def test_quat_translation_round_trip_regularises_large_rotations():
    pose = random_poses(np.random.default_rng(3), (40,), 4 * PI)
    back = N(g.quat_translation_to_pose(g.pose_to_quat_translation(T(pose))))
    assert (np.linalg.norm(back[:, :3], axis=-1) <= PI + 1e-15).all()
    np.testing.assert_allclose(matrices(back[:, :3]), matrices(pose[:, :3]), atol=TOL64)
    np.testing.assert_array_equal(back[:, 3:], pose[:, 3:])


# ------------------------------------------------------------------------------------------------
# Anchor points
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("half_size", [None, 10.0, 60.0, 0.5])
def test_pose_to_anchor_points_matches_definition(half_size):
    pose = random_poses(np.random.default_rng(4), (4, 5), 4 * PI)
    if half_size is None:
        got, a = g.pose_to_anchor_points(T(pose)), g.ANCHOR_HALF_SIZE_MM
    else:
        got, a = g.pose_to_anchor_points(T(pose), half_size_mm=half_size), half_size
    assert got.shape == (4, 5, 9)
    np.testing.assert_allclose(N(got), np_anchor_points(pose, a), rtol=0, atol=1e-11)
    # P2 is the translation (the slice centre)
    np.testing.assert_allclose(N(got)[..., 3:6], pose[..., 3:], rtol=0, atol=1e-12)


def test_anchor_default_half_size_is_60_mm():
    assert g.ANCHOR_HALF_SIZE_MM == 60.0
    pose = np.array([0.0, 0.0, 0.0, 1.0, 2.0, 3.0])
    want = [-59.0, -58.0, 3.0, 1.0, 2.0, 3.0, 61.0, -58.0, 3.0]
    np.testing.assert_allclose(N(g.pose_to_anchor_points(T(pose))), want, atol=0)


@pytest.mark.parametrize("half_size", [60.0, 10.0])
def test_anchor_points_round_trip(half_size):
    pose = np.concatenate(
        [random_poses(np.random.default_rng(5), (4, 10)).reshape(-1, 6), adversarial_poses()]
    )
    points = g.pose_to_anchor_points(T(pose), half_size)
    back = N(g.anchor_points_to_pose(points, half_size))
    np.testing.assert_allclose(back, pose, rtol=0, atol=1e-11)
    # from NumPy-made points too
    back_np = N(g.anchor_points_to_pose(T(np_anchor_points(pose, half_size)), half_size))
    np.testing.assert_allclose(back_np, pose, rtol=0, atol=1e-11)


def test_anchor_points_round_trip_at_pi_same_rotation():
    pose = adversarial_poses([PI])
    back = N(g.anchor_points_to_pose(g.pose_to_anchor_points(T(pose))))
    np.testing.assert_allclose(matrices(back[:, :3]), matrices(pose[:, :3]), atol=1e-12)
    np.testing.assert_allclose(back[:, 3:], pose[:, 3:], atol=1e-11)


def test_anchor_half_size_only_shifts_translation():
    pose = random_poses(np.random.default_rng(6), (20,))
    points = g.pose_to_anchor_points(T(pose), 60.0)
    wrong = N(g.anchor_points_to_pose(points, 30.0))
    np.testing.assert_allclose(wrong[:, :3], pose[:, :3], atol=1e-12)
    # t = centroid - R c(a) with template centroid c(a) = (0, -2a/3, 0): wrong a shifts t by
    # R (0, 2 (a_wrong - a_true) / 3, 0) = R (0, -20, 0) mm
    shift = np.einsum("nij,j->ni", matrices(pose[:, :3]), [0.0, -20.0, 0.0])
    np.testing.assert_allclose(wrong[:, 3:], pose[:, 3:] + shift, atol=1e-11)


def np_kabsch(points: np.ndarray, a: float) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid fit (Kabsch/SVD) of the plane template to (n, 9) points."""
    template = np.array([[-a, -a, 0.0], [0.0, 0.0, 0.0], [a, -a, 0.0]])
    p = points.reshape(-1, 3, 3)
    pc, tc = p.mean(1), template.mean(0)
    h = np.einsum("ki,nkj->nij", template - tc, p - pc[:, None])
    u, _, vt = np.linalg.svd(h)
    v, ut = np.swapaxes(vt, 1, 2), np.swapaxes(u, 1, 2)
    d = np.ones((len(p), 3))
    d[:, 2] = np.sign(np.linalg.det(v @ ut))
    r = v @ (d[:, :, None] * ut)
    return r, pc - np.einsum("nij,j->ni", r, tc)


@pytest.mark.parametrize("sigma", [0.01, 0.5])
def test_anchor_points_with_noise_recover_a_close_pose(sigma):
    gen = np.random.default_rng(7)
    n, a = 400, 60.0
    pose = random_poses(gen, (n,))
    noisy = np_anchor_points(pose, a) + gen.normal(size=(n, 9)) * sigma
    back = N(g.anchor_points_to_pose(T(noisy), a))
    angle = rotation_angle_between(back[:, :3], pose[:, :3])
    trans = np.linalg.norm(back[:, 3:] - pose[:, 3:], axis=-1)
    # Rotation error O(sigma / a), translation error O(sigma). Measured: angle max 4.0, median 1.33
    # (x sigma / a); translation max 3.6, median 1.2 (x sigma).
    assert angle.max() <= 6.0 * sigma / a and np.median(angle) <= 2.0 * sigma / a
    assert trans.max() <= 5.0 * sigma and np.median(trans) <= 1.8 * sigma
    # Nearly as good as the least-squares fit (measured mean angle 1.42 vs 1.38 sigma / a).
    r_k, t_k = np_kabsch(noisy, a)
    angle_k = np.linalg.norm(
        (Rotation.from_matrix(r_k).inv() * sp(pose[:, :3])).as_rotvec(), axis=-1
    )
    assert angle.mean() <= 1.15 * angle_k.mean()
    assert trans.mean() <= 1.15 * np.linalg.norm(t_k - pose[:, 3:], axis=-1).mean()


def test_anchor_points_to_pose_follows_documented_estimator_on_noisy_points():
    # Docstring: u = P3 - P1, v = P2 - (P1 + P3) / 2, Gram-Schmidt keeping u; t = centroid of the
    # points minus R times the template centroid (0, -2a/3, 0).
    gen = np.random.default_rng(15)
    a = 45.0
    noisy = np_anchor_points(random_poses(gen, (30,)), a) + gen.normal(size=(30, 9)) * 2.0
    p1, p2, p3 = noisy[:, :3], noisy[:, 3:6], noisy[:, 6:]
    r = np_gram_schmidt(np.concatenate([p3 - p1, p2 - 0.5 * (p1 + p3)], axis=-1))
    t = noisy.reshape(30, 3, 3).mean(1) - np.einsum("nij,j->ni", r, [0.0, -2 * a / 3, 0.0])
    got = N(g.anchor_points_to_pose(T(noisy), a))
    np.testing.assert_allclose(matrices(got[:, :3]), r, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[:, 3:], t, rtol=0, atol=1e-11)


def test_kabsch_oracle_recovers_exact_poses():
    pose = random_poses(np.random.default_rng(14), (10,))
    r_k, t_k = np_kabsch(np_anchor_points(pose, 60.0), 60.0)
    np.testing.assert_allclose(r_k, matrices(pose[:, :3]), atol=1e-12)
    np.testing.assert_allclose(t_k, pose[:, 3:], atol=1e-11)


def test_anchor_points_to_pose_returns_a_valid_rotation_for_scaled_points():
    # Uniformly scaled points (a network that gets the size wrong): rotation still exact.
    pose = random_poses(np.random.default_rng(8), (20,))
    points = np_anchor_points(pose, 60.0)
    centre = points[:, 3:6]
    scaled = (points.reshape(20, 3, 3) - centre[:, None]) * 1.3 + centre[:, None]
    back = N(g.anchor_points_to_pose(T(scaled.reshape(20, 9)), 60.0))
    np.testing.assert_allclose(matrices(back[:, :3]), matrices(pose[:, :3]), atol=1e-12)


# ------------------------------------------------------------------------------------------------
# 6D rotation + translation
# ------------------------------------------------------------------------------------------------


def test_pose_to_rotation6d_translation_matches_matrix_columns():
    pose = random_poses(np.random.default_rng(9), (4, 5), 4 * PI)
    got = N(g.pose_to_rotation_6d_translation(T(pose)))
    assert got.shape == (4, 5, 9)
    m = matrices(pose[..., :3])
    want = np.concatenate([m[..., :, 0], m[..., :, 1], pose[..., 3:]], axis=-1)
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL64)


def test_rotation6d_translation_to_pose_matches_gram_schmidt_and_scipy():
    gen = np.random.default_rng(10)
    d6t = np.concatenate([gen.normal(size=(4, 5, 6)) * 2, gen.normal(size=(4, 5, 3))], axis=-1)
    got = N(g.rotation_6d_translation_to_pose(T(d6t)))
    m = np_gram_schmidt(d6t[..., :6])
    want_r = Rotation.from_matrix(m.reshape(-1, 3, 3)).as_rotvec().reshape(4, 5, 3)
    np.testing.assert_allclose(got[..., :3], want_r, rtol=0, atol=TOL64)
    np.testing.assert_array_equal(got[..., 3:], d6t[..., 6:])


def test_rotation6d_translation_round_trip():
    pose = np.concatenate([random_poses(np.random.default_rng(11), (40,)), adversarial_poses()])
    back = N(g.rotation_6d_translation_to_pose(g.pose_to_rotation_6d_translation(T(pose))))
    np.testing.assert_allclose(back, pose, rtol=0, atol=TOL64)


# ------------------------------------------------------------------------------------------------
# Shared properties: dtype, gradients, hypothesis round trips
# ------------------------------------------------------------------------------------------------

FORWARD: dict[str, Callable] = {
    "quat": g.pose_to_quat_translation,
    "anchor": g.pose_to_anchor_points,
    "6d": g.pose_to_rotation_6d_translation,
}
BACKWARD: dict[str, Callable] = {
    "quat": g.quat_translation_to_pose,
    "anchor": g.anchor_points_to_pose,
    "6d": g.rotation_6d_translation_to_pose,
}


@pytest.mark.parametrize("rep", list(FORWARD))
@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
def test_dtype_preserved_and_float32_round_trip(rep, dtype):
    pose = random_poses(np.random.default_rng(12), (50,), PI - 1e-2)
    x = T(pose, dtype)
    enc = FORWARD[rep](x)
    back = BACKWARD[rep](enc)
    assert enc.dtype == dtype and back.dtype == dtype
    tol = 1e-12 if dtype == F64 else 1e-4  # float32: |t| ~ 30 mm, anchors ~ 60 mm
    np.testing.assert_allclose(N(back), N(x), rtol=0, atol=tol)


@pytest.mark.parametrize("rep", list(FORWARD))
@pytest.mark.parametrize("theta", [0.0, 1e-8, 1.3, PI - 1e-4])
def test_gradcheck(rep, theta):
    axes = np.array([[0.36, 0.48, 0.8], [-0.6, 0.0, 0.8]])
    pose = np.concatenate([axes * theta, [[1.0, -2.0, 3.0], [0.0, 4.0, -1.0]]], axis=-1)
    x = T(pose).requires_grad_(True)
    assert torch.autograd.gradcheck(FORWARD[rep], (x,))
    enc = FORWARD[rep](T(pose)).detach().requires_grad_(True)
    assert torch.autograd.gradcheck(BACKWARD[rep], (enc,))


@pytest.mark.parametrize("rep", list(FORWARD))
@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("theta", [0.0, PI - 1e-9, PI])
def test_gradients_finite(rep, dtype, theta):
    pose = np.array([[0.36 * theta, 0.48 * theta, 0.8 * theta, 1.0, 2.0, 3.0]])
    x = T(pose, dtype).requires_grad_(True)
    enc = FORWARD[rep](x)
    enc2 = enc.detach().clone().requires_grad_(True)
    back = BACKWARD[rep](enc2)
    w = torch.linspace(-1, 1, enc.shape[-1], dtype=dtype)
    (enc * w).sum().backward()
    (back * torch.linspace(-1, 1, 6, dtype=dtype)).sum().backward()
    for t in (enc, back, x.grad, enc2.grad):
        assert torch.isfinite(t).all()


HYP = settings(max_examples=60, deadline=None, derandomize=True, database=None)
_coord = st.floats(-1.0, 1.0, allow_nan=False)
_axis = st.tuples(_coord, _coord, _coord).filter(lambda v: sum(c * c for c in v) > 1e-2)
_pose_st = st.builds(
    lambda ax, th, t: np.concatenate([np.asarray(ax) / np.linalg.norm(ax) * th, t]),
    _axis,
    st.floats(0.0, PI - 1e-6),
    st.tuples(*[st.floats(-200.0, 200.0, allow_nan=False)] * 3),
)


@HYP
@given(pose=_pose_st, rep=st.sampled_from(list(FORWARD)))
def test_property_round_trips(pose, rep):
    back = N(BACKWARD[rep](FORWARD[rep](T(pose))))
    np.testing.assert_allclose(back, pose, rtol=0, atol=1e-10)


@HYP
@given(pose=_pose_st, half_size=st.floats(1.0, 200.0))
def test_property_anchor_points_are_rigid(pose, half_size):
    pts = N(g.pose_to_anchor_points(T(pose), half_size)).reshape(3, 3)
    a = half_size
    # distances of the template triangle (-a,-a), (0,0), (a,-a) are preserved
    np.testing.assert_allclose(np.linalg.norm(pts[2] - pts[0]), 2 * a, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pts[1] - pts[0]), math.sqrt(2) * a, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pts[2] - pts[1]), math.sqrt(2) * a, rtol=1e-12)
    # and the orientation: (P3 - P1) x (P2 - P1) is along the slice normal R e_z
    normal = np.cross(pts[2] - pts[0], pts[1] - pts[0])
    r_z = matrices(pose[:3])[:, 2]
    np.testing.assert_allclose(normal / np.linalg.norm(normal), r_z, atol=1e-9)


# ------------------------------------------------------------------------------------------------
# Argument checks
# ------------------------------------------------------------------------------------------------

ARG_CASES = [
    ("pose_to_quat_translation", "pose", 6),
    ("quat_translation_to_pose", "qt", 7),
    ("pose_to_anchor_points", "pose", 6),
    ("anchor_points_to_pose", "points", 9),
    ("pose_to_rotation_6d_translation", "pose", 6),
    ("rotation_6d_translation_to_pose", "d6t", 9),
]


@pytest.mark.parametrize("case", ARG_CASES, ids=[c[0] for c in ARG_CASES])
def test_bad_arguments(case):
    func, arg, size = case
    fn = getattr(g, func)
    fn(torch.ones(2, size, dtype=F64))  # well-formed
    for bad in [(2, size + 1), (size - 1,), ()]:
        msg = f"{func}(): '{arg}' must have shape (..., {size}), got {bad}"
        with pytest.raises(ValueError, match=re.escape(msg)):
            fn(torch.ones(bad, dtype=F64))
    for bad_value in [torch.ones(size, dtype=torch.int64), np.ones(size), [1.0] * size]:
        with pytest.raises(TypeError, match=re.escape(f"{func}(): '{arg}' must be")):
            fn(bad_value)


@pytest.mark.parametrize("half_size", [0.0, -1.0, -60.0, float("nan")])
@pytest.mark.parametrize("func", ["pose_to_anchor_points", "anchor_points_to_pose"])
def test_anchor_half_size_must_be_positive(func, half_size):
    size = 6 if func == "pose_to_anchor_points" else 9
    msg = f"{func}(): 'half_size_mm' must be > 0"
    with pytest.raises(ValueError, match=re.escape(msg)):
        getattr(g, func)(torch.ones(size, dtype=F64), half_size)
    with pytest.raises(ValueError, match=re.escape(msg)):
        getattr(g, func)(torch.ones(size, dtype=F64), half_size_mm=half_size)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    pose = T(random_poses(np.random.default_rng(13), (32,)))
    for rep in FORWARD:
        enc_cpu = FORWARD[rep](pose)
        enc_gpu = FORWARD[rep](pose.cuda())
        assert enc_gpu.device.type == "cuda"
        torch.testing.assert_close(enc_gpu.cpu(), enc_cpu, atol=1e-12, rtol=1e-12)
        back_gpu = BACKWARD[rep](enc_gpu)
        torch.testing.assert_close(back_gpu.cpu(), BACKWARD[rep](enc_cpu), atol=1e-12, rtol=1e-12)
