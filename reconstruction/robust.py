"""EM outlier weights at pixel and slice level (after Kuklisova-Murgasova et al. 2012).

Pixel level: each residual ``r = y - c A x`` is an inlier ``N(0, sigma^2)`` with probability
``c_in`` or an outlier of uniform density ``m`` (one over the range of the residuals); the pixel
weight is the posterior inlier probability. Slice level: each slice's inlier-weighted RMS
residual is an inlier or an outlier of a two-Gaussian mixture; the slice weight is the posterior
inlier probability. A few EM steps are run each time the weights are updated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["RobustWeights", "robust_weights"]


@dataclass(frozen=True)
class RobustWeights:
    """Outlier weights.

    Attributes:
        pixel: (P,) posterior inlier probability of each modelled pixel.
        slice: (N,) posterior inlier probability of each slice.
        sigma: Standard deviation of the inlier residuals.
    """

    pixel: Tensor
    slice: Tensor
    sigma: float


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
        median = float(e.median())
        mad = float((e - median).abs().median()) * 1.4826 + 1e-6
        # Inliers: around the median; outliers: one broad class above it.
        m1, v1 = median, mad**2
        m2, v2 = median + 4 * mad, (4 * mad) ** 2
        c = 0.9
        for _ in range(steps):
            g1 = c * _gauss(e, m1, v1)
            g2 = (1 - c) * _gauss(e, m2, v2) * (e > m1).to(e.dtype)
            q = g1 / (g1 + g2).clamp_min(1e-300)
            m1 = float((q * e).sum() / q.sum().clamp_min(1e-12))
            v1 = max(float((q * (e - m1) ** 2).sum() / q.sum().clamp_min(1e-12)), mad**2 / 4)
            o = 1 - q
            if float(o.sum()) > 1e-6:
                m2 = max(float((o * e).sum() / o.sum()), m1 + mad)
                v2 = max(float((o * (e - m2) ** 2).sum() / o.sum()), v1)
            c = float(q.mean().clamp(0.5, 0.999))
        g1 = c * _gauss(e, m1, v1)
        g2 = (1 - c) * _gauss(e, m2, v2) * (e > m1).to(e.dtype)
        slice_w[has_data] = g1 / (g1 + g2).clamp_min(1e-300)
    return RobustWeights(pixel.to(residuals.dtype), slice_w.to(residuals.dtype), math.sqrt(var))
