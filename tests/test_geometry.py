"""Tests of :mod:`svr.geometry` (SO(3) and SE(3)) against independent oracles.

Oracles: ``scipy.spatial.transform.Rotation`` (scalar-first, canonical quaternions),
``scipy.linalg.expm`` / ``logm`` of 4x4 twist matrices, the Van Loan block exponential for the left
Jacobian, closed forms, and NumPy float64 re-implementations of the textbook formulas. The library
is never checked only against itself.
"""

from __future__ import annotations

import inspect
import math
import re
import warnings
from collections.abc import Callable

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import np_gram_schmidt
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation

import svr.geometry as g

PI = math.pi
F32, F64 = torch.float32, torch.float64
TOL64 = 1e-12

TAIT_BRYAN = ["xyz", "xzy", "yxz", "yzx", "zxy", "zyx"]
ALL_CONVENTIONS = TAIT_BRYAN + [c.upper() for c in TAIT_BRYAN]

# Rotation angles that stress the formulas; the first group stays within [0, pi].
ANGLES_TO_PI = [0.0, 1e-12, 1e-6, 1e-3, 1.0, PI / 2, 2.5, PI - 1e-6, PI - 1e-9, PI]
ANGLES_BEYOND_PI = [PI + 1e-9, 2 * PI - 1e-6, 2 * PI, 2 * PI + 1e-3, 3 * PI, 4 * PI - 1e-9, 4 * PI]


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_axes(gen: np.random.Generator, n: int) -> np.ndarray:
    return _unit(gen.normal(size=(n, 3)))


# Coordinate axes of both signs (every Shepperd pivot), diagonals and a few random axes.
AXES = np.concatenate(
    [
        np.eye(3),
        -np.eye(3),
        _unit([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0], [-1.0, 2.0, -3.0], [0.0, -1.0, 1e-3]]),
        random_axes(np.random.default_rng(1234), 6),
    ]
)


def rotvecs_at(angles: list[float] | np.ndarray, axes: np.ndarray = AXES) -> np.ndarray:
    """(len(angles), len(axes), 3) rotation vectors ``axis * angle``."""
    return np.asarray(angles, dtype=np.float64)[:, None, None] * axes[None]


def rotvecs_up_to_4pi(seed: int) -> list[np.ndarray]:
    """Random rotation vectors with |r| up to 4 pi, then angles up to pi and beyond pi."""
    return [
        random_rotvecs(np.random.default_rng(seed), (4, 5), 4 * PI),
        rotvecs_at(ANGLES_TO_PI),
        rotvecs_at(ANGLES_BEYOND_PI),
    ]


def T(x: np.ndarray | float, dtype: torch.dtype = F64) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float64)).to(dtype)


def N(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().to(F64).numpy()


def sp(rotvec: np.ndarray) -> Rotation:
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64).reshape(-1, 3))


def sp_matrix(rotvec: np.ndarray) -> np.ndarray:
    rotvec = np.asarray(rotvec, dtype=np.float64)
    return sp(rotvec).as_matrix().reshape(*rotvec.shape[:-1], 3, 3)


def sp_quat(rot: Rotation, shape: tuple[int, ...]) -> np.ndarray:
    return rot.as_quat(scalar_first=True, canonical=True).reshape(*shape, 4)


def sp_rotvec_of_matrix(m: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(m.reshape(-1, 3, 3)).as_rotvec().reshape(*m.shape[:-2], 3)


def sp_euler(m: np.ndarray, convention: str) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # scipy's gimbal-lock warning
        return (
            Rotation.from_matrix(m.reshape(-1, 3, 3)).as_euler(convention).reshape(*m.shape[:-2], 3)
        )


def np_hat(w: np.ndarray) -> np.ndarray:
    w = np.asarray(w, dtype=np.float64)
    o = np.zeros_like(w[..., 0])
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    return np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(*w.shape[:-1], 3, 3)


def np_left_jacobian(w: np.ndarray) -> np.ndarray:
    """J_l(w) = sum_k [w]x^k / (k+1)!, the top-right block of expm([[[w]x, I], [0, 0]])."""
    block = np.zeros((6, 6))
    block[:3, :3] = np_hat(w)
    block[:3, 3:] = np.eye(3)
    return expm(block)[:3, 3:]


def twist_matrix(x: np.ndarray) -> np.ndarray:
    m = np.zeros((4, 4))
    m[:3, :3] = np_hat(x[:3])
    m[:3, 3] = x[3:]
    return m


def pose_matrix(pose: np.ndarray) -> np.ndarray:
    """4x4 matrices of (..., 6) pose vectors, built with scipy."""
    pose = np.asarray(pose, dtype=np.float64)
    m = np.zeros((*pose.shape[:-1], 4, 4))
    m[..., :3, :3] = sp_matrix(pose[..., :3])
    m[..., :3, 3] = pose[..., 3:]
    m[..., 3, 3] = 1.0
    return m


def oracle_se3_error(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(rotvec(R_p^T R_t), R_p^T (t_t - t_p)) in float64 with scipy."""
    pred, target = (
        np.array(x)
        for x in np.broadcast_arrays(np.asarray(pred, np.float64), np.asarray(target, np.float64))
    )
    shape = pred.shape[:-1]
    rp, rt = sp(pred[..., :3]), sp(target[..., :3])
    e_rot = (rp.inv() * rt).as_rotvec()
    dt = (target[..., 3:] - pred[..., 3:]).reshape(-1, 3)
    e_t = np.einsum("nji,nj->ni", rp.as_matrix(), dt)
    return np.concatenate([e_rot, e_t], axis=-1).reshape(*shape, 6)


def rotvec_distance(got: np.ndarray, want: np.ndarray, pi_band: float = 1e-12) -> np.ndarray:
    """|got - want|; where |want| is within ``pi_band`` of pi, ``-want`` is accepted as well."""
    got, want = np.broadcast_arrays(got, want)
    d = np.linalg.norm(got - want, axis=-1)
    flip = np.linalg.norm(got + want, axis=-1)
    near_pi = np.abs(np.linalg.norm(want, axis=-1) - PI) <= pi_band
    return np.where(near_pi, np.minimum(d, flip), d)


def quat_distance(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """|got - want|, also accepting ``-want`` where ``w`` is (numerically) zero."""
    d = np.linalg.norm(got - want, axis=-1)
    flip = np.linalg.norm(got + want, axis=-1)
    return np.where(np.abs(want[..., 0]) < 1e-12, np.minimum(d, flip), d)


def angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Difference of angles modulo 2 pi, in [-pi, pi)."""
    return (a - b + PI) % (2 * PI) - PI


def random_rotvecs(gen: np.random.Generator, shape: tuple[int, ...], max_angle: float):
    axes = random_axes(gen, math.prod(shape)).reshape(*shape, 3)
    return axes * gen.uniform(0.0, max_angle, size=(*shape, 1))


# ------------------------------------------------------------------------------------------------
# 1. Agreement with scipy / closed forms in float64
# ------------------------------------------------------------------------------------------------


def test_so3_exp_matches_scipy_batched():
    r = random_rotvecs(np.random.default_rng(0), (4, 5), 4 * PI)
    out = g.so3_exp(T(r))
    assert out.shape == (4, 5, 3, 3) and out.dtype == F64
    np.testing.assert_allclose(N(out), sp_matrix(r), rtol=0, atol=TOL64)


@pytest.mark.parametrize("angles", [ANGLES_TO_PI, ANGLES_BEYOND_PI], ids=["to_pi", "beyond_pi"])
def test_so3_exp_matches_scipy_adversarial(angles):
    r = rotvecs_at(angles)
    np.testing.assert_allclose(N(g.so3_exp(T(r))), sp_matrix(r), rtol=0, atol=TOL64)


def test_so3_exp_matches_rodrigues_closed_form():
    r = random_rotvecs(np.random.default_rng(1), (50,), PI)
    th = np.linalg.norm(r, axis=-1)[:, None, None]
    k = np_hat(r / th[..., 0])
    want = np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * (k @ k)
    np.testing.assert_allclose(N(g.so3_exp(T(r))), want, rtol=0, atol=TOL64)


@pytest.mark.parametrize("r", rotvecs_up_to_4pi(seed=2), ids=["random", "to_pi", "beyond_pi"])
def test_quat_from_rotvec_matches_scipy(r):
    q = N(g.rotvec_to_quat(T(r)))
    assert q.shape == (*r.shape[:-1], 4)
    assert (q[..., 0] >= 0).all()
    want = sp_quat(sp(r), r.shape[:-1])
    assert quat_distance(q, want).max() <= TOL64


def test_rotvec_from_quat_matches_scipy_random_unnormalised():
    gen = np.random.default_rng(3)
    q = gen.normal(size=(4, 5, 4)) * gen.uniform(0.1, 10.0, size=(4, 5, 1))
    got = N(g.quat_to_rotvec(T(q)))
    want = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_rotvec().reshape(4, 5, 3)
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL64)
    assert (np.linalg.norm(got, axis=-1) <= PI + 1e-15).all()


def test_rotvec_from_quat_matches_scipy_adversarial():
    r = rotvecs_at(ANGLES_TO_PI)
    q = sp_quat(sp(r), r.shape[:-1])
    for quat in (q, -q, 3.0 * q):
        got = N(g.quat_to_rotvec(T(quat)))
        assert rotvec_distance(got, r).max() <= TOL64


def test_rotvec_from_quat_at_w_zero_is_pi_about_the_vector_part():
    v = AXES
    q = np.concatenate([np.zeros((len(v), 1)), v], axis=-1)
    got = N(g.quat_to_rotvec(T(q)))
    assert rotvec_distance(got, PI * v).max() <= TOL64


def test_matrix_from_quat_matches_scipy_unnormalised():
    q = np.random.default_rng(4).normal(size=(4, 5, 4))
    want = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(4, 5, 3, 3)
    np.testing.assert_allclose(N(g.quat_to_matrix(T(q))), want, rtol=0, atol=TOL64)


@pytest.mark.parametrize(
    "r",
    [random_rotvecs(np.random.default_rng(5), (4, 5), PI), rotvecs_at(ANGLES_TO_PI)],
    ids=["random", "adversarial"],
)
def test_quat_from_matrix_matches_scipy(r):
    m = sp_matrix(r)
    q = N(g.matrix_to_quat(T(m)))
    assert (q[..., 0] >= 0).all()
    want = sp_quat(Rotation.from_matrix(m.reshape(-1, 3, 3)), r.shape[:-1])
    assert quat_distance(q, want).max() <= TOL64


@pytest.mark.parametrize(
    "r",
    [random_rotvecs(np.random.default_rng(6), (4, 5), PI), rotvecs_at(ANGLES_TO_PI)],
    ids=["random", "adversarial"],
)
def test_so3_log_matches_scipy(r):
    m = sp_matrix(r)
    got = N(g.so3_log(T(m)))
    assert got.shape == r.shape
    assert rotvec_distance(got, sp_rotvec_of_matrix(m)).max() <= TOL64
    assert rotvec_distance(got, r).max() <= TOL64  # the true rotation vector (angle <= pi)


def test_so3_log_of_half_turns_about_coordinate_axes():
    for i in range(3):
        m = -np.eye(3)
        m[i, i] = 1.0  # exactly diag(+-1): rotation by pi about axis i
        got = N(g.so3_log(T(m)))
        assert rotvec_distance(got, PI * np.eye(3)[i]).max() <= TOL64


@pytest.mark.parametrize("r", rotvecs_up_to_4pi(seed=7), ids=["random", "to_pi", "beyond_pi"])
def test_regularize_rotvec(r):
    got = N(g.regularize_rotvec(T(r)))
    assert (np.linalg.norm(got, axis=-1) <= PI + 1e-15).all()
    np.testing.assert_allclose(sp_matrix(got), sp_matrix(r), rtol=0, atol=TOL64)
    want = sp(r).as_rotvec().reshape(r.shape)
    assert rotvec_distance(got, want).max() <= TOL64


def test_regularize_rotvec_known_values():
    a = _unit([1.0, -2.0, 2.0])
    cases = [(0.5, 0.5), (PI + 0.5, -(PI - 0.5)), (2 * PI + 0.5, 0.5), (3 * PI - 0.5, PI - 0.5)]
    for angle, want in cases:
        np.testing.assert_allclose(N(g.regularize_rotvec(T(angle * a))), want * a, atol=TOL64)


def np_hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def test_quat_multiply_matches_hamilton_product_and_scipy_composition():
    gen = np.random.default_rng(8)
    a, b = gen.normal(size=(4, 1, 4)), gen.normal(size=(5, 4))
    got = N(g.quat_multiply(T(a), T(b)))
    assert got.shape == (4, 5, 4)
    np.testing.assert_allclose(got, np_hamilton(a, b), rtol=0, atol=TOL64)
    # a * b is the rotation b followed by a.
    a1 = _unit(a[:, 0])[:, None].repeat(5, 1).reshape(-1, 4)
    b1 = _unit(np.broadcast_to(b, (4, 5, 4))).reshape(-1, 4)
    prod = N(g.quat_multiply(T(a1), T(b1)))
    want = Rotation.from_quat(a1, scalar_first=True) * Rotation.from_quat(b1, scalar_first=True)
    np.testing.assert_allclose(
        Rotation.from_quat(prod, scalar_first=True).as_matrix(), want.as_matrix(), atol=TOL64
    )


def test_quat_rotate_matches_scipy_with_broadcasting():
    gen = np.random.default_rng(9)
    q, v = _unit(gen.normal(size=(3, 1, 4))), gen.normal(size=(6, 3)) * 50
    got = N(g.quat_rotate(T(q), T(v)))
    assert got.shape == (3, 6, 3)
    for i in range(3):
        want = Rotation.from_quat(q[i, 0], scalar_first=True).apply(v)
        np.testing.assert_allclose(got[i], want, rtol=0, atol=50 * TOL64)


def test_hat_is_the_cross_product_matrix():
    gen = np.random.default_rng(10)
    v, w = gen.normal(size=(4, 5, 3)), gen.normal(size=(4, 5, 3))
    h = N(g.hat(T(v)))
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", h, w), np.cross(v, w), atol=TOL64)
    np.testing.assert_array_equal(h, -np.swapaxes(h, -1, -2))


@pytest.mark.parametrize("convention", ALL_CONVENTIONS)
def test_euler_to_matrix_matches_scipy(convention):
    angles = np.random.default_rng(11).uniform(-2 * PI, 2 * PI, size=(4, 5, 3))
    want = Rotation.from_euler(convention, angles.reshape(-1, 3)).as_matrix().reshape(4, 5, 3, 3)
    got = N(g.euler_to_matrix(T(angles), convention))
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL64)


def test_euler_to_matrix_default_is_extrinsic_xyz_rz_ry_rx():
    a, b, c = 0.3, -0.7, 1.9
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    np.testing.assert_allclose(N(g.euler_to_matrix(T([a, b, c]))), rz @ ry @ rx, atol=TOL64)
    np.testing.assert_allclose(N(g.matrix_to_euler(T(rz @ ry @ rx))), [a, b, c], atol=TOL64)


@pytest.mark.parametrize("convention", ALL_CONVENTIONS)
def test_matrix_to_euler_matches_scipy(convention):
    m = Rotation.random(20, random_state=12).as_matrix().reshape(4, 5, 3, 3)
    got = N(g.matrix_to_euler(T(m), convention))
    np.testing.assert_allclose(got, sp_euler(m, convention), rtol=0, atol=TOL64)
    assert (np.abs(got[..., 1]) <= PI / 2).all()


def _near_lock_matrices(convention: str, offset: float) -> np.ndarray:
    """Matrices whose middle Euler angle is +-(pi/2 - offset), outer angles random."""
    gen = np.random.default_rng(13)
    n = 24
    mid = np.where(np.arange(n) % 2 == 0, PI / 2 - offset, -PI / 2 + offset)
    angles = np.stack([gen.uniform(-3, 3, n), mid, gen.uniform(-3, 3, n)], axis=-1)
    return Rotation.from_euler(convention, angles).as_matrix()


@pytest.mark.parametrize("offset", [0.0, 1e-9, 1e-8])
@pytest.mark.parametrize("convention", ALL_CONVENTIONS)
def test_matrix_to_euler_gimbal_lock_reconstructs_matrix(convention, offset):
    m = _near_lock_matrices(convention, offset)
    got = N(g.matrix_to_euler(T(m), convention))
    assert np.isfinite(got).all()
    # Setting one angle to zero inside the lock band costs O(offset), as in scipy.
    recon = Rotation.from_euler(convention, got).as_matrix()
    np.testing.assert_allclose(recon, m, rtol=0, atol=TOL64 + 3 * offset)
    np.testing.assert_allclose(got[:, 1], sp_euler(m, convention)[:, 1], rtol=0, atol=TOL64)


@pytest.mark.parametrize("convention", ALL_CONVENTIONS)
def test_matrix_to_euler_gimbal_lock_matches_scipy(convention):
    m = _near_lock_matrices(convention, 0.0)
    got = N(g.matrix_to_euler(T(m), convention))
    want = sp_euler(m, convention)
    assert (got[:, 2] == 0).all(), "third angle must be set to zero at gimbal lock, like scipy"
    assert np.abs(angle_diff(got, want)).max() <= TOL64


@pytest.mark.parametrize("offset", [1e-5, 1e-3])
@pytest.mark.parametrize("convention", ALL_CONVENTIONS)
def test_matrix_to_euler_close_to_but_outside_gimbal_lock(convention, offset):
    m = _near_lock_matrices(convention, offset)
    got = N(g.matrix_to_euler(T(m), convention))
    np.testing.assert_allclose(Rotation.from_euler(convention, got).as_matrix(), m, atol=TOL64)
    # The outer angles are ill-conditioned here: d(angle) ~ eps / cos(middle angle).
    tol = TOL64 + 1e-15 / offset
    assert np.abs(angle_diff(got, sp_euler(m, convention))).max() <= tol


def test_rotation_6d_to_matrix_matches_gram_schmidt():
    d6 = np.random.default_rng(14).normal(size=(4, 5, 6)) * 3
    got = N(g.rotation_6d_to_matrix(T(d6)))
    np.testing.assert_allclose(got, np_gram_schmidt(d6), rtol=0, atol=TOL64)
    eye = np.broadcast_to(np.eye(3), got.shape)
    np.testing.assert_allclose(np.swapaxes(got, -1, -2) @ got, eye, atol=TOL64)
    np.testing.assert_allclose(np.linalg.det(got), 1.0, atol=TOL64)


def test_matrix_to_rotation_6d_is_first_two_columns():
    m = Rotation.random(20, random_state=15).as_matrix().reshape(4, 5, 3, 3)
    got = N(g.matrix_to_rotation_6d(T(m)))
    want = np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)
    np.testing.assert_array_equal(got, want)


# ------------------------------------------------------------------------------------------------
# 2. float32 accuracy (oracles in float64 from the same float32 values)
# ------------------------------------------------------------------------------------------------

F32_ANGLES = np.concatenate(
    [
        np.logspace(-7, np.log10(PI - 1e-6), 60),
        PI - np.logspace(-6, -2, 10),
    ]
)


def _f32_rotvecs(seed: int, per_angle: int = 30) -> np.ndarray:
    gen = np.random.default_rng(seed)
    axes = random_axes(gen, len(F32_ANGLES) * per_angle).reshape(len(F32_ANGLES), per_angle, 3)
    r32 = (axes * F32_ANGLES[:, None, None]).astype(np.float32)
    return r32.reshape(-1, 3)


def _rel(err: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.linalg.norm(err, axis=-1) / np.maximum(np.linalg.norm(ref, axis=-1), 1e-30)


def test_float32_quat_from_rotvec_accuracy():
    r32 = _f32_rotvecs(20)
    q = g.rotvec_to_quat(torch.from_numpy(r32))
    assert q.dtype == F32
    q = N(q)
    want = Rotation.from_rotvec(r32.astype(np.float64)).as_quat(scalar_first=True, canonical=True)
    # |q| = 1, so this is the relative error of the quaternion (measured <= 2.3e-7) ...
    assert np.linalg.norm(q - want, axis=-1).max() <= 1e-6
    # ... and of its vector part (axis * sin(theta/2)), also for theta = 1e-7 (measured <= 1.6e-7).
    assert _rel(q[:, 1:] - want[:, 1:], want[:, 1:]).max() <= 1e-6


def test_float32_rotvec_from_quat_accuracy():
    r = _f32_rotvecs(21).astype(np.float64)
    q32 = Rotation.from_rotvec(r).as_quat(scalar_first=True, canonical=True).astype(np.float32)
    got = g.quat_to_rotvec(torch.from_numpy(q32))
    assert got.dtype == F32
    want = Rotation.from_quat(q32.astype(np.float64), scalar_first=True).as_rotvec()
    assert _rel(N(got) - want, want).max() <= 1e-6  # measured <= 1.7e-7


def test_float32_regularize_rotvec_accuracy():
    r32 = _f32_rotvecs(22)
    got = N(g.regularize_rotvec(torch.from_numpy(r32)))
    want = r32.astype(np.float64)  # already regular
    assert _rel(got - want, want).max() <= 1e-6


def test_float32_so3_log_bound():
    """Measured over 4e5 samples: abs error <= 5.2e-7 rad, relative <= 3.0e-7 (asserted 6e-7, 4e-7).

    Both against scipy's log of the float32 matrix re-orthonormalised in float64 and against the
    true rotation vector; near 0 the absolute error is ~2e-9 rad, near and at pi ~5e-7 rad (a few
    float32 ulps of pi).
    """
    gen = np.random.default_rng(23)
    n = 600
    bands = {
        "near_zero": np.logspace(-8, -2, n),
        "generic": gen.uniform(1e-2, PI - 1e-2, n),
        "near_pi": PI - np.logspace(-9, -2, n),
        "pi": np.full(n, PI),
    }
    for name, theta in bands.items():
        r = random_axes(gen, n) * theta[:, None]
        m32 = Rotation.from_rotvec(r).as_matrix().astype(np.float32)
        got = g.so3_log(torch.from_numpy(m32))
        assert got.dtype == F32
        got = N(got)
        u, _, vt = np.linalg.svd(m32.astype(np.float64))
        ref = Rotation.from_matrix(u @ vt).as_rotvec()
        # Within float32 resolution of pi the axis sign is not determined by the matrix.
        for want in (ref, r):
            d = rotvec_distance(got, want, pi_band=1e-6)
            assert d.max() <= 6e-7, name
            assert (d / np.linalg.norm(want, axis=-1)).max() <= 4e-7, name
        angle_err = np.abs(np.linalg.norm(got, axis=-1) - np.linalg.norm(ref, axis=-1))
        assert angle_err.max() <= 6e-7, name


def _pose_pairs_f32(regime: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
    gen = np.random.default_rng(seed)
    n = 200
    if regime == "from_identity":
        theta = np.concatenate(
            [np.logspace(-7, np.log10(PI - 1e-6), n - 20), PI - np.logspace(-6, -2, 20)]
        )
        pred_rot = np.zeros((n, 3))
    else:
        theta = (
            np.logspace(-7, -3, n)
            if regime == "large_tiny_relative"
            else PI - np.logspace(-6, -2, n)
        )
        pred_rot = random_axes(gen, n) * gen.uniform(2.0, PI - 1e-2, (n, 1))
    target_rot = (sp(pred_rot) * sp(random_axes(gen, n) * theta[:, None])).as_rotvec()
    pred = np.concatenate([pred_rot, gen.normal(size=(n, 3)) * 20], axis=-1)
    target = np.concatenate([target_rot, pred[:, 3:] + gen.normal(size=(n, 3))], axis=-1)
    return pred.astype(np.float32), target.astype(np.float32)


@pytest.mark.parametrize("regime", ["from_identity", "large_tiny_relative", "near_pi_relative"])
def test_float32_se3_error_accuracy(regime):
    pred, target = _pose_pairs_f32(regime, 24)
    got = g.se3_error(torch.from_numpy(pred), torch.from_numpy(target))
    assert got.dtype == F32
    got = N(got)
    want = oracle_se3_error(pred.astype(np.float64), target.astype(np.float64))
    angle = np.linalg.norm(want[:, :3], axis=-1)
    if regime == "large_tiny_relative":  # the relative rotations really are tiny
        assert angle.max() < 2e-3 and np.median(angle) < 1e-4
    if regime == "near_pi_relative":
        assert angle.min() > PI - 2e-2
    # Relative error floor 1e-12 rad for relative rotations that float32 rounding made ~0.
    rot_err = np.linalg.norm(got[:, :3] - want[:, :3], axis=-1) / np.maximum(angle, 1e-12)
    assert rot_err.max() <= 1e-6  # measured <= 6e-8
    assert _rel(got[:, 3:] - want[:, 3:], want[:, 3:]).max() <= 1e-6


# ------------------------------------------------------------------------------------------------
# 3. Round trips
# ------------------------------------------------------------------------------------------------


def test_exp_of_log_is_identity_on_matrices():
    m = np.concatenate(
        [
            Rotation.random(50, random_state=30).as_matrix(),
            sp_matrix(rotvecs_at(ANGLES_TO_PI).reshape(-1, 3)),
        ]
    )
    np.testing.assert_allclose(N(g.so3_exp(g.so3_log(T(m)))), m, rtol=0, atol=TOL64)


def test_log_of_exp_is_identity_below_pi():
    angles = [0.0, 1e-12, 1e-8, 1e-6, 1e-3, 0.5, 2.0, PI - 1e-3, PI - 1e-6, PI - 1e-9]
    r = np.concatenate(
        [rotvecs_at(angles).reshape(-1, 3), random_rotvecs(np.random.default_rng(31), (50,), PI)]
    )
    np.testing.assert_allclose(N(g.so3_log(g.so3_exp(T(r)))), r, rtol=0, atol=TOL64)


def test_quaternion_double_cover():
    q = np.random.default_rng(32).normal(size=(30, 4))
    q = np.concatenate([q, sp_quat(sp(rotvecs_at(ANGLES_TO_PI)), (-1,))])
    m_pos, m_neg = N(g.quat_to_matrix(T(q))), N(g.quat_to_matrix(T(-q)))
    np.testing.assert_allclose(m_pos, m_neg, rtol=0, atol=TOL64)
    r_pos, r_neg = N(g.quat_to_rotvec(T(q))), N(g.quat_to_rotvec(T(-q)))
    np.testing.assert_allclose(r_pos, r_neg, rtol=0, atol=TOL64)
    # and both agree with scipy's matrix of the same quaternion
    want = Rotation.from_quat(q, scalar_first=True).as_matrix()
    np.testing.assert_allclose(m_pos, want, rtol=0, atol=TOL64)


def test_quat_round_trips():
    r = random_rotvecs(np.random.default_rng(33), (40,), PI)
    q = g.rotvec_to_quat(T(r))
    np.testing.assert_allclose(N(g.quat_to_rotvec(q)), r, rtol=0, atol=TOL64)
    np.testing.assert_allclose(N(g.matrix_to_quat(g.quat_to_matrix(q))), N(q), atol=TOL64)


@pytest.mark.parametrize("convention", ALL_CONVENTIONS)
def test_euler_round_trips(convention):
    gen = np.random.default_rng(34)
    n = 50
    angles = np.stack(
        [
            gen.uniform(-PI + 1e-3, PI - 1e-3, n),
            gen.uniform(-PI / 2 + 1e-3, PI / 2 - 1e-3, n),
            gen.uniform(-PI + 1e-3, PI - 1e-3, n),
        ],
        axis=-1,
    )
    back = N(g.matrix_to_euler(g.euler_to_matrix(T(angles), convention), convention))
    np.testing.assert_allclose(back, angles, rtol=0, atol=TOL64)
    m = Rotation.random(n, random_state=35).as_matrix()
    m_back = N(g.euler_to_matrix(g.matrix_to_euler(T(m), convention), convention))
    np.testing.assert_allclose(m_back, m, rtol=0, atol=TOL64)


def test_rotation_6d_round_trip():
    m = Rotation.random(40, random_state=36).as_matrix()
    back = N(g.rotation_6d_to_matrix(g.matrix_to_rotation_6d(T(m))))
    np.testing.assert_allclose(back, m, rtol=0, atol=TOL64)


def random_poses(gen: np.random.Generator, shape: tuple[int, ...], max_angle: float = PI):
    r = random_rotvecs(gen, shape, max_angle)
    return np.concatenate([r, gen.normal(size=(*shape, 3)) * 30], axis=-1)


def test_se3_from_vector_matches_scipy_and_round_trips():
    p = random_poses(np.random.default_rng(40), (4, 5))
    m = g.vector_to_se3(T(p))
    assert m.shape == (4, 5, 4, 4)
    np.testing.assert_allclose(N(m), pose_matrix(p), rtol=0, atol=TOL64)
    np.testing.assert_allclose(N(g.se3_to_vector(m)), p, rtol=0, atol=TOL64)
    np.testing.assert_allclose(N(g.se3_to_vector(m[..., :3, :])), p, rtol=0, atol=TOL64)


def test_se3_to_vector_regularises_large_rotations():
    p = random_poses(np.random.default_rng(41), (30,), 4 * PI)
    back = N(g.se3_to_vector(g.vector_to_se3(T(p))))
    assert (np.linalg.norm(back[:, :3], axis=-1) <= PI + 1e-15).all()
    np.testing.assert_allclose(pose_matrix(back), pose_matrix(p), rtol=0, atol=1e-12)


def test_se3_compose_and_inverse_match_matrix_algebra():
    gen = np.random.default_rng(42)
    a, b = pose_matrix(random_poses(gen, (4, 1))), pose_matrix(random_poses(gen, (5,)))
    got = N(g.se3_compose(T(a), T(b)))
    assert got.shape == (4, 5, 4, 4)
    np.testing.assert_allclose(got, a @ b, rtol=0, atol=1e-11)
    np.testing.assert_allclose(N(g.se3_inverse(T(a))), np.linalg.inv(a), rtol=0, atol=1e-11)
    # (3, 4) forms: both (3, 4) -> (3, 4); mixed -> (4, 4)
    got34 = g.se3_compose(T(a[..., :3, :]), T(b[..., :3, :]))
    assert got34.shape == (4, 5, 3, 4)
    np.testing.assert_allclose(N(got34), (a @ b)[..., :3, :], atol=1e-11)
    mixed = g.se3_compose(T(a[..., :3, :]), T(b))
    assert mixed.shape == (4, 5, 4, 4)
    np.testing.assert_allclose(N(mixed), a @ b, atol=1e-11)
    inv34 = g.se3_inverse(T(a[..., :3, :]))
    assert inv34.shape == (4, 1, 3, 4)
    np.testing.assert_allclose(N(inv34), np.linalg.inv(a)[..., :3, :], atol=1e-11)


def test_se3_compose_with_inverse_is_identity_and_associative():
    gen = np.random.default_rng(43)
    a, b, c = (T(pose_matrix(random_poses(gen, (10,)))) for _ in range(3))
    eye = np.broadcast_to(np.eye(4), (10, 4, 4))
    np.testing.assert_allclose(N(g.se3_compose(a, g.se3_inverse(a))), eye, atol=1e-12)
    np.testing.assert_allclose(N(g.se3_compose(g.se3_inverse(a), a)), eye, atol=1e-12)
    left = g.se3_compose(g.se3_compose(a, b), c)
    right = g.se3_compose(a, g.se3_compose(b, c))
    np.testing.assert_allclose(N(left), N(right), rtol=0, atol=1e-11)


GROUP_ANGLES = [0.0, 1e-12, 1e-8, 1e-6, 1e-3, 0.5, 2.0, PI - 1e-2]


def _twists(angles: list[float], seed: int) -> np.ndarray:
    gen = np.random.default_rng(seed)
    w = rotvecs_at(angles, AXES[[0, 4, 8, 10]]).reshape(-1, 3)
    return np.concatenate([w, gen.normal(size=w.shape) * 10], axis=-1)


def test_se3_group_exp_matches_expm():
    x = _twists([*GROUP_ANGLES, PI - 1e-6, PI], 50)
    got = N(g.se3_group_exp(T(x)))
    want = np.stack([expm(twist_matrix(xi)) for xi in x])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_se3_group_log_matches_logm():
    x = _twists(GROUP_ANGLES, 51)  # logm loses accuracy near pi; see the next test there
    m = np.stack([expm(twist_matrix(xi)) for xi in x])
    got = N(g.se3_group_log(T(m)))
    logs = [np.real(logm(mi)) for mi in m]
    want = np.stack([[lg[2, 1], lg[0, 2], lg[1, 0], *lg[:3, 3]] for lg in logs])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-11)
    np.testing.assert_allclose(got, x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(N(g.se3_group_log(T(m[:, :3, :]))), got, atol=0)


def test_se3_group_log_near_pi_closed_form_and_round_trip():
    x = _twists([PI - 1e-2, PI - 1e-4, PI - 1e-6, PI - 1e-9], 52)
    m = np.stack([expm(twist_matrix(xi)) for xi in x])
    got = N(g.se3_group_log(T(m)))
    # u = J_l(w)^-1 t, with J_l from the Van Loan block exponential
    u = np.stack(
        [np.linalg.solve(np_left_jacobian(w), mi[:3, 3]) for w, mi in zip(x[:, :3], m, strict=True)]
    )
    np.testing.assert_allclose(got, np.concatenate([x[:, :3], u], -1), rtol=0, atol=1e-10)
    # exactly pi: the axis sign is arbitrary, but exp(log(T)) = T
    x_pi = _twists([PI], 53)
    m_pi = np.stack([expm(twist_matrix(xi)) for xi in x_pi])
    back = N(g.se3_group_exp(g.se3_group_log(T(m_pi))))
    np.testing.assert_allclose(back, m_pi, rtol=0, atol=1e-11)


def test_group_log_translation_differs_from_pose_vector_translation():
    # For t perpendicular to the axis |V^-1 t| / |t| = (theta/2) / sin(theta/2): 1.1107 at 90 deg.
    for theta in (PI / 2, PI * 179 / 180):
        pose = np.array([0.0, 0.0, theta, 10.0, 0.0, 0.0])
        twist = N(g.se3_group_log(g.vector_to_se3(T(pose))))
        ratio = np.linalg.norm(twist[3:]) / 10.0
        np.testing.assert_allclose(ratio, (theta / 2) / math.sin(theta / 2), rtol=1e-12)
    np.testing.assert_allclose((PI / 4) / math.sin(PI / 4), 1.1107, atol=1e-4)


# ------------------------------------------------------------------------------------------------
# 4. se3_error
# ------------------------------------------------------------------------------------------------


def test_se3_error_matches_definition_random_batched():
    gen = np.random.default_rng(60)
    pred, target = random_poses(gen, (4, 5)), random_poses(gen, (4, 5))
    got = g.se3_error(T(pred), T(target))
    assert got.shape == (4, 5, 6) and got.dtype == F64
    np.testing.assert_allclose(N(got), oracle_se3_error(pred, target), rtol=0, atol=1e-12)


def test_se3_error_matches_definition_adversarial_relative_rotations():
    gen = np.random.default_rng(61)
    rel = rotvecs_at(ANGLES_TO_PI).reshape(-1, 3)
    pred = random_poses(gen, (len(rel),), 4 * PI)
    target_rot = (sp(pred[:, :3]) * sp(rel)).as_rotvec()
    target = np.concatenate([target_rot, gen.normal(size=(len(rel), 3)) * 30], axis=-1)
    got = N(g.se3_error(T(pred), T(target)))
    want = oracle_se3_error(pred, target)
    assert rotvec_distance(got[:, :3], rel, pi_band=1e-9).max() <= 1e-12
    assert rotvec_distance(got[:, :3], want[:, :3], pi_band=1e-9).max() <= 1e-12
    np.testing.assert_allclose(got[:, 3:], want[:, 3:], rtol=0, atol=1e-12)


def test_se3_error_of_identical_poses_is_exactly_zero():
    gen = np.random.default_rng(62)
    for dtype in (F32, F64):
        p = T(random_poses(gen, (3, 7), 4 * PI), dtype)
        e = g.se3_error(p, p.clone())
        assert e.dtype == dtype
        assert torch.equal(e, torch.zeros_like(e))


def test_se3_error_broadcasting_and_dtype():
    gen = np.random.default_rng(63)
    pred, target = random_poses(gen, (5,)), random_poses(gen, ())
    got = g.se3_error(T(pred), T(target))
    assert got.shape == (5, 6)
    np.testing.assert_allclose(N(got), oracle_se3_error(pred, target), atol=1e-12)
    got2 = g.se3_error(T(target), T(pred))
    np.testing.assert_allclose(N(got2), oracle_se3_error(target, pred), atol=1e-12)
    a, b = random_poses(gen, (2, 1)), random_poses(gen, (3,))
    got3 = g.se3_error(T(a), T(b))
    assert got3.shape == (2, 3, 6)
    np.testing.assert_allclose(N(got3), oracle_se3_error(a, b), atol=1e-12)
    assert g.se3_error(T(a, F32), T(b, F32)).dtype == F32
    assert g.se3_error(T(a, F32), T(b, F64)).dtype == F64


def test_se3_error_translation_is_not_the_screw_log():
    # 90 deg about z, translation along x: e_t = R^T dt has the norm of dt (no 1.11 stretch).
    pred = np.zeros(6)
    target = np.array([0.0, 0.0, PI / 2, 10.0, 0.0, 0.0])
    e = N(g.se3_error(T(pred), T(target)))
    np.testing.assert_allclose(e, [0.0, 0.0, PI / 2, 10.0, 0.0, 0.0], atol=1e-12)
    pred = np.array([0.0, 0.0, PI / 2, 1.0, 2.0, 3.0])
    target = np.array([0.0, 0.0, PI / 2, 1.0, 12.0, 3.0])
    # R_pred^T (0, 10, 0) = (10, 0, 0) for a 90 deg rotation about z
    np.testing.assert_allclose(N(g.se3_error(T(pred), T(target))), [0, 0, 0, 10, 0, 0], atol=1e-12)


# ------------------------------------------------------------------------------------------------
# 5. Differentiability
# ------------------------------------------------------------------------------------------------

_AX = np.array([[0.36, 0.48, 0.8], [-0.6, 0.0, 0.8]])  # unit axes, exactly
GRAD_POINTS = {"generic": 1.3, "zero": 0.0, "tiny": 1e-8, "near_pi": PI - 1e-4}


def _rv(theta: float) -> np.ndarray:
    return _AX * theta


def _mat(theta: float) -> np.ndarray:
    return sp_matrix(_rv(theta))


def _pose(theta: float) -> np.ndarray:
    return np.concatenate([_rv(theta), [[1.0, -2.0, 3.0], [0.5, 0.0, -4.0]]], axis=-1)


def _error_inputs(theta: float) -> tuple[np.ndarray, np.ndarray]:
    pred = np.array([[0.3, -1.2, 0.5, 1.0, 2.0, 3.0], [2.0, 0.1, -0.4, -1.0, 0.0, 5.0]])
    target_rot = (sp(pred[:, :3]) * sp(_rv(theta))).as_rotvec()
    return pred, np.concatenate([target_rot, [[0.0, 1.0, 2.0], [3.0, -1.0, 0.0]]], axis=-1)


GRAD_FUNCTIONS: dict[str, tuple[Callable, Callable[[float], tuple[np.ndarray, ...]]]] = {
    "so3_exp": (g.so3_exp, lambda th: (_rv(th),)),
    "rotvec_to_quat": (g.rotvec_to_quat, lambda th: (_rv(th),)),
    "regularize_rotvec": (g.regularize_rotvec, lambda th: (_rv(th),)),
    "so3_left_jacobian": (g.so3_left_jacobian, lambda th: (_rv(th),)),
    "so3_left_jacobian_inverse": (g.so3_left_jacobian_inverse, lambda th: (_rv(th),)),
    "so3_log": (g.so3_log, lambda th: (_mat(th),)),
    "matrix_to_quat": (g.matrix_to_quat, lambda th: (_mat(th),)),
    "quat_to_rotvec": (
        g.quat_to_rotvec,
        lambda th: (1.7 * sp_quat(sp(_rv(th)), (2,)),),
    ),
    "vector_to_se3": (g.vector_to_se3, lambda th: (_pose(th),)),
    "se3_to_vector": (g.se3_to_vector, lambda th: (pose_matrix(_pose(th)),)),
    "se3_group_exp": (g.se3_group_exp, lambda th: (_pose(th),)),
    "se3_group_log": (g.se3_group_log, lambda th: (pose_matrix(_pose(th)),)),
    "se3_error": (g.se3_error, _error_inputs),
}


@pytest.mark.parametrize("point", list(GRAD_POINTS))
@pytest.mark.parametrize("name", list(GRAD_FUNCTIONS))
def test_gradcheck(name, point):
    fn, make = GRAD_FUNCTIONS[name]
    inputs = tuple(T(x).requires_grad_(True) for x in make(GRAD_POINTS[point]))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("convention", ["xyz", "zyx", "XYZ", "YZX"])
@pytest.mark.parametrize("angles", [[0.0, 0.0, 0.0], [0.3, -0.7, 1.1], [2.9, 1.2, -3.0]])
def test_gradcheck_euler(convention, angles):
    m = T(Rotation.from_euler(convention, angles).as_matrix()).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: g.matrix_to_euler(x, convention), (m,))
    a = T(angles).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: g.euler_to_matrix(x, convention), (a,))


def test_gradcheck_other_functions():
    gen = np.random.default_rng(70)
    cases = [
        (g.rotation_6d_to_matrix, (gen.normal(size=(3, 6)),)),
        (g.matrix_to_rotation_6d, (gen.normal(size=(2, 3, 3)),)),
        (g.quat_to_matrix, (gen.normal(size=(3, 4)),)),
        (g.quat_multiply, (gen.normal(size=(3, 4)), gen.normal(size=(3, 4)))),
        (g.quat_rotate, (_unit(gen.normal(size=(3, 4))), gen.normal(size=(3, 3)))),
        (g.hat, (gen.normal(size=(3, 3)),)),
        (
            g.se3_compose,
            (pose_matrix(random_poses(gen, (2,))), pose_matrix(random_poses(gen, (2,)))),
        ),
        (g.se3_inverse, (pose_matrix(random_poses(gen, (2,))),)),
    ]
    for fn, args in cases:
        inputs = tuple(T(a).requires_grad_(True) for a in args)
        assert torch.autograd.gradcheck(fn, inputs), fn.__name__


FINITE_ANGLES = [0.0, 1e-12, PI - 1e-9, PI, 2 * PI]


@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
@pytest.mark.parametrize("theta", FINITE_ANGLES)
def test_gradients_are_finite_at_singular_angles(theta, dtype):
    finite_fns = dict(GRAD_FUNCTIONS)
    finite_fns["matrix_to_euler"] = (g.matrix_to_euler, lambda th: (_mat(th),))
    if theta >= 2 * PI:  # J_l^-1 has a pole at 2 pi
        del finite_fns["so3_left_jacobian_inverse"]
    weights = torch.Generator().manual_seed(0)
    for name, (fn, make) in finite_fns.items():
        inputs = tuple(T(x, dtype).requires_grad_(True) for x in make(theta))
        out = fn(*inputs)
        assert torch.isfinite(out).all(), name
        w = torch.randn(out.shape, generator=weights, dtype=F64).to(dtype)
        (out * w).sum().backward()
        for x in inputs:
            assert x.grad is not None and torch.isfinite(x.grad).all(), name


@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
def test_gradient_of_so3_exp_at_zero_is_hat(dtype):
    # d exp([r]x) / d r_i at r = 0 is [e_i]x, exactly.
    r = torch.zeros(3, dtype=dtype, requires_grad=True)
    jac = torch.autograd.functional.jacobian(g.so3_exp, r)
    want = np_hat(np.eye(3))  # (3, 3, 3): want[i] = [e_i]x
    np.testing.assert_allclose(N(jac).transpose(2, 0, 1), want, atol=1e-7)
    # and of so3_log at the identity: d r / d M = the inverse (vee) map, 1/2 (M - M^T)
    m = torch.eye(3, dtype=dtype, requires_grad=True)
    jac_log = N(torch.autograd.functional.jacobian(g.so3_log, m))
    np.testing.assert_allclose(jac_log[0, 2, 1], 0.5, atol=1e-7)
    np.testing.assert_allclose(jac_log[0, 1, 2], -0.5, atol=1e-7)
    np.testing.assert_allclose(jac_log[2, 1, 0], 0.5, atol=1e-7)


# ------------------------------------------------------------------------------------------------
# 6. Property-based tests
# ------------------------------------------------------------------------------------------------

HYP = settings(max_examples=60, deadline=None, derandomize=True, database=None)
_coord = st.floats(-1.0, 1.0, allow_nan=False)
_axis = st.tuples(_coord, _coord, _coord).filter(lambda v: sum(c * c for c in v) > 1e-2)


def _rotvec_strategy(max_angle: float):
    return st.builds(lambda a, th: _unit(a) * th, _axis, st.floats(0.0, max_angle))


_translation = st.tuples(*[st.floats(-100.0, 100.0, allow_nan=False)] * 3)
_pose_st = st.builds(lambda r, t: np.concatenate([r, t]), _rotvec_strategy(4 * PI), _translation)


@HYP
@given(r=_rotvec_strategy(4 * PI))
def test_property_exp_log(r):
    m = g.so3_exp(T(r))
    mn = N(m)
    np.testing.assert_allclose(mn.T @ mn, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(mn), 1.0, atol=1e-14)
    log = N(g.so3_log(m))
    assert np.linalg.norm(log) <= PI + 1e-12
    np.testing.assert_allclose(sp_matrix(log), sp_matrix(r), atol=1e-12)
    # Angle of exp(r) is |r| folded into [0, pi].
    folded = abs((np.linalg.norm(r) + PI) % (2 * PI) - PI)
    np.testing.assert_allclose(np.linalg.norm(log), folded, atol=1e-9)


@HYP
@given(a=_pose_st, b=_pose_st)
def test_property_se3_error_swap(a, b):
    e_ab = N(g.se3_error(T(a), T(b)))
    e_ba = N(g.se3_error(T(b), T(a)))
    # e(b, a) = Log(X^-1) with X = a^-1 b: rotation -w, translation -exp(w)^T e_t(a, b)
    np.testing.assert_allclose(np.linalg.norm(e_ba[3:]), np.linalg.norm(e_ab[3:]), rtol=1e-12)
    if np.linalg.norm(e_ab[:3]) < PI - 1e-6:
        np.testing.assert_allclose(e_ba[:3], -e_ab[:3], atol=1e-12)
        want_t = -sp_matrix(e_ab[:3]).T @ e_ab[3:]
        np.testing.assert_allclose(e_ba[3:], want_t, atol=1e-10)


@HYP
@given(a=_pose_st, b=_pose_st, c=_pose_st)
def test_property_se3_error_left_invariant(a, b, c):
    def left(p):  # c o p as a pose vector, composed with scipy
        rot = sp(c[:3]) * sp(p[:3])
        return np.concatenate([rot.as_rotvec()[0], sp(c[:3]).apply(p[3:])[0] + c[3:]])

    e = N(g.se3_error(T(a), T(b)))
    e_left = N(g.se3_error(T(left(a)), T(left(b))))
    if np.linalg.norm(e[:3]) < PI - 1e-6:
        np.testing.assert_allclose(e_left, e, atol=1e-9)


_quat_st = st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 4).filter(
    lambda q: sum(c * c for c in q) > 1e-2
)


@HYP
@given(qa=_quat_st, qb=_quat_st)
def test_property_quaternion_homomorphism(qa, qb):
    qa, qb = np.asarray(qa), np.asarray(qb)
    prod = g.quat_multiply(T(qa), T(qb))
    want = Rotation.from_quat(qa, scalar_first=True) * Rotation.from_quat(qb, scalar_first=True)
    np.testing.assert_allclose(N(g.quat_to_matrix(prod)), want.as_matrix(), atol=1e-12)
    rv = N(g.quat_to_rotvec(prod))
    assert rotvec_distance(rv, want.as_rotvec(), pi_band=1e-9) <= 1e-9


@HYP
@given(r=_rotvec_strategy(2 * PI - 1e-2))
def test_property_left_jacobian_identities(r):
    j, j_inv = N(g.so3_left_jacobian(T(r))), N(g.so3_left_jacobian_inverse(T(r)))
    np.testing.assert_allclose(j @ j_inv, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(j @ r, r, atol=1e-12)
    # det J_l = 2 (1 - cos t) / t^2 = (sin(t/2) / (t/2))^2
    half = np.linalg.norm(r) / 2
    det = (np.sin(half) / half) ** 2 if half > 0 else 1.0
    np.testing.assert_allclose(np.linalg.det(j), det, rtol=1e-12)


# ------------------------------------------------------------------------------------------------
# 7. Jacobian identities
# ------------------------------------------------------------------------------------------------

JAC_ANGLES = [0.0, 1e-12, 1e-8, 1e-6, 1e-3, 4e-3, 0.1, 1.0, 2.5, PI - 1e-6, PI, 4.0, 2 * PI - 0.1]


def test_left_jacobian_matches_van_loan_block_exponential():
    r = rotvecs_at(JAC_ANGLES, AXES[[0, 4, 7, 9]]).reshape(-1, 3)
    got, got_inv = N(g.so3_left_jacobian(T(r))), N(g.so3_left_jacobian_inverse(T(r)))
    want = np.stack([np_left_jacobian(ri) for ri in r])
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL64)
    np.testing.assert_allclose(got_inv, np.linalg.inv(want), rtol=0, atol=1e-11)
    eye = np.broadcast_to(np.eye(3), got.shape)
    np.testing.assert_allclose(got @ got_inv, eye, rtol=0, atol=1e-11)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", got, r), r, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", got_inv, r), r, atol=1e-12)
    # right Jacobian J_r(r) = J_l(-r) = J_l(r)^T
    np.testing.assert_allclose(N(g.so3_left_jacobian(T(-r))), np.swapaxes(got, 1, 2), atol=TOL64)


def test_left_jacobian_inverse_at_pi_coefficient():
    # (1 - (t/2) cot(t/2)) / t^2 = 1/pi^2 at t = pi: J^-1 = I - K/2 + K^2 / pi^2
    a = _unit([1.0, 2.0, -2.0])
    k = np_hat(PI * a)
    want = np.eye(3) - k / 2 + (k @ k) / PI**2
    np.testing.assert_allclose(N(g.so3_left_jacobian_inverse(T(PI * a))), want, atol=TOL64)


@pytest.mark.parametrize("theta", [0.0, 1e-6, 0.7, 2.0, PI - 1e-3])
def test_left_jacobian_finite_differences_of_exp(theta):
    # exp(r + h e_i) exp(r)^T = exp(h J_l(r) e_i + O(h^2)): central differences of the scipy log.
    r = theta * _unit([0.3, -0.5, 0.8])
    h = 1e-5
    base = Rotation.from_rotvec(r).inv()
    cols = []
    for i in range(3):
        d = np.eye(3)[i] * h
        plus = (Rotation.from_rotvec(r + d) * base).as_rotvec()
        minus = (Rotation.from_rotvec(r - d) * base).as_rotvec()
        cols.append((plus - minus) / (2 * h))
    fd = np.stack(cols, axis=-1)
    np.testing.assert_allclose(N(g.so3_left_jacobian(T(r))), fd, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------------
# 8. Argument checks
# ------------------------------------------------------------------------------------------------


def _z(*shape: int) -> torch.Tensor:
    return torch.zeros(shape, dtype=F64)


# (function name, argument name, expected trailing shape, caller given the argument)
ARG_CASES: list[tuple[str, str, str, Callable[[object], object]]] = [
    ("hat", "v", "(..., 3)", lambda x: g.hat(x)),
    ("so3_exp", "rotvec", "(..., 3)", lambda x: g.so3_exp(x)),
    ("so3_log", "matrix", "(..., 3, 3)", lambda x: g.so3_log(x)),
    ("rotvec_to_quat", "rotvec", "(..., 3)", lambda x: g.rotvec_to_quat(x)),
    ("quat_to_rotvec", "quat", "(..., 4)", lambda x: g.quat_to_rotvec(x)),
    ("matrix_to_quat", "matrix", "(..., 3, 3)", lambda x: g.matrix_to_quat(x)),
    ("quat_to_matrix", "quat", "(..., 4)", lambda x: g.quat_to_matrix(x)),
    ("quat_multiply", "a", "(..., 4)", lambda x: g.quat_multiply(x, _z(4))),
    ("quat_multiply", "b", "(..., 4)", lambda x: g.quat_multiply(_z(4), x)),
    ("quat_rotate", "quat", "(..., 4)", lambda x: g.quat_rotate(x, _z(3))),
    ("quat_rotate", "v", "(..., 3)", lambda x: g.quat_rotate(_z(4), x)),
    ("euler_to_matrix", "angles_rad", "(..., 3)", lambda x: g.euler_to_matrix(x)),
    ("matrix_to_euler", "matrix", "(..., 3, 3)", lambda x: g.matrix_to_euler(x)),
    ("rotation_6d_to_matrix", "d6", "(..., 6)", lambda x: g.rotation_6d_to_matrix(x)),
    ("matrix_to_rotation_6d", "matrix", "(..., 3, 3)", lambda x: g.matrix_to_rotation_6d(x)),
    ("so3_left_jacobian", "rotvec", "(..., 3)", lambda x: g.so3_left_jacobian(x)),
    ("so3_left_jacobian_inverse", "rotvec", "(..., 3)", lambda x: g.so3_left_jacobian_inverse(x)),
    ("regularize_rotvec", "rotvec", "(..., 3)", lambda x: g.regularize_rotvec(x)),
    ("vector_to_se3", "pose", "(..., 6)", lambda x: g.vector_to_se3(x)),
    ("se3_group_exp", "twist", "(..., 6)", lambda x: g.se3_group_exp(x)),
    ("se3_error", "pred", "(..., 6)", lambda x: g.se3_error(x, _z(6))),
    ("se3_error", "target", "(..., 6)", lambda x: g.se3_error(_z(6), x)),
]
SE3_MATRIX_CASES: list[tuple[str, str, Callable[[object], object]]] = [
    ("se3_to_vector", "matrix", lambda x: g.se3_to_vector(x)),
    ("se3_group_log", "matrix", lambda x: g.se3_group_log(x)),
    ("se3_inverse", "a", lambda x: g.se3_inverse(x)),
    ("se3_compose", "a", lambda x: g.se3_compose(x, torch.eye(4, dtype=F64))),
    ("se3_compose", "b", lambda x: g.se3_compose(torch.eye(4, dtype=F64), x)),
]


def _good_shape(expected: str) -> tuple[int, ...]:
    return tuple(int(d) for d in re.findall(r"\d+", expected))


def _check_arg_name(func: str, arg: str) -> None:
    assert arg in inspect.signature(getattr(g, func)).parameters


@pytest.mark.parametrize("case", ARG_CASES, ids=[f"{c[0]}-{c[1]}" for c in ARG_CASES])
def test_wrong_trailing_shape_raises_value_error(case):
    func, arg, expected, call = case
    _check_arg_name(func, arg)
    good = _good_shape(expected)
    call(_z(2, *good))  # sanity: a well-formed argument is accepted
    for bad in [(2, *good[:-1], good[-1] + 1), good[:-1] or (), (good[-1] - 1,)]:
        msg = f"{func}(): '{arg}' must have shape {expected}, got {bad}"
        with pytest.raises(ValueError, match=re.escape(msg)):
            call(_z(*bad))


@pytest.mark.parametrize("case", ARG_CASES, ids=[f"{c[0]}-{c[1]}" for c in ARG_CASES])
def test_non_float_arguments_raise_type_error(case):
    func, arg, expected, call = case
    good = _good_shape(expected)
    bad_values = [
        torch.zeros(good, dtype=torch.int64),
        torch.zeros(good, dtype=torch.bool),
        np.zeros(good),
        [0.0] * good[-1],
    ]
    for bad in bad_values:
        with pytest.raises(TypeError, match=re.escape(f"{func}(): '{arg}' must be")):
            call(bad)


@pytest.mark.parametrize("case", SE3_MATRIX_CASES, ids=[f"{c[0]}-{c[1]}" for c in SE3_MATRIX_CASES])
def test_se3_matrix_shapes(case):
    func, arg, call = case
    _check_arg_name(func, arg)
    call(_z(2, 4, 4) + torch.eye(4, dtype=F64))
    call(_z(2, 3, 4) + torch.eye(4, dtype=F64)[:3])
    msg = f"{func}(): '{arg}' must have shape (..., 4, 4)"
    for bad in [(3, 3), (2, 3, 3), (4, 3), (4,), (4, 5)]:
        with pytest.raises(ValueError, match=re.escape(msg)):
            call(_z(*bad))
    for bad in [torch.eye(4, dtype=torch.int32), np.eye(4)]:
        with pytest.raises(TypeError, match=re.escape(f"{func}(): '{arg}' must be")):
            call(bad)


@pytest.mark.parametrize("convention", ["xyx", "zyz", "xYz", "XYz", "ab", "xy", "xyzx", "", "xxy"])
@pytest.mark.parametrize("func", ["euler_to_matrix", "matrix_to_euler"])
def test_bad_euler_convention_raises(func, convention):
    arg = _z(3) if func == "euler_to_matrix" else torch.eye(3, dtype=F64)
    msg = f"{func}(): 'convention' must be a Tait-Bryan sequence"
    with pytest.raises(ValueError, match=re.escape(msg)):
        getattr(g, func)(arg, convention)


@pytest.mark.parametrize("func", ["euler_to_matrix", "matrix_to_euler"])
def test_non_string_euler_convention_raises_type_error(func):
    arg = _z(3) if func == "euler_to_matrix" else torch.eye(3, dtype=F64)
    msg = f"{func}(): 'convention' must be a string such as 'xyz', got int"
    with pytest.raises(TypeError, match=re.escape(msg)):
        getattr(g, func)(arg, 1)


# ------------------------------------------------------------------------------------------------
# 9. CUDA
# ------------------------------------------------------------------------------------------------


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("dtype", [F32, F64], ids=["f32", "f64"])
def test_cuda_matches_cpu(dtype):
    gen = np.random.default_rng(90)
    r = T(random_rotvecs(gen, (64,), 4 * PI), dtype)
    m = T(Rotation.random(64, random_state=91).as_matrix(), dtype)
    p, q = T(random_poses(gen, (64,)), dtype), T(random_poses(gen, (64,)), dtype)
    d6 = T(gen.normal(size=(64, 6)), dtype)
    cases = [
        (g.so3_exp, (r,)),
        (g.rotvec_to_quat, (r,)),
        (g.regularize_rotvec, (r,)),
        (g.so3_left_jacobian, (r,)),
        (g.so3_log, (m,)),
        (g.matrix_to_quat, (m,)),
        (g.matrix_to_euler, (m,)),
        (g.rotation_6d_to_matrix, (d6,)),
        (g.se3_error, (p, q)),
        (g.se3_group_exp, (p,)),
        (g.se3_group_log, (g.vector_to_se3(p),)),
    ]
    tol = 1e-5 if dtype == F32 else 1e-12
    for fn, args in cases:
        cpu_args = [a.clone().requires_grad_(True) for a in args]
        gpu_args = [a.detach().cuda().requires_grad_(True) for a in args]
        out_cpu, out_gpu = fn(*cpu_args), fn(*gpu_args)
        assert out_gpu.device.type == "cuda" and out_gpu.dtype == dtype, fn.__name__
        torch.testing.assert_close(out_gpu.cpu(), out_cpu, atol=tol, rtol=tol)
        out_cpu.sum().backward()
        out_gpu.sum().backward()
        for a_cpu, a_gpu in zip(cpu_args, gpu_args, strict=True):
            assert torch.isfinite(a_gpu.grad).all(), fn.__name__
            torch.testing.assert_close(a_gpu.grad.cpu(), a_cpu.grad, atol=10 * tol, rtol=10 * tol)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("theta", [0.0, 1e-4, 1e-2, 1.0])
def test_half_precision_small_angles_are_finite_and_accurate(dtype, theta):
    r = torch.tensor([theta, 0.0, 0.0], dtype=dtype, requires_grad=True)
    R = g.so3_exp(r)
    R.sum().backward()
    assert torch.isfinite(R).all() and torch.isfinite(r.grad).all()
    want = Rotation.from_rotvec([theta, 0.0, 0.0]).as_matrix()
    np.testing.assert_allclose(R.detach().double().numpy(), want, atol=4 * torch.finfo(dtype).eps)
    q = g.rotvec_to_quat(r.detach())
    assert torch.isfinite(q).all() and torch.isfinite(g.so3_left_jacobian(r.detach())).all()


def test_rotation_angle_against_scipy() -> None:
    a = Rotation.random(64, random_state=3)
    b = Rotation.random(64, random_state=4)
    expected = (a.inv() * b).magnitude()
    ma = torch.from_numpy(a.as_matrix())
    mb = torch.from_numpy(b.as_matrix())
    assert torch.allclose(g.rotation_angle(ma, mb), torch.from_numpy(expected), atol=1e-9)
    # Rigid transforms: the rotation parts only; the identity and a half turn.
    ta, tb = (
        torch.eye(4, dtype=torch.float64).repeat(64, 1, 1),
        torch.eye(4).double().repeat(64, 1, 1),
    )
    ta[:, :3, :3], tb[:, :3, :3] = ma, mb
    ta[:, :3, 3] = 50.0
    assert torch.allclose(g.rotation_angle(ta, tb), torch.from_numpy(expected), atol=1e-9)
    assert float(g.rotation_angle(ma[0], ma[0])) < 1e-6
    half = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    assert abs(float(g.rotation_angle(torch.eye(3, dtype=torch.float64), half)) - math.pi) < 1e-9
    with pytest.raises(ValueError, match="'a'"):
        g.rotation_angle(torch.eye(2), torch.eye(3))


def test_half_turns_are_180_degrees_about_x_y_z() -> None:
    """Oracle: scipy's rotation by pi about each axis; a half turn is its own inverse and, applied
    on the left, turns a pose about the axis of the frame it maps into."""
    turns = g.half_turns()
    assert turns.shape == (3, 4, 4) and turns.dtype == torch.float64
    for turn, axis in zip(turns, "xyz", strict=True):
        expected = Rotation.from_euler(axis, 180, degrees=True).as_matrix()
        np.testing.assert_allclose(turn[:3, :3].numpy(), expected, atol=1e-12)
        assert torch.equal(turn[:3, 3], torch.zeros(3, dtype=torch.float64))
        assert torch.equal(turn[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64))
        torch.testing.assert_close(g.se3_compose(turn, turn), torch.eye(4, dtype=torch.float64))
    pose = torch.from_numpy(Rotation.random(random_state=4).as_matrix())
    moved = g.se3_compose(turns[2], torch.block_diag(pose, torch.ones(1, dtype=torch.float64)))
    np.testing.assert_allclose(
        moved[:3, :3].numpy(),
        (
            Rotation.from_euler("z", 180, degrees=True) * Rotation.from_matrix(pose.numpy())
        ).as_matrix(),
        atol=1e-12,
    )
    assert g.half_turns(torch.float32).dtype == torch.float32
