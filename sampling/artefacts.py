"""Scanner artefacts of simulated thick-slice stacks (:func:`svr.sampling.simulate.simulate_case`).

A smooth multiplicative bias field over the brain, signal voids (dark blobs on some slices) and
Rician noise, drawn in that order from one generator by :func:`stack_artefacts`.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["bias_field", "rician_noise", "signal_voids", "stack_artefacts"]


def bias_field(
    points: Tensor, strength: float, generator: torch.Generator, radius: float
) -> Tensor:
    """A smooth multiplicative field: exp of a random quadratic polynomial, at points.

    Args:
        points: (..., 3) points relative to the brain centre, mm.
        strength: Scale of the polynomial's 9 coefficients (standard deviation ``strength / 3``).
        generator: Source of the coefficients.
        radius: The brain's radius, mm (points are divided by it).

    Returns:
        (...) field values, in ``points``' dtype.
    """
    x = points / radius
    coeffs = torch.randn(9, generator=generator, dtype=torch.float64) * strength / 3
    terms = torch.stack(
        [
            x[..., 0],
            x[..., 1],
            x[..., 2],
            x[..., 0] ** 2,
            x[..., 1] ** 2,
            x[..., 2] ** 2,
            x[..., 0] * x[..., 1],
            x[..., 1] * x[..., 2],
            x[..., 0] * x[..., 2],
        ],
        -1,
    )
    return torch.exp(terms.to(torch.float64) @ coeffs).to(points.dtype)


def rician_noise(slices: Tensor, sigma: float, generator: torch.Generator) -> Tensor:
    """Rician noise: the magnitude of ``slices`` plus complex Gaussian noise of ``sigma``.

    Args:
        slices: (K, H, W) intensities.
        sigma: Standard deviation of each Gaussian component, in intensity units.
        generator: Source of the noise (two draws of ``slices``' shape).

    Returns:
        (K, H, W) noisy intensities (>= 0).
    """
    n1 = torch.randn(slices.shape, generator=generator, dtype=slices.dtype) * sigma
    n2 = torch.randn(slices.shape, generator=generator, dtype=slices.dtype) * sigma
    return ((slices + n1).square() + n2.square()).sqrt()


def signal_voids(slices: Tensor, probability: float, generator: torch.Generator) -> Tensor:
    """Dark Gaussian blobs (down to 10 % of the signal) on a random share of the slices.

    Args:
        slices: (K, H, W) intensities.
        probability: Chance of a void per slice.
        generator: Source of which slices, and of each void's centre and radius (pixels).

    Returns:
        (K, H, W) intensities (``slices`` itself when no slice has a void).
    """
    b, h, w = slices.shape
    hit = torch.rand(b, generator=generator) < probability
    if not bool(hit.any()):
        return slices
    a = torch.arange(h, dtype=slices.dtype)[:, None]
    c = torch.arange(w, dtype=slices.dtype)[None, :]
    out = slices.clone()
    for i in torch.nonzero(hit).flatten().tolist():
        ca, cc = (torch.rand(2, generator=generator) * torch.tensor([h, w])).tolist()
        r = float(torch.rand(1, generator=generator)) * min(h, w) / 4 + 3
        blob = torch.exp(-((a - ca) ** 2 + (c - cc) ** 2) / (2 * r * r))
        out[i] = slices[i] * (1 - 0.9 * blob)
    return out


def stack_artefacts(
    slices: Tensor,
    planes: Tensor,
    in_plane_mm: float,
    brain_centre: Tensor,
    radius: float,
    bias_strength: float,
    void_probability: float,
    sigma: float | None,
    generator: torch.Generator,
) -> Tensor:
    """The bias field, signal voids and Rician noise of one stack, each only when asked for.

    Args:
        slices: (K, H, W) float32 slices, on the CPU.
        planes: (K, 4, 4) float64 nominal slice-to-scanner poses (where the bias field is
            evaluated), mm.
        in_plane_mm: The slices' pixel spacing, mm.
        brain_centre: (3,) float64 the brain centre in the scanner frame, mm.
        radius: The brain's radius, mm.
        bias_strength: :func:`bias_field`'s ``strength`` (0: none).
        void_probability: :func:`signal_voids`' ``probability`` (0: none).
        sigma: :func:`rician_noise`'s ``sigma`` (``None``: none).
        generator: Source of every draw, in that order.

    Returns:
        (K, H, W) float32 slices.
    """
    if bias_strength > 0:
        h, w = slices.shape[1:]
        u = (torch.arange(h, dtype=torch.float64) - (h - 1) / 2) * in_plane_mm
        v = (torch.arange(w, dtype=torch.float64) - (w - 1) / 2) * in_plane_mm
        grid = (
            planes[:, None, None, :3, 3]
            + u[None, :, None, None] * planes[:, None, None, :3, 0]
            + v[None, None, :, None] * planes[:, None, None, :3, 1]
        ) - brain_centre
        slices = slices * bias_field(grid, bias_strength, generator, radius).float()
    if void_probability > 0:
        slices = signal_voids(slices, void_probability, generator)
    if sigma is not None:
        slices = rician_noise(slices, sigma, generator)
    return slices
