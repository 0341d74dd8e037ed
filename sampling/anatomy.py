"""Training brains whose anatomy and contrast differ from the atlas's: label-edited variants.

The training atlas (spina bifida aperta, Fidon et al. 2021) has large lateral ventricles and a
small, low cerebellum at every age; a typical clinical fetus has neither. A stack-pose network
trained on those brains alone learned cues that turned round on a real scan without spina bifida
(the front-back twin of each stack scored higher than the right frame on three of its six
stacks). A variant is the atlas brain with its tissue labels edited and its intensities re-drawn
per label:

* the ventricles shrunk by a random depth (the voxels within it of their edge become white
  matter);
* the cerebellum grown by a random depth into the neighbouring extra-axial CSF, brainstem and
  white matter;
* each label's intensity the atlas's median for it times a random factor near 1 (T2-like), or,
  with probability ``random_contrast_probability``, a random level in (0.1, 1) (SynthSeg-style
  domain randomisation); the atlas's own texture (its deviation from its label's median) is kept
  and the result blurred slightly, so that edited edges are not sharper than the atlas's.

The brain mask is unchanged. Labels follow the atlas's parcellation
(``parcellation.nii.gz``: 1 white matter, 2 ventricles, 3 cerebellum, 4 extra-axial CSF, 5
cortical grey matter, 6 deep grey matter, 7 brainstem, 8 corpus callosum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from svr.image import Image
from svr.validation import (
    check_fraction,
    check_instance,
    check_int,
    check_int_tuple,
    check_number,
    check_range,
    is_integer,
)

__all__ = ["AnatomyVariantConfig", "AtlasLabels", "anatomy_variant"]


@dataclass(frozen=True)
class AtlasLabels:
    """The parcellation's label values of the tissues a variant edits.

    Attributes:
        white_matter: Where shrunk ventricles go.
        ventricles: The lateral (and other) ventricles.
        cerebellum: The cerebellum.
        grows_into: Labels the cerebellum may grow into.

    Raises:
        ConfigFieldError: On construction, naming the field, for a label that is not an
            integer >= 1.
    """

    white_matter: int = 1
    ventricles: int = 2
    cerebellum: int = 3
    grows_into: tuple[int, ...] = (1, 4, 7)

    def __post_init__(self) -> None:
        owner = "AtlasLabels"
        for name in ("white_matter", "ventricles", "cerebellum"):
            check_int(owner, name, getattr(self, name), minimum=1)
        value = check_int_tuple(owner, "grows_into", self.grows_into, minimum=1, allow_list=True)
        object.__setattr__(self, "grows_into", value)


@dataclass(frozen=True)
class AnatomyVariantConfig:
    """The ranges a variant is drawn from.

    Attributes:
        ventricle_shrink_mm: (low, high) depth the ventricles are shrunk by (mm).
        cerebellum_grow_mm: (low, high) depth the cerebellum is grown by (mm).
        intensity_jitter: Each label's T2-like level is its atlas median times a factor in
            ``1 +- intensity_jitter``.
        random_contrast_probability: Probability that every label gets a random level in
            (0.1, 1) times the brain's 99th percentile instead.
        blur_mm: Standard deviation of the final Gaussian blur (mm; 0 for none).
        labels: The parcellation's label values.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value out of range.
    """

    ventricle_shrink_mm: tuple[float, float] = (0.0, 8.0)
    cerebellum_grow_mm: tuple[float, float] = (0.0, 3.0)
    intensity_jitter: float = 0.15
    random_contrast_probability: float = 0.5
    blur_mm: float = 0.5
    labels: AtlasLabels = AtlasLabels()

    def __post_init__(self) -> None:
        owner = "AnatomyVariantConfig"
        for name in ("ventricle_shrink_mm", "cerebellum_grow_mm"):
            value = check_range(owner, name, getattr(self, name), ge=0, allow_list=True)
            object.__setattr__(self, name, value)
        check_number(owner, "intensity_jitter", self.intensity_jitter, ge=0, lt=1)
        check_fraction(owner, "random_contrast_probability", self.random_contrast_probability)
        check_number(owner, "blur_mm", self.blur_mm, ge=0)
        check_instance(owner, "labels", self.labels, AtlasLabels)


def _within(region: np.ndarray, depth_mm: float, spacing: tuple[float, ...]) -> np.ndarray:
    """Voxels of ``region`` closer than ``depth_mm`` to its outside."""
    if depth_mm <= 0 or not region.any():
        return np.zeros_like(region)
    return region & (ndimage.distance_transform_edt(region, sampling=spacing) <= depth_mm)


def _near(region: np.ndarray, depth_mm: float, spacing: tuple[float, ...]) -> np.ndarray:
    """Voxels outside ``region`` closer than ``depth_mm`` to it."""
    if depth_mm <= 0 or not region.any():
        return np.zeros_like(region)
    return ~region & (ndimage.distance_transform_edt(~region, sampling=spacing) <= depth_mm)


def anatomy_variant(
    volume: Image,
    mask: torch.Tensor,
    labels: torch.Tensor,
    config: AnatomyVariantConfig | None = None,
    seed: int = 0,
) -> Image:
    """A brain with edited anatomy and re-drawn contrast (module docstring).

    Args:
        volume: (I, J, K) intensities (e.g. an atlas ``srr.nii.gz``); its affine gives the
            voxel spacing.
        mask: (I, J, K) brain mask on the same grid (bool, or > 0.5 is brain).
        labels: (I, J, K) tissue labels on the same grid (integers, 0 outside the brain).
        config: The ranges; ``None`` for ``AnatomyVariantConfig()``.
        seed: Seed of every random choice (a variant is a pure function of its inputs and
            seed), >= 0.

    Returns:
        The variant's intensities on ``volume``'s grid (float32, 0 outside the mask), to be
        canonicalised with the same mask.

    Raises:
        ValueError: If the grids' shapes differ, ``labels`` holds non-integers or negative
            values, or ``seed`` is negative.
    """
    cfg = AnatomyVariantConfig() if config is None else config
    if not (is_integer(seed) and seed >= 0):
        raise ValueError(f"anatomy_variant(): 'seed' must be an integer >= 0, got {seed!r}")
    shape = tuple(volume.shape)
    for name, value in (("mask", mask), ("labels", labels)):
        if tuple(value.shape) != shape:
            raise ValueError(
                f"anatomy_variant(): '{name}' must have the volume's shape {shape}, "
                f"got {tuple(value.shape)}"
            )
    tissue = labels.detach().cpu().numpy()
    if not np.array_equal(tissue, np.round(tissue)) or (tissue < 0).any():
        raise ValueError("anatomy_variant(): 'labels' must be integers >= 0")
    tissue = tissue.astype(np.int64)
    brain = (mask.detach().cpu().numpy() > 0.5) if mask.dtype != torch.bool else mask.cpu().numpy()
    image = volume.data.detach().cpu().numpy().astype(np.float64)
    spacing = tuple(float(s) for s in volume.affine[:3, :3].norm(dim=0).tolist())
    rng = np.random.default_rng(seed)
    names = cfg.labels

    count = int(tissue.max()) + 1
    median = np.zeros(count)
    for label in range(1, count):
        inside = (tissue == label) & brain
        median[label] = float(np.median(image[inside])) if inside.any() else 0.0
    texture = np.where(brain, image - median[tissue], 0.0)

    edited = tissue.copy()
    shrink = rng.uniform(*cfg.ventricle_shrink_mm)
    edited[_within(tissue == names.ventricles, shrink, spacing)] = names.white_matter
    grow = rng.uniform(*cfg.cerebellum_grow_mm)
    around = _near(tissue == names.cerebellum, grow, spacing)
    edited[around & np.isin(tissue, names.grows_into) & brain] = names.cerebellum

    top = float(np.percentile(image[brain], 99)) if brain.any() else 1.0
    if rng.uniform() < cfg.random_contrast_probability:
        level = rng.uniform(0.1, 1.0, size=count) * top
    else:
        level = median * rng.uniform(1 - cfg.intensity_jitter, 1 + cfg.intensity_jitter, count)
    out = level[edited] + texture
    if cfg.blur_mm > 0:
        out = ndimage.gaussian_filter(out, [cfg.blur_mm / s for s in spacing])
    out = np.where(brain, np.clip(out, 0.0, None), 0.0)
    return Image(torch.from_numpy(out.astype(np.float32)), volume.affine.clone())
