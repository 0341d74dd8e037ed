"""Small synthetic brains for tests: a textured ellipsoid and its mask, and the smallest phantom."""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from svr.image import Image
from svr.sampling.phantom import gestational_age_config, make_phantom


def ellipsoid_brain(
    n: int,
    spacing: float,
    semi_axes_mm: tuple[float, float, float],
    seed: int,
    texture: float = 2.0,
    smoothing: float = 2.0,
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[Image, Image]:
    """An n^3 grid at ``spacing`` mm holding an ellipsoid of smooth random texture.

    Returns:
        ``(volume, mask)``: float32 images whose voxel (0, 0, 0) sits at ``origin_mm``.
    """
    rng = np.random.default_rng(seed)
    grid = (np.indices((n, n, n)) - (n - 1) / 2) * spacing
    r = np.sqrt(sum((g / a) ** 2 for g, a in zip(grid, semi_axes_mm, strict=True)))
    mask = r < 1
    data = mask * (1 + texture * gaussian_filter(rng.normal(size=(n, n, n)), smoothing)).clip(0)
    affine = torch.diag(torch.tensor([spacing, spacing, spacing, 1.0], dtype=torch.float64))
    affine[:3, 3] = torch.tensor(origin_mm, dtype=torch.float64)
    return (
        Image(torch.from_numpy(data).float(), affine),
        Image(torch.from_numpy(mask).float(), affine.clone()),
    )


def small_phantom() -> tuple[Image, Image]:
    """The built-in phantom at GA 20 on a 36^3 grid at 2 mm, ``(volume, mask)``: fast commands."""
    return make_phantom(gestational_age_config(20, spacing_mm=2.0, shape=(36, 36, 36)))
