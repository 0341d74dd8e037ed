"""The weighted rigid fit (Horn's quaternion method) against scipy, closed forms and gradcheck."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from svr.geometry import RigidFitError, weighted_rigid_fit


def _points(n: int, seed: int) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).normal(size=(n, 3)) * 20.0)


def test_noise_free_points_give_the_exact_pose() -> None:
    x = _points(12, 0)
    rotation = Rotation.random(random_state=3).as_matrix()
    shift = np.array([3.0, -7.0, 11.0])
    y = x @ torch.from_numpy(rotation).T + torch.from_numpy(shift)
    fit = weighted_rigid_fit(x, y)
    assert torch.allclose(fit[:3, :3], torch.from_numpy(rotation), atol=1e-12)
    assert torch.allclose(fit[:3, 3], torch.from_numpy(shift), atol=1e-10)
    assert torch.equal(fit[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64))


def test_weighted_fit_matches_scipy_align_vectors_on_noisy_points() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(size=(30, 3)) * 15
    rotation = Rotation.random(random_state=5)
    y = rotation.apply(x) + rng.normal(size=(30, 3)) * 2.0
    w = rng.uniform(0.1, 2.0, size=30)
    fit = weighted_rigid_fit(torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(w))
    # scipy's align_vectors(a, b, w) minimises sum w |a - R b|^2 for vectors about the origin;
    # centre both sets on their weighted centroids first.
    cx = (w[:, None] * x).sum(0) / w.sum()
    cy = (w[:, None] * y).sum(0) / w.sum()
    oracle, _ = Rotation.align_vectors(y - cy, x - cx, weights=w)
    assert np.allclose(fit[:3, :3].numpy(), oracle.as_matrix(), atol=1e-10)
    assert np.allclose(fit[:3, 3].numpy(), cy - oracle.apply(cx), atol=1e-9)


def test_a_reflected_set_still_gives_a_proper_rotation() -> None:
    x = _points(10, 2)
    y = x * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)  # a mirror image
    fit = weighted_rigid_fit(x, y)
    assert torch.linalg.det(fit[:3, :3]) == pytest.approx(1.0, abs=1e-12)


def test_batches_fit_independently() -> None:
    x = _points(8, 3).expand(4, 8, 3)
    rotations = torch.from_numpy(Rotation.random(4, random_state=7).as_matrix())
    y = x @ rotations.transpose(1, 2)
    fit = weighted_rigid_fit(x, y)
    assert fit.shape == (4, 4, 4)
    assert torch.allclose(fit[:, :3, :3], rotations, atol=1e-12)


def test_gradcheck_float64() -> None:
    x = _points(9, 4)
    rotation = torch.from_numpy(Rotation.random(random_state=9).as_matrix())
    y = (x @ rotation.T + torch.randn(9, 3, dtype=torch.float64)).requires_grad_(True)
    w = torch.rand(9, dtype=torch.float64).add(0.1).requires_grad_(True)
    xs = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(weighted_rigid_fit, (xs, y, w))


def test_gradients_are_finite_on_an_isotropic_grid_at_a_perfect_fit() -> None:
    # A cubic grid has equal spread in every direction: the SVD's derivative is infinite there.
    axis = torch.arange(4, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    for angle in (0.0, 1e-8, np.pi - 1e-6, np.pi):
        rotation = torch.from_numpy(Rotation.from_rotvec([0.0, 0.0, angle]).as_matrix())
        y = (grid @ rotation.T).requires_grad_(True)
        fit = weighted_rigid_fit(grid, y)
        (fit[:3, :3] * torch.randn(3, 3, dtype=torch.float64)).sum().backward()
        assert torch.isfinite(y.grad).all()
        assert torch.allclose(fit[:3, :3], rotation, atol=1e-9)


@pytest.mark.parametrize(
    ("source", "weights", "message"),
    [
        (torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]), None, "collinear"),
        (torch.zeros(4, 3), None, "collinear"),
        (torch.randn(4, 3), torch.zeros(4), "sum to 0"),
    ],
)
def test_degenerate_point_sets_are_rejected(source, weights, message) -> None:
    with pytest.raises(RigidFitError, match=message):
        weighted_rigid_fit(
            source.double(), source.double(), None if weights is None else weights.double()
        )


def test_bad_arguments_name_themselves() -> None:
    x = torch.randn(5, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="'target'"):
        weighted_rigid_fit(x, torch.randn(6, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="'weights'"):
        weighted_rigid_fit(x, x, torch.ones(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="'weights' must be >= 0"):
        weighted_rigid_fit(x, x, -torch.ones(5, dtype=torch.float64))
    with pytest.raises(ValueError, match="N >= 3"):
        weighted_rigid_fit(x[:2], x[:2])
