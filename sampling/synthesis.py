"""Synthetic T2-like brains from a label map: SynthSeg-style domain randomisation.

A network trained on one atlas family learns that family's contrast. A synthetic brain keeps a
real brain's tissue labels (its geometry) and draws everything else at random, so that the
network has to place a stack by the brain's shape. Two modes:

* ``"labels"``: the intensities come from the parcellation alone. Each label gets a random mean:
  with probability ``t2_like_probability`` a T2-like one (``t2_levels``, the label's level
  relative to the brain's bright end in the Fidon 2021 atlas, raised to a random contrast
  exponent and jittered per label), else uniform in ``mean_range`` (any contrast, the labels'
  order included). Each label has a smooth random texture: its mean times ``1 + s T``, ``T`` a
  smooth unit field of its own (control points ``texture_mm`` apart) and ``s`` drawn per label
  in ``texture``.
* ``"mixed"``: the real image, its intensities remapped per label by a random curve through
  ``curve_knots`` knots over the brain's range: increasing (a monotone remap, the texture's
  order kept) with probability ``monotone_probability``, else with random knot values (a
  non-monotone remap, texture and contrast both changed).

Both then go through the same steps, in this order (each drawn per brain):

1. **Partial volume**: the labels' one-hot maps are blurred (Gaussian, standard deviation drawn
   in ``partial_volume_mm``) before the labels' intensities are mixed by them, so that borders
   between labels are soft as in a real image.
2. **Bias field**: a smooth multiplicative field ``exp(b B)``, ``B`` a smooth unit field on
   ``bias_points`` control points per axis and ``b`` drawn in ``bias``.
3. **Resolution loss**: a Gaussian blur whose standard deviation is drawn per axis in
   ``blur_mm`` (anisotropic, as a thick-slice acquisition).
4. **Rician-like noise**: ``sqrt((y + s n1)^2 + (s n2)^2)``, ``s`` drawn in ``noise`` (relative to
   the brain's 99th percentile).
5. The result is set to 0 outside the brain mask and divided by its in-mask 99th percentile, as
   :func:`svr.sampling.volume.canonicalize` normalises a real brain.

The brain mask and the labels are unchanged unless ``deform_mm`` > 0: then labels, mask and image
are first deformed by a random smooth displacement field with no rigid part
(:func:`svr.sampling.deform.random_displacement`), which changes the anatomy but not the
canonical frame. Every draw comes from one ``torch.Generator``, in a fixed order whatever the
probabilities, so a brain is a pure function of its inputs, the config and the generator's state.
The functions are batched over a leading dimension ``B`` (one draw per brain);
:func:`synthesize_volume` makes one synthetic copy of a
:class:`~svr.sampling.volume.CanonicalVolume` that has labels (cropped to its brain first, for
speed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor
from torch.nn import functional

from svr.image import Image
from svr.sampling.deform import random_displacement, warp_channels
from svr.sampling.volume import CanonicalVolume
from svr.validation import (
    check_choice,
    check_fraction,
    check_int,
    check_number,
    check_number_tuple,
    check_range,
)

__all__ = [
    "SYNTHESIS_MODES",
    "SynthesisConfig",
    "SyntheticBrain",
    "draw_label_means",
    "gaussian_blur",
    "label_maps",
    "remap_per_label",
    "smooth_field",
    "synthesize",
    "synthesize_volume",
]

SYNTHESIS_MODES: tuple[str, ...] = ("labels", "mixed")
"""What a synthetic brain's intensities come from: the labels alone, or the real image remapped."""

FIDON_T2_LEVELS: tuple[float, ...] = (0.63, 0.87, 0.60, 0.83, 0.49, 0.55, 0.51, 0.52)
"""Median T2w intensity of labels 1-8 over the brain's 99th percentile, Fidon 2021 atlas GA 28
(1 white matter, 2 ventricles, 3 cerebellum, 4 extra-axial CSF, 5 cortical grey matter, 6 deep
grey matter, 7 brainstem, 8 corpus callosum)."""

_CROP_MARGIN = 4
"""Voxels kept around the brain's bounding box by :func:`synthesize_volume`."""


@dataclass(frozen=True)
class SynthesisConfig:
    """The ranges a synthetic brain is drawn from (module docstring).

    Attributes:
        mode: ``"labels"`` (intensities from the labels) or ``"mixed"`` (the real image
            remapped per label).
        mean_range: (low, high) of a label's random mean (or a random knot value), relative to
            the brain's bright end; 0 <= low <= high.
        t2_like_probability: Chance that the labels' means are T2-like (``t2_levels``) instead
            of random in ``mean_range``.
        t2_levels: T2-like mean of labels 1, 2, ... (relative levels, > 0); label 0 (brain
            without a label) and labels past the tuple's end get a random mean.
        t2_contrast: (low, high) of the exponent the T2-like levels are raised to (log-uniform;
            > 1 strengthens the contrast).
        t2_jitter: Each T2-like mean is multiplied by a factor in ``1 +- t2_jitter``, in [0, 1).
        texture: (low, high) of each label's relative texture amplitude (standard deviation
            of ``s T``), >= 0.
        texture_mm: Spacing of the texture's control points (mm), > 0.
        partial_volume_mm: (low, high) of the one-hot blur's standard deviation (mm), >= 0.
        bias: (low, high) of the log bias field's standard deviation, >= 0.
        bias_points: Control points per axis of the bias field, >= 2.
        blur_mm: (low, high) of the resolution blur's standard deviation per axis (mm), >= 0.
        noise: (low, high) of the Rician-like noise relative to the bright end, >= 0.
        deform_mm: Standard deviation of the deformation's control values (mm, >= 0; 0 keeps
            the labels' geometry).
        monotone_probability: ``"mixed"``: chance of an increasing remap per brain.
        curve_knots: ``"mixed"``: knots of each label's remap curve, >= 2.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    mode: str = "labels"
    mean_range: tuple[float, float] = (0.05, 1.0)
    t2_like_probability: float = 0.5
    t2_levels: tuple[float, ...] = FIDON_T2_LEVELS
    t2_contrast: tuple[float, float] = (0.6, 2.2)
    t2_jitter: float = 0.2
    texture: tuple[float, float] = (0.0, 0.15)
    texture_mm: float = 8.0
    partial_volume_mm: tuple[float, float] = (0.3, 1.0)
    bias: tuple[float, float] = (0.0, 0.3)
    bias_points: int = 4
    blur_mm: tuple[float, float] = (0.0, 1.2)
    noise: tuple[float, float] = (0.0, 0.04)
    deform_mm: float = 0.0
    monotone_probability: float = 0.5
    curve_knots: int = 6

    def __post_init__(self) -> None:
        owner = "SynthesisConfig"
        check_choice(owner, "mode", self.mode, SYNTHESIS_MODES)
        for name in ("mean_range", "texture", "partial_volume_mm", "bias", "blur_mm", "noise"):
            value = check_range(owner, name, getattr(self, name), ge=0, allow_list=True)
            object.__setattr__(self, name, value)
        contrast = check_range(owner, "t2_contrast", self.t2_contrast, gt=0, allow_list=True)
        object.__setattr__(self, "t2_contrast", contrast)
        levels = check_number_tuple(
            owner, "t2_levels", self.t2_levels, gt=0, allow_empty=True, allow_list=True
        )
        object.__setattr__(self, "t2_levels", levels)
        for name in ("t2_like_probability", "monotone_probability"):
            check_fraction(owner, name, getattr(self, name))
        check_number(owner, "t2_jitter", self.t2_jitter, ge=0, lt=1)
        check_number(owner, "texture_mm", self.texture_mm, gt=0)
        check_number(owner, "deform_mm", self.deform_mm, ge=0)
        check_int(owner, "bias_points", self.bias_points, minimum=2)
        check_int(owner, "curve_knots", self.curve_knots, minimum=2)


class SyntheticBrain(NamedTuple):
    """A batch of synthetic brains.

    Attributes:
        image: (B, I, J, K) float32 intensities, 0 outside the mask, in-mask 99th percentile 1.
        mask: (B, I, J, K) bool brain masks (the input's unless deformed).
        labels: (B, I, J, K) int64 labels (the input's unless deformed).
    """

    image: Tensor
    mask: Tensor
    labels: Tensor


def _uniform(
    low_high: tuple[float, float], shape: tuple[int, ...], generator: torch.Generator
) -> Tensor:
    low, high = low_high
    return low + (high - low) * torch.rand(shape, generator=generator, dtype=torch.float64)


def label_maps(labels: Tensor, table: Tensor) -> Tensor:
    """Per-label values painted on label maps: ``out[b, m] = table[b, labels[b], m]``.

    Args:
        labels: (B, I, J, K) integer labels in [0, C).
        table: (B, C, M) values of each label.

    Returns:
        (B, M, I, J, K) maps in ``table``'s dtype.
    """
    b, m = labels.shape[0], table.shape[2]
    index = labels.reshape(b, 1, -1).expand(b, m, -1).to(table.device)
    return torch.gather(table.transpose(1, 2), 2, index).reshape(b, m, *labels.shape[1:])


def gaussian_blur(x: Tensor, sigma_voxels: Tensor) -> Tensor:
    """Separable Gaussian blur of (B, C, I, J, K) volumes, each brain with its own widths.

    Args:
        x: (B, C, I, J, K) floating-point volumes.
        sigma_voxels: (B, 3) standard deviations along I, J and K in voxels (0: no blur along
            that axis for that brain).

    Returns:
        (B, C, I, J, K) blurred volumes: zero beyond the grid, each kernel 3 standard deviations
        each side (rounded, as ``scipy.ndimage.gaussian_filter`` cuts it) and normalised.
    """
    b = x.shape[0]
    sigma = sigma_voxels.to(torch.float64).reshape(b, 3)
    for axis in range(3):
        reach = torch.floor(3.0 * sigma[:, axis, None] + 0.5)  # (B, 1) each brain's radius
        radius = min(int(reach.max()) if b else 0, x.shape[2 + axis] - 1)
        if radius <= 0:
            continue
        offsets = torch.arange(-radius, radius + 1, dtype=torch.float64)
        width = sigma[:, axis, None].clamp(min=1e-6)
        kernel = torch.exp(-0.5 * (offsets[None] / width) ** 2) * (offsets.abs()[None] <= reach)
        kernel = (kernel / kernel.sum(1, keepdim=True)).to(x)  # (B, 2r + 1)
        weight = kernel.reshape(b, 1, 1, 1, 1, -1)
        dim, n = 2 + axis, x.shape[2 + axis]
        out = x * weight[..., radius]
        for shift in range(1, radius + 1):  # shifted sums: much faster than conv3d on a CPU
            out.narrow(dim, shift, n - shift).add_(
                x.narrow(dim, 0, n - shift) * weight[..., radius - shift]
            )
            out.narrow(dim, 0, n - shift).add_(
                x.narrow(dim, shift, n - shift) * weight[..., radius + shift]
            )
        x = out
    return x


def smooth_field(
    batch: int,
    channels: int,
    shape: tuple[int, int, int],
    points: tuple[int, int, int],
    generator: torch.Generator,
) -> Tensor:
    """Smooth random fields: unit Gaussians on a coarse grid, trilinear in between.

    Args:
        batch: ``B``.
        channels: ``C``, independent fields per brain.
        shape: (I, J, K) of the result.
        points: Control points per axis (>= 2 each); the grid spans the volume corner to corner.
        generator: Source of the control values.

    Returns:
        (B, C, I, J, K) float32 fields.
    """
    coarse = torch.randn(batch, channels, *points, generator=generator, dtype=torch.float64)
    return functional.interpolate(
        coarse.float(), size=shape, mode="trilinear", align_corners=True
    ).contiguous()


def _control_points(
    shape: tuple[int, ...], spacing_mm: Tensor, every_mm: float
) -> tuple[int, int, int]:
    """Control points per axis about ``every_mm`` apart over a grid (at least 2)."""
    a, b, c = (
        max(2, math.ceil(n * float(s) / every_mm) + 1)
        for n, s in zip(shape, spacing_mm, strict=True)
    )
    return a, b, c


def draw_label_means(
    config: SynthesisConfig, batch: int, classes: int, generator: torch.Generator
) -> Tensor:
    """Each label's mean intensity for ``batch`` brains (``"labels"`` mode).

    Args:
        config: The ranges.
        batch: ``B``.
        classes: ``C``, labels 0 .. C - 1 (T2-like levels for 1 .. ``len(t2_levels)``).
        generator: Source of the draws (the same number whatever the probabilities).

    Returns:
        (B, C) float64 means, relative to the brain's bright end.
    """
    t2_like = torch.rand(batch, generator=generator, dtype=torch.float64) < (
        config.t2_like_probability
    )
    low, high = (math.log(v) for v in config.t2_contrast)
    exponent = torch.exp(_uniform((low, high), (batch, 1), generator))
    jitter = _uniform((1 - config.t2_jitter, 1 + config.t2_jitter), (batch, classes), generator)
    random = _uniform(config.mean_range, (batch, classes), generator)
    known = max(0, min(classes - 1, len(config.t2_levels)))
    levels = torch.full((classes,), float("nan"), dtype=torch.float64)
    levels[1 : known + 1] = torch.tensor(config.t2_levels[:known], dtype=torch.float64)
    t2 = levels[None] ** exponent * jitter
    t2 = torch.where(torch.isnan(t2), random, t2)
    return torch.where(t2_like[:, None], t2, random)


def _label_intensities(
    labels: Tensor,
    blur: Tensor,
    spacing: Tensor,
    config: SynthesisConfig,
    generator: torch.Generator,
) -> Tensor:
    """``"labels"`` mode: each label's mean and smooth texture, mixed by the blurred labels.

    Each label's texture is ``cos(a) T1 + sin(a) T2`` (``a`` random per label, ``T1``, ``T2``
    smooth unit fields): a unit field of its own. Blurring the one-hot label maps and then
    mixing the labels' values by them is, by linearity, blurring each value painted on the
    labels: ``sum_l blur(1[L = l]) v_l = blur(v_L)``, done on three maps instead of C one-hots.
    """
    b = labels.shape[0]
    shape = (labels.shape[1], labels.shape[2], labels.shape[3])
    classes = int(labels.max()) + 1
    means = draw_label_means(config, b, classes, generator)
    means[:, 0] = 0.0  # outside the brain
    amplitude = _uniform(config.texture, (b, classes), generator)
    angle = _uniform((0.0, 2 * math.pi), (b, classes), generator)
    table = torch.stack(
        [means, means * amplitude * torch.cos(angle), means * amplitude * torch.sin(angle)], -1
    )
    maps = gaussian_blur(label_maps(labels, table.float()), blur)  # (B, 3, I, J, K)
    fields = smooth_field(
        b, 2, shape, _control_points(shape, spacing, config.texture_mm), generator
    )
    return (maps[:, 0] + (maps[:, 1:] * fields).sum(1)).clamp(min=0)


def remap_per_label(
    image: Tensor,
    labels: Tensor,
    blur: Tensor,
    mask: Tensor,
    config: SynthesisConfig,
    generator: torch.Generator,
) -> Tensor:
    """The real image remapped by a random curve per label (``"mixed"`` mode).

    Each label ``l`` has a piecewise-linear curve ``f_l`` through ``curve_knots`` evenly spaced
    knots over ``[0, the brain's maximum]``: increasing with probability
    ``monotone_probability`` (per brain), else with knot values uniform in ``mean_range``. The
    result is ``sum_l w_l f_l(x)`` with ``w_l`` the labels' one-hot maps blurred by ``blur``,
    computed as ``sum_k phi_k(x) blur(v_{L, k})`` (``phi_k`` the knots' hat functions; by
    linearity the same).

    Args:
        image: (B, I, J, K) intensities.
        labels: (B, I, J, K) integer labels in [0, C); label 0 (outside the brain) maps to 0.
        blur: (B, 3) partial-volume blur of the labels, in voxels.
        mask: (B, I, J, K) bool brain masks (the curves span the brain's range).
        config: The ranges.
        generator: Source of the draws.

    Returns:
        (B, I, J, K) float32 remapped intensities.
    """
    b, c, k = labels.shape[0], int(labels.max()) + 1, config.curve_knots
    monotone = torch.rand(b, generator=generator, dtype=torch.float64) < (
        config.monotone_probability
    )
    ends = _uniform(config.mean_range, (b, c, 2), generator).sort(dim=-1).values
    steps = -torch.log(torch.rand(b, c, k - 1, generator=generator, dtype=torch.float64))
    rising = torch.cat([torch.zeros(b, c, 1, dtype=torch.float64), steps.cumsum(-1)], dim=-1)
    rising = ends[..., :1] + (ends[..., 1:] - ends[..., :1]) * rising / rising[..., -1:]
    free = _uniform(config.mean_range, (b, c, k), generator)
    knots = torch.where(monotone[:, None, None], rising, free).float()  # (B, C, K)
    knots[:, 0] = 0.0  # outside the brain
    values = gaussian_blur(label_maps(labels, knots), blur)  # (B, K, I, J, K)
    top = torch.stack(
        [image[i][mask[i]].max() if bool(mask[i].any()) else image.new_ones(()) for i in range(b)]
    ).clamp(min=1e-6)
    t = (image / top.reshape(b, 1, 1, 1)).clamp(0, 1) * (k - 1)
    low = t.floor().clamp(max=k - 2).long()[:, None]
    frac = t[:, None] - low
    at = torch.gather(values, 1, low)
    above = torch.gather(values, 1, low + 1)
    return (at + (above - at) * frac)[:, 0]


def _percentile_99(values: Tensor) -> Tensor:
    """The 99th percentile of a 1D tensor, interpolated as ``numpy.percentile`` does."""
    position = 0.99 * (len(values) - 1)
    low = math.floor(position)
    a = torch.kthvalue(values, low + 1).values
    b = torch.kthvalue(values, min(low + 2, len(values))).values
    return a + (b - a) * (position - low)


def _normalise(image: Tensor, mask: Tensor) -> Tensor:
    """Zero outside each mask, divided by each brain's in-mask 99th percentile."""
    out = torch.where(mask, image, torch.zeros_like(image))
    for i in range(len(out)):
        if bool(mask[i].any()):
            out[i] = out[i] / _percentile_99(out[i][mask[i]]).clamp(min=1e-6)
    return out


def _deform(
    labels: Tensor,
    mask: Tensor,
    image: Tensor | None,
    affine: Tensor,
    config: SynthesisConfig,
    generator: torch.Generator,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Labels (nearest), mask and image (trilinear) deformed alike, one field per brain."""
    out_labels, out_mask, out_image = [], [], []
    for i in range(len(labels)):
        grid = Image(mask[i].float(), affine)
        field = random_displacement(grid, config.deform_mm, generator)
        nearest = warp_channels(labels[i][None].float(), affine, field, mode="nearest")
        out_labels.append(nearest[0].round().long())
        channels = [mask[i].float()[None]] + ([] if image is None else [image[i][None].float()])
        warped = warp_channels(torch.cat(channels), affine, field)
        out_mask.append(warped[0] > 0.5)
        if image is not None:
            out_image.append(warped[1])
    return (
        torch.stack(out_labels),
        torch.stack(out_mask),
        None if image is None else torch.stack(out_image),
    )


def synthesize(
    labels: Tensor,
    mask: Tensor,
    affine: Tensor,
    config: SynthesisConfig,
    generator: torch.Generator,
    image: Tensor | None = None,
) -> SyntheticBrain:
    """Synthetic brains from label maps (module docstring).

    Args:
        labels: (B, I, J, K) integer labels >= 0 (0: no label; the brain's voxels without one
            get a random intensity of their own, those outside the mask 0).
        mask: (B, I, J, K) brain masks (bool, or > 0.5 is brain).
        affine: (4, 4) voxel -> world affine of the grid (its column norms are the spacing).
        config: The ranges.
        generator: The only source of randomness (CPU generator).
        image: (B, I, J, K) real intensities, needed for ``config.mode == "mixed"``.

    Returns:
        The brains (float32 images on the labels' device).

    Raises:
        ValueError: If the shapes differ, ``labels`` has negative values, or ``"mixed"`` has no
            ``image``.
    """
    if (
        labels.dim() != 4
        or mask.shape != labels.shape
        or (image is not None and image.shape != labels.shape)
    ):
        raise ValueError(
            "synthesize(): 'labels', 'mask' and 'image' must be (B, I, J, K) alike, got "
            f"{tuple(labels.shape)}, {tuple(mask.shape)}"
            f"{'' if image is None else ', ' + str(tuple(image.shape))}"
        )
    if labels.is_floating_point() or bool((labels < 0).any()):
        raise ValueError("synthesize(): 'labels' must be integers >= 0")
    if config.mode == "mixed" and image is None:
        raise ValueError("synthesize(): the 'mixed' mode needs the real 'image'")
    brain = mask if mask.dtype == torch.bool else mask > 0.5
    labels = labels.long()
    b = labels.shape[0]
    shape = (labels.shape[1], labels.shape[2], labels.shape[3])
    spacing = affine[:3, :3].to(torch.float64).norm(dim=0).cpu()
    if config.deform_mm > 0:
        labels, brain, image = _deform(labels, brain, image, affine, config, generator)
    # Class 0 is outside the brain (intensity 0); brain voxels without a label get a class of
    # their own after the labels', so that their intensity does not leak past the mask.
    unlabelled = (int(labels.max()) if labels.numel() else 0) + 1
    classes = torch.where(brain & (labels == 0), unlabelled, labels)
    classes = torch.where(brain, classes, torch.zeros_like(classes))
    pv = (_uniform(config.partial_volume_mm, (b, 1), generator) / spacing).expand(b, 3)
    if config.mode == "labels":
        out = _label_intensities(classes, pv, spacing, config, generator)
    else:
        assert image is not None
        out = remap_per_label(image.float(), classes, pv, brain, config, generator)
    strength = _uniform(config.bias, (b, 1, 1, 1), generator).float()
    bias = smooth_field(b, 1, shape, (config.bias_points,) * 3, generator)[:, 0]
    out = out * torch.exp(strength * bias)
    blur = _uniform(config.blur_mm, (b, 3), generator) / spacing
    out = _normalise(gaussian_blur(out[:, None], blur)[:, 0], brain)
    sigma = _uniform(config.noise, (b, 1, 1, 1), generator).float()
    noise = torch.randn(2, *out.shape, generator=generator).to(out.device)
    out = torch.sqrt((out + sigma * noise[0]) ** 2 + (sigma * noise[1]) ** 2)
    return SyntheticBrain(_normalise(out, brain), brain, labels)


def synthesize_volume(
    volume: CanonicalVolume, config: SynthesisConfig, generator: torch.Generator
) -> CanonicalVolume:
    """One synthetic copy of a canonical brain that has labels, on its grid and frame.

    The brain is cropped to its mask's bounding box (with a margin) for :func:`synthesize`
    and put back on the full grid.

    Args:
        volume: The brain, with ``labels``.
        config: The ranges.
        generator: The only source of randomness.

    Returns:
        The synthetic brain: its image (normalised as canonical volumes are), mask and labels
        (the input's unless deformed), the input's frame, centre and intensity scale.

    Raises:
        ValueError: If the volume has no labels or an empty mask.
    """
    if volume.labels is None:
        raise ValueError("synthesize_volume(): the volume has no 'labels' (tissue label map)")
    inside = torch.nonzero(volume.mask)
    if not len(inside):
        raise ValueError("synthesize_volume(): the volume's mask is empty")
    size = torch.tensor(volume.mask.shape)
    low = (inside.min(0).values - _CROP_MARGIN).clamp(min=0)
    high = torch.minimum(inside.max(0).values + _CROP_MARGIN + 1, size)
    box = tuple(slice(int(a), int(b)) for a, b in zip(low, high, strict=True))
    affine = volume.image.affine.to(torch.float64).clone()
    affine[:3, 3] += affine[:3, :3] @ low.to(torch.float64)
    made = synthesize(
        volume.labels[box][None],
        volume.mask[box][None],
        affine,
        config,
        generator,
        image=volume.image.data[box][None] if config.mode == "mixed" else None,
    )
    image = torch.zeros_like(volume.image.data, dtype=torch.float32)
    image[box] = made.image[0]
    mask, labels = volume.mask, volume.labels
    if config.deform_mm > 0:
        mask = torch.zeros_like(volume.mask)
        mask[box] = made.mask[0]
        labels = torch.zeros_like(volume.labels)
        labels[box] = made.labels[0].to(labels.dtype)
    return CanonicalVolume(
        Image(image, volume.image.affine),
        mask,
        volume.centre_mm,
        volume.intensity_scale,
        labels,
    )
