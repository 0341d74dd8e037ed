"""Slice augmentation: config validation, drawing, identity, gamma, bias field, noise, shifts."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from svr.sampling.augment import (
    AugmentParams,
    SliceAugmentConfig,
    apply_augment,
    bias_field,
    draw_augment_params,
    shift_poses,
)


def smooth_slices(b: int = 4, size: tuple[int, int] = (32, 40), seed: int = 0) -> torch.Tensor:
    """Non-negative slices with a zero background border, like masked MRI slices."""
    g = torch.Generator().manual_seed(seed)
    p = torch.linspace(-1, 1, size[0])[:, None]
    q = torch.linspace(-1, 1, size[1])[None, :]
    inside = (p**2 + q**2) < 0.6
    x = torch.rand(b, 1, 1, generator=g) + 0.5 + 0.3 * torch.sin(3 * p + 2 * q)
    return torch.where(inside, x, torch.zeros(()))


def with_changes(params: AugmentParams, **changes: torch.Tensor) -> AugmentParams:
    fields = {
        name: getattr(params, name)
        for name in ("scale", "gamma", "bias_coefficients", "noise_sigma", "noise_seed")
    }
    fields.update(changes)
    return AugmentParams(**fields)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("scale_prob", 1.5),
        ("gamma_prob", -0.1),
        ("bias_prob", float("nan")),
        ("noise_prob", True),
        ("scale_range", (1.2, 0.8)),
        ("scale_range", (0.0, 1.0)),
        ("gamma_range", (0.5,)),
        ("gamma_range", (0.5, float("inf"))),
        ("bias_order", 0),
        ("bias_order", 2.0),
        ("bias_coefficient_max", -0.1),
        ("noise_sigma_max", float("nan")),
    ],
)
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        SliceAugmentConfig(**{field: value})


def test_draw_is_deterministic_and_in_range():
    config = SliceAugmentConfig(scale_prob=1, gamma_prob=1, bias_prob=1, noise_prob=1)
    a = draw_augment_params(config, 64, torch.Generator().manual_seed(3))
    b = draw_augment_params(config, 64, torch.Generator().manual_seed(3))
    c = draw_augment_params(config, 64, torch.Generator().manual_seed(4))
    for name in ("scale", "gamma", "bias_coefficients", "noise_sigma", "noise_seed"):
        assert torch.equal(getattr(a, name), getattr(b, name))
        assert not torch.equal(getattr(a, name), getattr(c, name))
    assert a.scale.shape == (64,) and a.scale.dtype == torch.float64
    assert a.bias_coefficients.shape == (64, 4, 4) and a.noise_seed.dtype == torch.int64
    assert ((a.scale >= 0.8) & (a.scale <= 1.25)).all()
    assert ((a.gamma >= 0.7) & (a.gamma <= 1.4)).all()
    assert ((a.noise_sigma >= 0) & (a.noise_sigma <= 0.03)).all()
    assert a.bias_coefficients.abs().max() <= 0.3
    degree = torch.arange(4)
    outside = (degree[:, None] + degree[None, :] == 0) | (degree[:, None] + degree[None, :] > 3)
    assert (a.bias_coefficients[:, outside] == 0).all()
    assert (a.bias_coefficients[:, ~outside] != 0).all()


def test_zero_probabilities_draw_the_identity():
    config = SliceAugmentConfig(scale_prob=0, gamma_prob=0, bias_prob=0, noise_prob=0)
    params = draw_augment_params(config, 8, torch.Generator().manual_seed(0))
    identity = AugmentParams.identity(8)
    for name in ("scale", "gamma", "bias_coefficients", "noise_sigma"):
        assert torch.equal(getattr(params, name), getattr(identity, name))


def test_probabilities_are_respected():
    config = SliceAugmentConfig(scale_prob=0.25, gamma_prob=0.5, bias_prob=0.75, noise_prob=1.0)
    p = draw_augment_params(config, 4000, torch.Generator().manual_seed(1))
    applied = [
        (p.scale != 1).double().mean(),
        (p.gamma != 1).double().mean(),
        p.bias_coefficients.flatten(1).ne(0).any(1).double().mean(),
        (p.noise_sigma > 0).double().mean(),
    ]
    np.testing.assert_allclose([float(a) for a in applied], [0.25, 0.5, 0.75, 1.0], atol=0.03)


def test_identity_params_give_identity():
    x = smooth_slices()
    assert torch.equal(apply_augment(x, AugmentParams.identity(4)), x)


def test_apply_is_deterministic_and_does_not_modify_input():
    x = smooth_slices()
    params = draw_augment_params(
        SliceAugmentConfig(scale_prob=1, gamma_prob=1, bias_prob=1, noise_prob=1),
        4,
        torch.Generator().manual_seed(5),
    )
    before = x.clone()
    y1, y2 = apply_augment(x, params), apply_augment(x, params)
    assert torch.equal(y1, y2) and torch.equal(x, before)
    assert y1.shape == x.shape and y1.dtype == x.dtype
    assert not torch.allclose(y1, x)


def test_scale_multiplies():
    x = smooth_slices()
    scale = torch.tensor([0.5, 1.0, 2.0, 1.25], dtype=torch.float64)
    y = apply_augment(x, with_changes(AugmentParams.identity(4), scale=scale))
    torch.testing.assert_close(y, x * scale[:, None, None].float())


def test_gamma_keeps_zeros_and_maximum():
    x = smooth_slices()
    gamma = torch.tensor([0.5, 2.0, 1.0, 1.3], dtype=torch.float64)
    y = apply_augment(x, with_changes(AugmentParams.identity(4), gamma=gamma))
    assert (y[x == 0] == 0).all()
    torch.testing.assert_close(y.flatten(1).amax(1), x.flatten(1).amax(1))
    peak = x.flatten(1).amax(1)[:, None, None]
    torch.testing.assert_close(y, peak * (x / peak) ** gamma[:, None, None].float())
    assert torch.equal(y[2], x[2])


def test_gamma_leaves_all_zero_slices_unchanged():
    x = torch.zeros(2, 8, 8)
    y = apply_augment(x, with_changes(AugmentParams.identity(2), gamma=torch.full((2,), 2.0)))
    assert torch.equal(y, x)


def test_bias_field_is_smooth_positive_with_mean_one():
    params = draw_augment_params(
        SliceAugmentConfig(bias_prob=1.0), 16, torch.Generator().manual_seed(2)
    )
    field = bias_field(params.bias_coefficients, (64, 48), torch.float64)
    assert field.shape == (16, 64, 48)
    assert (field > 0).all()
    torch.testing.assert_close(field.mean(dim=(1, 2)), torch.ones(16, dtype=torch.float64))
    log_field = field.log()
    # a polynomial of degree <= 3: its 4th differences vanish along both axes
    assert log_field.diff(n=4, dim=1).abs().max() < 1e-9
    assert log_field.diff(n=4, dim=2).abs().max() < 1e-9
    # and it varies slowly from pixel to pixel, but does vary
    assert log_field.diff(dim=1).abs().max() < 0.2
    assert log_field.diff(dim=2).abs().max() < 0.2
    assert (field.flatten(1).amax(1) / field.flatten(1).amin(1) > 1.05).all()


def test_bias_field_matches_closed_form():
    c = torch.zeros(1, 3, 3, dtype=torch.float64)
    c[0, 1, 0], c[0, 0, 2] = 0.2, -0.1  # 0.2 P1(p) - 0.1 P2(q)
    p = torch.linspace(-1, 1, 5, dtype=torch.float64)[:, None]
    q = torch.linspace(-1, 1, 7, dtype=torch.float64)[None, :]
    expected = torch.exp(0.2 * p - 0.1 * (1.5 * q**2 - 0.5))
    expected = expected / expected.mean()
    torch.testing.assert_close(bias_field(c, (5, 7), torch.float64)[0], expected)
    x = smooth_slices(1, (5, 7)).double()
    y = apply_augment(x, with_changes(AugmentParams.identity(1, bias_order=2), bias_coefficients=c))
    torch.testing.assert_close(y, x * expected)


def test_noise_level_scales_with_sigma():
    x = torch.full((2, 96, 96), 2.0)
    seeds = torch.tensor([11, 11])
    sigma = torch.tensor([0.01, 0.04], dtype=torch.float64)
    params = with_changes(AugmentParams.identity(2), noise_sigma=sigma, noise_seed=seeds)
    y = apply_augment(x, params)
    std = (y - x).flatten(1).std(1)
    # sigma is relative to the 99th percentile (2.0 here); Rician ~ Gaussian at high SNR
    np.testing.assert_allclose(std.numpy(), 2.0 * sigma.numpy(), rtol=0.05)
    assert float(std[1] / std[0]) == pytest.approx(4.0, rel=1e-3)
    assert (y >= 0).all()


def test_rician_noise_in_background_is_positive():
    x = smooth_slices(1, (64, 64))
    params = with_changes(
        AugmentParams.identity(1),
        noise_sigma=torch.tensor([0.05], dtype=torch.float64),
        noise_seed=torch.tensor([3]),
    )
    y = apply_augment(x, params)
    background = y[x == 0]
    assert (background > 0).all()
    ref = torch.quantile(x.flatten(), 0.99)
    # Rayleigh background: mean = s sqrt(pi / 2)
    assert float(background.mean()) == pytest.approx(
        0.05 * float(ref) * math.sqrt(math.pi / 2), rel=0.1
    )


def test_apply_rejects_bad_inputs():
    with pytest.raises(ValueError, match="slices"):
        apply_augment(torch.zeros(2, 1, 8, 8), AugmentParams.identity(2))
    with pytest.raises(ValueError, match="params"):
        apply_augment(torch.zeros(3, 8, 8), AugmentParams.identity(2))
    with pytest.raises(ValueError, match="gamma"):
        with_changes(AugmentParams.identity(2), gamma=torch.ones(3))
    with pytest.raises(ValueError, match="batch"):
        draw_augment_params(SliceAugmentConfig(), -1, torch.Generator())
    with pytest.raises(TypeError, match="generator"):
        draw_augment_params(SliceAugmentConfig(), 2, None)


def test_shift_poses_moves_the_origin_in_plane():
    rng = np.random.default_rng(0)
    rotvec = Rotation.random(10, random_state=rng).as_rotvec()
    poses = torch.from_numpy(np.concatenate([rotvec, rng.normal(size=(10, 3)) * 5], 1))
    shifts = torch.from_numpy(rng.uniform(-3, 3, size=(10, 2)))
    shifted = shift_poses(poses, shifts)
    R = Rotation.from_rotvec(rotvec).as_matrix()
    expected_t = poses[:, 3:].numpy() + np.einsum("nij,nj->ni", R[:, :, :2], shifts.numpy())
    np.testing.assert_allclose(shifted[:, 3:].numpy(), expected_t, atol=1e-12)
    assert torch.equal(shifted[:, :3], poses[:, :3])
    # the normal offset t . n is unchanged
    normal = torch.from_numpy(R[:, :, 2])
    torch.testing.assert_close((shifted[:, 3:] * normal).sum(1), (poses[:, 3:] * normal).sum(1))
    with pytest.raises(ValueError, match="shifts_mm"):
        shift_poses(poses, shifts[:, :1])
