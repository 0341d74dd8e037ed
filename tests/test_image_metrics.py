"""Image-similarity metrics against NumPy / scikit-image oracles and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from skimage.metrics import mean_squared_error, peak_signal_noise_ratio, structural_similarity

from svr.image_metrics import mse, ncc, psnr, ssim


def smooth_pair(rng: np.random.Generator, b: int = 4, size=(24, 20)) -> tuple[np.ndarray, ...]:
    """Two correlated stacks of smooth random slices in roughly [0, 1]."""
    a = gaussian_filter(rng.normal(size=(b, *size)), (0, 2, 2)) * 3 + 0.5
    noise = gaussian_filter(rng.normal(size=(b, *size)), (0, 1, 1))
    return a, a + 0.3 * noise


def t(x: np.ndarray, dtype=torch.float64) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x)).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ncc_matches_corrcoef(rng, dtype):
    a, b = smooth_pair(rng)
    got = ncc(t(a, dtype), t(b, dtype))
    assert got.shape == (4,) and got.dtype == torch.float64
    want = [np.corrcoef(x.ravel(), y.ravel())[0, 1] for x, y in zip(a, b, strict=True)]
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(got.numpy(), want, atol=tol)


def test_ncc_with_mask_matches_corrcoef_of_the_masked_pixels(rng):
    a, b = smooth_pair(rng)
    mask = rng.uniform(size=a.shape) < 0.4
    got = ncc(t(a), t(b), t(mask, torch.bool))
    want = [np.corrcoef(x[m], y[m])[0, 1] for x, y, m in zip(a, b, mask, strict=True)]
    np.testing.assert_allclose(got.numpy(), want, atol=1e-12)


def test_ncc_is_invariant_to_positive_affine_intensity_changes(rng):
    a, b = (t(x) for x in smooth_pair(rng))
    np.testing.assert_allclose(ncc(a, 3 * a + 2).numpy(), 1.0, atol=1e-12)
    np.testing.assert_allclose(ncc(a, -2 * a + 1).numpy(), -1.0, atol=1e-12)
    np.testing.assert_allclose(ncc(2 * a + 5, 0.5 * b - 1).numpy(), ncc(a, b).numpy(), atol=1e-12)


def test_ncc_of_constant_slices_is_zero_and_of_empty_masks_nan(rng):
    a, _ = smooth_pair(rng, b=3)
    b = np.stack([np.full(a.shape[1:], 0.1), np.zeros(a.shape[1:]), a[2]])
    got = ncc(t(a), t(b))
    np.testing.assert_array_equal(got[:2].numpy(), [0.0, 0.0])
    assert got[2] == pytest.approx(1.0)
    mask = torch.ones(a.shape, dtype=torch.bool)
    mask[1] = False
    got = ncc(t(a), t(a), mask)
    assert math.isnan(got[1]) and got[0] == pytest.approx(1.0)


def test_mse_matches_skimage_and_masked_mean(rng):
    a, b = smooth_pair(rng)
    want = [mean_squared_error(x, y) for x, y in zip(a, b, strict=True)]
    np.testing.assert_allclose(mse(t(a), t(b)).numpy(), want, rtol=1e-12)
    mask = rng.uniform(size=a.shape) < 0.5
    want = [np.mean((x[m] - y[m]) ** 2) for x, y, m in zip(a, b, mask, strict=True)]
    np.testing.assert_allclose(mse(t(a), t(b), t(mask, torch.bool)).numpy(), want, rtol=1e-12)
    assert torch.isnan(mse(t(a), t(b), torch.zeros(a.shape, dtype=torch.bool))).all()


def test_psnr_matches_skimage(rng):
    a, b = smooth_pair(rng)
    want = [peak_signal_noise_ratio(x, y, data_range=2.5) for x, y in zip(a, b, strict=True)]
    np.testing.assert_allclose(psnr(t(a), t(b), 2.5).numpy(), want, rtol=1e-12)


def test_psnr_of_known_noise(rng):
    # +-sigma noise has mse sigma^2 exactly, so PSNR = 20 log10(R / sigma).
    a, _ = smooth_pair(rng)
    sigma, data_range = 0.05, 2.0
    b = a + sigma * rng.choice([-1.0, 1.0], size=a.shape)
    np.testing.assert_allclose(
        psnr(t(a), t(b), data_range).numpy(), 20 * np.log10(data_range / sigma), rtol=1e-9
    )


def test_psnr_of_identical_slices_is_capped(rng):
    a, _ = smooth_pair(rng, b=2)
    np.testing.assert_array_equal(psnr(t(a), t(a), 1.0).numpy(), [100.0, 100.0])
    np.testing.assert_array_equal(psnr(t(a), t(a), 1.0, max_db=60.0).numpy(), [60.0, 60.0])


@pytest.mark.parametrize("data_range", [0.0, -1.0, math.inf, math.nan])
def test_bad_data_range_raises(rng, data_range):
    a, b = (t(x) for x in smooth_pair(rng, b=1))
    with pytest.raises(ValueError, match="'data_range'"):
        psnr(a, b, data_range)
    with pytest.raises(ValueError, match="'data_range'"):
        ssim(a, b, data_range)


def test_ssim_matches_skimage_with_the_standard_setting(rng):
    a, b = smooth_pair(rng)
    want = [
        structural_similarity(
            x, y, data_range=3.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
        )
        for x, y in zip(a, b, strict=True)
    ]
    got = ssim(t(a, torch.float32), t(b, torch.float32), 3.0)
    assert got.dtype == torch.float64
    np.testing.assert_allclose(got.numpy(), want, atol=1e-6)
    np.testing.assert_allclose(ssim(t(a), t(a), 3.0).numpy(), 1.0, atol=1e-12)


def test_ssim_of_constant_slices_is_the_luminance_term():
    # With no variance only l(x, y) = (2 x y + C1) / (x^2 + y^2 + C1) is left, C1 = (0.01 L)^2.
    x, y, data_range = 0.3, 0.7, 1.0
    c1 = (0.01 * data_range) ** 2
    a, b = torch.full((1, 16, 16), x), torch.full((1, 16, 16), y)
    want = (2 * x * y + c1) / (x**2 + y**2 + c1)
    assert float(ssim(a, b, data_range)[0]) == pytest.approx(want, rel=1e-6)


def test_bad_shapes_name_the_argument():
    a = torch.zeros(2, 16, 16)
    with pytest.raises(ValueError, match="'a'"):
        ncc(a[0], a[0])
    with pytest.raises(ValueError, match="'b'"):
        mse(a, torch.zeros(2, 16, 15))
    with pytest.raises(ValueError, match="'b'"):
        psnr(a, torch.zeros(2, 1, 16, 16), 1.0)
    with pytest.raises(ValueError, match="'mask'"):
        ncc(a, a, torch.ones(2, 16, 17, dtype=torch.bool))
    with pytest.raises(TypeError, match="'mask'"):
        mse(a, a, torch.ones(2, 16, 16))
    with pytest.raises(TypeError, match="'a'"):
        ssim(a.numpy(), a, 1.0)
    with pytest.raises(TypeError, match="'b'"):
        ncc(a, torch.zeros(2, 16, 16, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"'a'.*11 x 11"):
        ssim(torch.zeros(2, 10, 16), torch.zeros(2, 10, 16), 1.0)
