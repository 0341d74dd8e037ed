"""Pose metrics: rotation, translation, geodesic and Euler-angle errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from oracles import random_poses
from scipy.spatial.transform import Rotation

from svr.metrics import (
    euler_angle_errors_deg,
    geodesic_distance,
    pose_errors,
    rotation_error_rad,
    translation_error_mm,
)


def test_rotation_translation_and_geodesic_against_scipy(rng):
    p, q = random_poses(rng, 30), random_poses(rng, 30)
    theta = (Rotation.from_rotvec(p[:, :3]).inv() * Rotation.from_rotvec(q[:, :3])).magnitude()
    dist = np.linalg.norm(q[:, 3:] - p[:, 3:], axis=1)
    pt, qt = torch.from_numpy(p), torch.from_numpy(q)
    np.testing.assert_allclose(rotation_error_rad(pt, qt).numpy(), theta, rtol=1e-12)
    np.testing.assert_allclose(translation_error_mm(pt, qt).numpy(), dist, rtol=1e-12)
    np.testing.assert_allclose(
        geodesic_distance(pt, qt).numpy(), np.sqrt(theta**2 + dist**2 / 900.0), rtol=1e-12
    )
    z = torch.tensor([4.0, 4, 4, 1, 1, 1], dtype=torch.float64)
    np.testing.assert_allclose(
        geodesic_distance(pt, qt, z).numpy(), np.sqrt(4 * theta**2 + dist**2), rtol=1e-12
    )


def test_euler_errors_single_axis_and_wrap():
    base = np.deg2rad([[30.0, -20.0, 179.0]])
    moved = base + np.deg2rad([[10.0, 0.0, 2.0]])  # z goes past 180 and wraps to -179
    poses = [
        np.concatenate([Rotation.from_euler("xyz", a).as_rotvec(), np.zeros((1, 3))], 1)
        for a in (base, moved)
    ]
    got = euler_angle_errors_deg(*(torch.from_numpy(x) for x in poses))
    np.testing.assert_allclose(got.numpy(), [[10.0, 0.0, 2.0]], atol=1e-9)


def test_pose_errors_bundle(rng):
    p, q = (torch.from_numpy(random_poses(rng, 7)) for _ in range(2))
    out = pose_errors(p, q)
    assert set(out) == {
        "rotation_deg",
        "translation_mm",
        "geodesic",
        "euler_x_deg",
        "euler_y_deg",
        "euler_z_deg",
    }
    assert all(v.shape == (7,) for v in out.values())
    torch.testing.assert_close(out["rotation_deg"], rotation_error_rad(p, q) * 180 / math.pi)


def test_bad_inputs():
    with pytest.raises(ValueError, match="geodesic_distance\\(\\): 'pred'"):
        geodesic_distance(torch.zeros(3, 4), torch.zeros(3, 6))
    with pytest.raises(ValueError, match="'weights'"):
        geodesic_distance(torch.zeros(3, 6), torch.zeros(3, 6), torch.ones(4))
