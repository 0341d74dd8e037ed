"""Scanner artefacts of simulated thick-slice stacks (:func:`svr.sampling.simulate.simulate_case`).

A smooth multiplicative bias field over the brain, signal voids (dark blobs on some slices) and
Rician noise, drawn in that order from one generator by :func:`stack_artefacts`; and the errors
of an automatic brain mask on a whole-uterus scan (:func:`loose_mask`).
"""

from __future__ import annotations

import torch
from scipy import ndimage
from torch import Tensor
from torch.nn import functional

__all__ = ["bias_field", "loose_mask", "rician_noise", "signal_voids", "stack_artefacts"]


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


def loose_mask(
    mask: Tensor,
    data: Tensor,
    spacing_mm: Tensor,
    reach_mm: float,
    generator: torch.Generator,
    tissue: tuple[float, float] = (0.2, 2.0),
) -> tuple[Tensor, Tensor]:
    """An automatic mask's errors: its edge moved in and out by a smooth field, tissue taken in.

    An automatic mask on a whole-uterus scan misses a rim of the brain in one place and takes in
    fluid or tissue beside the head in another (more end slices, a wedge below the brain). Its
    edge is put where the signed distance to the true edge equals a smooth random field (a
    4 x 4 x 4 grid of values of random sign and size 0.3-1 times 0.5-1 of ``reach_mm``,
    interpolated over the stack, plus an offset up to a quarter of that), so that it lies out
    in some places and in in others; the voxels it takes in outside the brain are filled with a
    tissue of random brightness (``tissue``, relative to the brain's median) and 15 % noise.

    Args:
        mask: (I, J, K) bool true brain mask on the stack's grid (CPU, as ``data``).
        data: (I, J, K) float stack intensities on the same grid (0 outside the brain where the
            source brain was skull-stripped).
        spacing_mm: (3,) voxel sizes along I, J, K, mm (the signed distance is in mm).
        reach_mm: The field's largest value, mm (> 0).
        generator: Source of every draw.
        tissue: (low, high) brightness range of what the mask takes in, relative to the brain's
            median intensity.

    Returns:
        ``(mask, data)``: the (I, J, K) bool loose mask, and the intensities with the tissue it
        takes in filled (``data`` itself where it takes in nothing outside the brain).

    Raises:
        ValueError: If ``reach_mm`` is not > 0 or the shapes differ.
    """
    if not reach_mm > 0:
        raise ValueError(f"loose_mask(): 'reach_mm' must be > 0, got {reach_mm}")
    if mask.shape != data.shape or mask.dim() != 3:
        raise ValueError(
            f"loose_mask(): 'mask' and 'data' must be the same (I, J, K) shape, got "
            f"{tuple(mask.shape)} and {tuple(data.shape)}"
        )
    brain = mask.bool()
    if not bool(brain.any()):
        return brain, data
    sampling = spacing_mm.double().tolist()
    inside = brain.numpy()
    signed = ndimage.distance_transform_edt(~inside, sampling=sampling) - (
        ndimage.distance_transform_edt(inside, sampling=sampling)
    )
    amplitude = reach_mm * (0.5 + 0.5 * float(torch.rand(1, generator=generator)))
    sign = torch.randint(2, (1, 1, 4, 4, 4), generator=generator).double() * 2 - 1
    coarse = sign * (
        0.3 + 0.7 * torch.rand(1, 1, 4, 4, 4, generator=generator, dtype=torch.float64)
    )
    offset = (float(torch.rand(1, generator=generator)) * 2 - 1) * 0.25 * amplitude
    field = functional.interpolate(coarse, size=tuple(mask.shape), mode="trilinear")[0, 0]
    loose = torch.from_numpy(signed < (field * amplitude + offset).numpy())
    taken = loose & ~brain
    if not bool(taken.any()):
        return loose, data
    low, high = tissue
    level = float(data[brain].median()) * (
        low + (high - low) * float(torch.rand(1, generator=generator))
    )
    noise = torch.randn(data.shape, generator=generator, dtype=torch.float64).to(data.dtype)
    filled = data.clone()
    filled[taken] = (level * (1 + 0.15 * noise[taken])).clamp(min=0)
    return loose, filled
