"""EM outlier weights at pixel and slice level (after Kuklisova-Murgasova et al. 2012).

Pixel level: each residual ``r = y - c A x`` is an inlier ``N(0, sigma^2)`` with probability
``c_in`` or an outlier of uniform density ``m`` (one over the range of the residuals); the pixel
weight is the posterior inlier probability. Slice level: each slice's inlier-weighted RMS
residual is an inlier (a Gaussian started at the median and 1.4826 MAD, at least a quarter of
the median) or an outlier (uniform
over the range of the slices' errors); the slice weight is the posterior inlier probability,
1 for slices whose error is below the inlier mean. A few EM steps are run at each level.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["RobustWeights", "robust_weights"]

# The inlier slices' errors spread by at least this fraction of their median: slices differ in
# content, and a narrower inlier class would reject sound slices.
SLICE_SPREAD_FLOOR = 0.25


@dataclass(frozen=True)
class RobustWeights:
    """Outlier weights.

    Attributes:
        pixel: (P,) posterior inlier probability of each modelled pixel.
        slice: (N,) posterior inlier probability of each slice.
        sigma: Standard deviation of the inlier residuals.
        inlier_fraction: Prior probability of the pixel-level inlier class.
        outlier_density: Density of the pixel-level outlier class (one over the residuals' range).
    """

    pixel: Tensor
    slice: Tensor
    sigma: float
    inlier_fraction: float = 1.0
    outlier_density: float = 0.0

    def pixel_posterior(self, residuals: Tensor) -> Tensor:
        """Inlier probability of further residuals under the fitted pixel-level mixture.

        Args:
            residuals: (B,) residuals of pixels that took no part in the fit.

        Returns:
            (B,) posterior inlier probabilities, in the dtype of ``residuals``.
        """
        g = self.inlier_fraction * _gauss(residuals.to(torch.float64), 0.0, self.sigma**2)
        return (g / (g + (1 - self.inlier_fraction) * self.outlier_density)).to(residuals.dtype)


def _gauss(x: Tensor, mean: float | Tensor, var: float | Tensor) -> Tensor:
    return torch.exp(-0.5 * (x - mean) ** 2 / var) / torch.sqrt(2 * math.pi * torch.as_tensor(var))


def robust_weights(
    residuals: Tensor, slice_of: Tensor, num_slices: int, steps: int = 3
) -> RobustWeights:
    """Pixel- and slice-level inlier probabilities from residuals.

    Args:
        residuals: (P,) ``y - c A x`` at the modelled pixels.
        slice_of: (P,) slice index of each pixel.
        num_slices: N.
        steps: EM iterations at each level.

    Returns:
        The weights.
    """
    r = residuals.to(torch.float64)
    spread = float(r.max() - r.min())
    density = 1.0 / max(spread, 1e-12)
    var = float((r * r).mean()) + 1e-12
    mix = 0.9
    for _ in range(steps):
        g = _gauss(r, 0.0, var)
        p = mix * g / (mix * g + (1 - mix) * density)
        var = float((p * r * r).sum() / p.sum().clamp_min(1e-12)) + 1e-12
        mix = float(p.mean().clamp(0.05, 0.999))
    g = _gauss(r, 0.0, var)
    pixel = mix * g / (mix * g + (1 - mix) * density)

    counts = torch.zeros(num_slices, dtype=torch.float64, device=r.device)
    num = counts.index_add(0, slice_of, pixel * r * r)
    den = counts.index_add(0, slice_of, pixel)
    has_data = den > 0
    error = torch.sqrt(num / den.clamp_min(1e-12))
    slice_w = torch.ones(num_slices, dtype=torch.float64, device=r.device)
    e = error[has_data]
    if e.numel() >= 4:
        # Inliers: a Gaussian around the median error; outliers: uniform over the range.
        mean = float(e.median())
        floor = (SLICE_SPREAD_FLOOR * mean) ** 2 + 1e-12
        spread = max((1.4826 * float((e - mean).abs().median())) ** 2, floor)
        # The outlier class spans at least six inlier standard deviations.
        outlier_density = 1.0 / max(float(e.max() - e.min()), 6 * math.sqrt(spread))
        slice_mix = 0.95
        for _ in range(steps):
            g = slice_mix * _gauss(e, mean, spread)
            q = g / (g + (1 - slice_mix) * outlier_density)
            mean = float((q * e).sum() / q.sum().clamp_min(1e-12))
            spread = max(float((q * (e - mean) ** 2).sum() / q.sum().clamp_min(1e-12)), floor)
            slice_mix = float(q.mean().clamp(0.5, 0.999))
        g = slice_mix * _gauss(e, mean, spread)
        # Slices better than the inlier mean are never outliers.
        slice_w[has_data] = torch.where(e <= mean, 1.0, g / (g + (1 - slice_mix) * outlier_density))
    return RobustWeights(
        pixel.to(residuals.dtype), slice_w.to(residuals.dtype), math.sqrt(var), mix, density
    )
