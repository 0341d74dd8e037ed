"""Batched image-similarity metrics between two stacks of 2D slices.

Every function takes ``a`` and ``b`` as (B, H, W) floating-point tensors of the same shape (slice
``k`` of ``a`` is compared with slice ``k`` of ``b``) and returns one value per slice, a (B,)
float64 tensor on ``a``'s device. The arithmetic is done in float64.

Conventions:
    * ``mask`` (where accepted) is a (B, H, W) bool tensor selecting the pixels that count; a
      slice whose mask selects no pixel gets NaN (there is nothing to compare).
    * :func:`ncc` is the Pearson correlation coefficient. It is undefined when either image is
      constant over the region; such slices get 0 ("no evidence of alignment"), which is also
      what NeSVoR and NiftyMIC assume when they reject slices by NCC. An image counts as
      constant when its standard deviation over the region is at most ``1e-10`` times its
      largest absolute value there (rounding noise, not signal).
    * :func:`mse` is the mean of ``(a - b)^2`` over the region, in squared intensity units.
    * :func:`psnr` is ``10 log10(data_range^2 / mse)`` in dB. ``data_range`` (the span of
      intensities a perfect image could take, e.g. 255 for 8-bit images or the 99.9th percentile
      of a normalised volume) must be given: guessing it from the data makes the numbers
      incomparable between images. Identical images (``mse == 0``) would give +inf, which no
      mean survives; the value is capped at ``max_db`` (100 dB by default) instead.
    * :func:`ssim` is the structural similarity of Wang et al. (2004) with their standard
      setting: Gaussian weighting windows of sigma 1.5 pixels (11 x 11 after truncation at 3.5
      sigma), ``K1 = 0.01``, ``K2 = 0.03`` and population (not sample) covariances, averaged over
      the pixels whose window lies inside the slice, as computed by
      :func:`skimage.metrics.structural_similarity`; slices must be at least 11 x 11.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from skimage.metrics import structural_similarity
from torch import Tensor

SSIM_SIGMA = 1.5
SSIM_MIN_SIZE = 11  # the Gaussian window's width for sigma 1.5 (truncated at 3.5 sigma)
DEFAULT_MAX_PSNR_DB = 100.0
_CONSTANT_RTOL = 1e-10


def _check_pair(a: object, b: object, func: str) -> tuple[Tensor, Tensor]:
    """Check two (B, H, W) floating-point tensors of one shape; return them as float64."""
    for name, x in (("a", a), ("b", b)):
        if not isinstance(x, Tensor):
            raise TypeError(
                f"{func}(): '{name}' must be a torch.Tensor of shape (B, H, W), "
                f"got {type(x).__name__}"
            )
        if not x.is_floating_point():
            raise TypeError(f"{func}(): '{name}' must be a floating-point tensor, got {x.dtype}")
        if x.dim() != 3:
            raise ValueError(f"{func}(): '{name}' must have shape (B, H, W), got {tuple(x.shape)}")
    assert isinstance(a, Tensor) and isinstance(b, Tensor)  # checked above
    if a.shape != b.shape:
        raise ValueError(
            f"{func}(): 'b' must have the shape of 'a' {tuple(a.shape)}, got {tuple(b.shape)}"
        )
    return a.to(torch.float64), b.to(device=a.device, dtype=torch.float64)


def _weights(mask: object, a: Tensor, func: str) -> Tensor:
    """The mask as float64 0/1 weights (all ones when ``mask`` is None)."""
    if mask is None:
        return torch.ones_like(a)
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise TypeError(f"{func}(): 'mask' must be a bool torch.Tensor of shape (B, H, W)")
    if mask.shape != a.shape:
        raise ValueError(
            f"{func}(): 'mask' must have the shape of 'a' {tuple(a.shape)}, got {tuple(mask.shape)}"
        )
    return mask.to(device=a.device, dtype=torch.float64)


def _check_data_range(data_range: float, func: str) -> float:
    if not (math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"{func}(): 'data_range' must be finite and > 0, got {data_range}")
    return float(data_range)


def ncc(a: Tensor, b: Tensor, mask: Tensor | None = None) -> Tensor:
    """Pearson correlation coefficient of each pair of slices.

    Args:
        a: (B, H, W) slices.
        b: (B, H, W) slices.
        mask: Optional (B, H, W) bool tensor of the pixels to use.

    Returns:
        (B,) float64 correlations in [-1, 1]; 0 where either slice is constant over the region,
        NaN where the mask is empty.

    Raises:
        TypeError: If an argument is not a (floating-point / bool) tensor.
        ValueError: If a shape is wrong, naming the argument.
    """
    a, b = _check_pair(a, b, "ncc")
    w = _weights(mask, a, "ncc")
    n = w.sum(dim=(1, 2))
    safe_n = n.clamp(min=1.0)[:, None, None]
    da = (a - (w * a).sum(dim=(1, 2))[:, None, None] / safe_n) * w
    db = (b - (w * b).sum(dim=(1, 2))[:, None, None] / safe_n) * w
    ss_a, ss_b = da.square().sum(dim=(1, 2)), db.square().sum(dim=(1, 2))
    cov = (da * db).sum(dim=(1, 2))

    def constant(ss: Tensor, x: Tensor) -> Tensor:
        peak = (x * w).abs().amax(dim=(1, 2))
        return ss <= n * (_CONSTANT_RTOL * peak).square()

    degenerate = constant(ss_a, a) | constant(ss_b, b)
    r = cov / (ss_a * ss_b).sqrt().where(~degenerate, torch.ones_like(cov))
    r = r.where(~degenerate, torch.zeros_like(r)).clamp(-1.0, 1.0)
    return r.where(n > 0, torch.full_like(r, math.nan))


def mse(a: Tensor, b: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean squared difference of each pair of slices.

    Args:
        a: (B, H, W) slices.
        b: (B, H, W) slices.
        mask: Optional (B, H, W) bool tensor of the pixels to use.

    Returns:
        (B,) float64 mean squared errors; NaN where the mask is empty.

    Raises:
        TypeError: If an argument is not a (floating-point / bool) tensor.
        ValueError: If a shape is wrong, naming the argument.
    """
    a, b = _check_pair(a, b, "mse")
    w = _weights(mask, a, "mse")
    return ((a - b).square() * w).sum(dim=(1, 2)) / w.sum(dim=(1, 2))


def psnr(
    a: Tensor,
    b: Tensor,
    data_range: float,
    mask: Tensor | None = None,
    max_db: float = DEFAULT_MAX_PSNR_DB,
) -> Tensor:
    """Peak signal-to-noise ratio ``10 log10(data_range^2 / mse)`` of each pair, in dB.

    Args:
        a: (B, H, W) slices (which one is the reference does not matter).
        b: (B, H, W) slices.
        data_range: The intensity span of a perfect image (> 0); not estimated from the data.
        mask: Optional (B, H, W) bool tensor of the pixels to use.
        max_db: Cap on the result, reached by identical slices (which would give +inf).

    Returns:
        (B,) float64 PSNRs in dB, at most ``max_db``; NaN where the mask is empty.

    Raises:
        TypeError: If an argument is not a (floating-point / bool) tensor.
        ValueError: If a shape is wrong (naming the argument) or ``data_range`` is not > 0.
    """
    data_range = _check_data_range(data_range, "psnr")
    err = mse(a, b, mask)
    return (10.0 * torch.log10(data_range**2 / err)).clamp(max=max_db)


def ssim(a: Tensor, b: Tensor, data_range: float) -> Tensor:
    """Mean structural similarity (Wang et al. 2004, Gaussian windows, sigma 1.5) of each pair.

    Args:
        a: (B, H, W) slices, H and W at least 11.
        b: (B, H, W) slices.
        data_range: The intensity span of a perfect image (> 0), the ``L`` of the SSIM
            constants ``C1 = (0.01 L)^2`` and ``C2 = (0.03 L)^2``.

    Returns:
        (B,) float64 SSIMs in [-1, 1] (1 for identical slices).

    Raises:
        TypeError: If an argument is not a floating-point tensor.
        ValueError: If a shape is wrong or the slices are smaller than 11 x 11 (naming the
            argument), or ``data_range`` is not > 0.
    """
    a, b = _check_pair(a, b, "ssim")
    data_range = _check_data_range(data_range, "ssim")
    if min(a.shape[1:]) < SSIM_MIN_SIZE:
        raise ValueError(
            f"ssim(): 'a' slices must be at least {SSIM_MIN_SIZE} x {SSIM_MIN_SIZE} pixels "
            f"(the Gaussian window), got shape {tuple(a.shape)}"
        )
    a_np, b_np = a.cpu().numpy(), b.cpu().numpy()
    values = [
        structural_similarity(
            x,
            y,
            data_range=data_range,
            gaussian_weights=True,
            sigma=SSIM_SIGMA,
            use_sample_covariance=False,
        )
        for x, y in zip(a_np, b_np, strict=True)
    ]
    return torch.from_numpy(np.asarray(values, dtype=np.float64).reshape(-1)).to(a.device)
