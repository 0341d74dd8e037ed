"""Data-adaptive metric weights diag(cov^-1) and the default weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svr.losses import default_metric_weights, estimate_metric_weights, validate_metric_weights


def test_matches_numpy_inverse_covariance(rng):
    mix = rng.normal(size=(6, 6))
    errors = rng.normal(size=(500, 6)) @ mix
    got = estimate_metric_weights(torch.from_numpy(errors))
    np.testing.assert_allclose(got.numpy(), np.linalg.inv(np.cov(errors.T)).diagonal(), rtol=1e-10)


def test_recovers_known_precisions_and_normalises(rng):
    sigma = np.array([0.05, 0.1, 0.2, 1.0, 2.0, 4.0])
    errors = torch.from_numpy(rng.normal(size=(40000, 6)) * sigma).float()
    got = estimate_metric_weights(errors)
    assert got.dtype == torch.float32
    np.testing.assert_allclose(got.numpy(), 1 / sigma**2, rtol=0.03)
    unit = estimate_metric_weights(errors, normalize=True)
    assert unit.norm().item() == pytest.approx(1.0)
    np.testing.assert_allclose(unit.numpy(), got.numpy() / np.linalg.norm(got.numpy()), rtol=1e-5)


def test_estimated_weights_are_a_valid_inner_product(rng):
    w = estimate_metric_weights(torch.from_numpy(rng.normal(size=(50, 6))))
    assert validate_metric_weights(w) is w


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda e: e[:5], "N >= 7"),
        (lambda e: e[:, :5], r"\(\.\.\., 6\)"),
        (lambda e: e.unsqueeze(0), "shape \\(N, 6\\)"),
        (lambda e: torch.where(e > 2.5, float("nan"), e), "NaN or Inf"),
    ],
)
def test_bad_errors_rejected(rng, make, message):
    errors = torch.from_numpy(rng.normal(size=(100, 6)))
    with pytest.raises(ValueError, match=message):
        estimate_metric_weights(make(errors))


def test_constant_component_is_named(rng):
    errors = torch.from_numpy(rng.normal(size=(100, 6)))
    errors[:, 5] = 0.7
    with pytest.raises(ValueError, match=r"singular.*t_z"):
        estimate_metric_weights(errors)


def test_collinear_components_are_named(rng):
    errors = torch.from_numpy(rng.normal(size=(100, 6)))
    errors[:, 3] = 2.0 * errors[:, 0] - 1.0
    with pytest.raises(ValueError, match=r"r_x, t_x\)"):
        estimate_metric_weights(errors)


def test_default_weights():
    w = default_metric_weights(10.0, dtype=torch.float64)
    np.testing.assert_allclose(w.numpy(), [1, 1, 1, 0.01, 0.01, 0.01])
    assert default_metric_weights().dtype == torch.get_default_dtype()
    with pytest.raises(ValueError, match="'length_scale_mm' must be > 0"):
        default_metric_weights(0.0)
