"""A procedural T2-weighted fetal-brain phantom.

Tests, demos and machines without the real atlas use it as a built-in brain volume: a label map
of fetal anatomy is drawn from signed-distance functions, mapped to fetal T2w contrast and
blurred slightly for partial volume. Everything is deterministic for a given
:class:`PhantomConfig` (a seeded ``numpy`` generator; no global RNG), and the anatomy does not
depend on the grid: it is analytic (in units of the brain length), and only its rasterisation and
the cortex's distance transform see the voxels.

Grid and frame:
    The affine is ``diag(spacing_mm)`` with the world origin at the geometric centre of the
    grid: voxel ``(i, j, k)`` is at ``spacing_mm * ((i, j, k) - (shape - 1) / 2)`` mm (RAS+:
    ``i`` -> x right, ``j`` -> y anterior, ``k`` -> z superior). The anatomy is placed so that
    the centroid of the brain mask is the world origin, i.e. the world frame is already the
    canonical frame of ``docs/conventions.md`` (to within the rasterisation, well under a voxel).

Anatomy (all sizes scale with ``brain_length_mm`` = L, the fronto-occipital length of the
cerebrum):
    * Cerebrum: an egg-like ellipsoid of length L (y), width ~0.8 L (x, slightly wider
      posteriorly) and height ~0.66 L (z, flatter below than above), split into two hemispheres
      by an interhemispheric fissure (a flat CSF sheet 0.018 L wide) that reaches down to an
      arched floor above the lateral ventricles (where the corpus callosum is) and cuts right
      through in front of and behind it.
    * Cortex: a grey-matter ribbon of thickness ``clip(0.025 L, 1.5, 3)`` mm under every
      cerebral surface (convexity, fissure walls, tentorial and basal surfaces, sulci), found
      with a Euclidean distance transform of the folded cerebrum.
    * Folding: the cerebral surface is pushed inwards by ``depth = A (0.6 + 0.4 m) exp(-(n /
      0.35)^2)`` where ``n`` and ``m`` are smooth seeded 3D noise fields (sums of 24 random plane
      waves, unit variance). Sulci therefore follow the zero set of ``n`` -- a labyrinth of
      narrow, V-shaped infoldings filled with CSF and lined by cortex, of varying depth (``m``).
      The amplitude ``A = 0.10 L * folding`` and the spatial frequency (wavelength ``(0.30 -
      0.14 folding) L``) grow with ``folding``; ``folding = 0`` is smooth (lissencephalic). The
      floor of the fissure and the surfaces around the diencephalon and midbrain stay unfolded.
      A broad lateral dimple (Sylvian fissure / insula), ``(0.03 + 0.04 folding) L`` deep, is
      present at every folding.
    * White matter fills the cerebrum inside the cortex.
    * Deep grey matter: thalami beside the third ventricle and basal-ganglia blobs lateral to the
      frontal horns.
    * Lateral ventricles: C-shaped tubes of varying radius (frontal horn, body, a wide atrium,
      temporal horn curving down and forwards); a slit-like midline third ventricle; a cavum
      septi pellucidi (CSF) between the frontal horns.
    * Cerebellum (two hemispheres and a vermis) posterior-inferior under the occipital lobes,
      separated from them by a CSF gap (tentorium), and a brainstem (midbrain, pons, medulla)
      in front of it, with CSF in between (fourth ventricle / cisterns).
    * Extra-axial CSF: a layer 0.04 L thick around the whole brain; its outer surface is the
      skull boundary, outside which the volume is background 0.

Labels (:class:`PhantomLabel`) and fetal T2w intensities (:data:`T2_INTENSITY`): background 0
(0.0), CSF 1 (1.0: extra-axial CSF, fissures, sulci, cisterns, cavum), cortex 2 (0.42), white
matter 3 (0.68, unmyelinated), deep grey 4 (0.5), lateral ventricles 5 (1.0), third ventricle 6
(1.0), cerebellum 7 (0.5), brainstem 8 (0.45). The volume is the intensity of the label map
blurred with a Gaussian of sigma 0.5 voxel (partial volume). The mask is every non-background
label (brain tissue, ventricles and extra-axial CSF, as fetal brain masks are drawn).

How it differs from real anatomy:
    * Shapes are ellipsoids, tubes and noise, not anatomy: sulci follow no real sulcal pattern
      (no named primary sulci beyond the Sylvian dimple; the pattern depends on the seed), the
      gyri have no preferred orientation and folding is uniform over the hemispheres (real
      sulci appear in a fixed order and layout, the Sylvian, parieto-occipital, calcarine,
      cingulate and central sulci first), and the opercula do not close over the insula.
    * No corpus callosum, fornix, hippocampus, optic chiasm or fourth-ventricle shape; the
      cortical ribbon also lines the floor of the interhemispheric fissure, which happens to
      give the callosum's dark T2 appearance.
    * No transient fetal layers (germinal matrix, subplate, intermediate zone), no myelination
      gradient and no cerebellar folia: each tissue has one intensity, with no texture, noise
      or bias field.
    * The fissure is a flat sheet in the midsagittal plane x = 0, so the midline sagittal slice
      shows its CSF (with the medial gyri as partial-volume patches) above the callosal floor
      rather than the medial surface of one hemisphere.
    * The hemispheres are mirror images apart from the folding; there is no skull, scalp,
      amniotic fluid, placenta or maternal tissue around the brain.
    * The gestational-age mapping (:func:`gestational_age_config`) is approximate and for
      realism of scale only, not a clinical growth reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from functools import cache
from typing import Any

import numpy as np
import torch
from scipy import ndimage
from scipy.interpolate import make_interp_spline
from scipy.spatial import cKDTree

from svr.errors import ConfigFieldError
from svr.image import Image
from svr.validation import (
    check_fraction,
    check_int,
    check_int_tuple,
    check_number,
    is_finite_number,
)


class PhantomLabel(IntEnum):
    """Label ids of :func:`make_phantom_labels`."""

    BACKGROUND = 0
    CSF = 1
    CORTEX = 2
    WHITE_MATTER = 3
    DEEP_GREY = 4
    LATERAL_VENTRICLES = 5
    THIRD_VENTRICLE = 6
    CEREBELLUM = 7
    BRAINSTEM = 8


T2_INTENSITY: dict[PhantomLabel, float] = {
    PhantomLabel.BACKGROUND: 0.0,
    PhantomLabel.CSF: 1.0,
    PhantomLabel.CORTEX: 0.42,
    PhantomLabel.WHITE_MATTER: 0.68,
    PhantomLabel.DEEP_GREY: 0.5,
    PhantomLabel.LATERAL_VENTRICLES: 1.0,
    PhantomLabel.THIRD_VENTRICLE: 1.0,
    PhantomLabel.CEREBELLUM: 0.5,
    PhantomLabel.BRAINSTEM: 0.45,
}
"""Fetal T2w intensity of each label before the partial-volume blur, in [0, 1]."""

PARTIAL_VOLUME_SIGMA_VOXELS = 0.5
"""Standard deviation of the Gaussian partial-volume blur, in voxels."""

# Gestational age (weeks) -> cerebral fronto-occipital length (mm) and folding. Rounded from the
# trend of published fetal-MRI biometry (~3.3 mm/week in mid-gestation, slowing towards term) and
# the usual timeline of sulcation (lissencephalic before ~22 weeks, primary sulci 24-30 weeks,
# secondary and tertiary sulci after 30 weeks).
GA_WEEKS = (20.0, 22.0, 24.0, 26.0, 28.0, 30.0, 32.0, 34.0, 36.0, 38.0)
GA_BRAIN_LENGTH_MM = (52.0, 60.0, 67.0, 74.0, 81.0, 88.0, 94.0, 100.0, 105.0, 109.0)
GA_FOLDING = (0.0, 0.05, 0.15, 0.3, 0.45, 0.6, 0.75, 0.85, 0.95, 1.0)

# Geometry in units of the brain length L, in the anatomical frame (origin at the centre of the
# cerebral ellipsoid; x right, y anterior, z superior).
_CEREBRUM_HALF_WIDTH = 0.40  # x semi-axis at y = 0; 6 % narrower at the frontal pole
_CEREBRUM_HALF_LENGTH = 0.50
_CEREBRUM_HALF_HEIGHT_UP, _CEREBRUM_HALF_HEIGHT_DOWN = 0.36, 0.30
_EXTRA_AXIAL_CSF = 0.04
_FISSURE_HALF_WIDTH = 0.009
_CALLOSUM_HALF_LENGTH = 0.24  # the fissure floor is arched over |y| < this, open beyond
_TENTORIUM_GAP = 0.015
_BRAINSTEM_GAP = 0.012
_LATERAL_VENTRICLE = (  # right side (x > 0): centreline points and radii
    ((0.07, 0.215, 0.0), 0.022),
    ((0.08, 0.12, 0.03), 0.03),
    ((0.09, 0.0, 0.04), 0.028),
    ((0.105, -0.12, 0.035), 0.032),
    ((0.15, -0.215, 0.005), 0.052),
    ((0.19, -0.19, -0.08), 0.032),
    ((0.21, -0.09, -0.13), 0.02),
    ((0.215, 0.01, -0.145), 0.014),
)
_BRAINSTEM = (
    ((0.0, -0.08, -0.08), 0.05),
    ((0.0, -0.11, -0.17), 0.06),
    ((0.0, -0.12, -0.25), 0.065),
    ((0.0, -0.16, -0.40), 0.045),
)
_BRAINSTEM_CARVE_BELOW_Z = -0.17  # only pons and medulla push the cerebrum away
_CEREBELLUM = (  # (centre, semi-axes): two hemispheres and the vermis
    ((0.095, -0.32, -0.26), (0.12, 0.10, 0.095)),
    ((-0.095, -0.32, -0.26), (0.12, 0.10, 0.095)),
    ((0.0, -0.31, -0.25), (0.05, 0.095, 0.10)),
)
_THIRD_VENTRICLE = ((0.0, -0.03, -0.06), (0.012, 0.08, 0.055))
_CAVUM = ((0.0, 0.11, 0.035), (0.018, 0.07, 0.035))
_DEEP_GREY = (
    ((0.065, -0.05, -0.045), (0.055, 0.085, 0.06)),  # thalami
    ((-0.065, -0.05, -0.045), (0.055, 0.085, 0.06)),
    ((0.145, 0.06, -0.01), (0.05, 0.10, 0.07)),  # basal ganglia
    ((-0.145, 0.06, -0.01), (0.05, 0.10, 0.07)),
)
_NOISE_WAVES = 24
_SULCUS_DEPTH = 0.10  # deepest sulcus at folding 1
_SULCUS_WIDTH = 0.35  # in units of the noise's standard deviation
_UNFOLDED_CORE = ((0.0, -0.03, -0.03), (0.13, 0.28, 0.17))  # callosum, diencephalon, midbrain
_GYRAL_WAVELENGTH = (0.30, 0.16)  # at folding 0 and 1
_SYLVIAN_DEPTH = (0.03, 0.07)  # at folding 0 and 1
_BLUR_MARGIN_VOXELS = 2  # the mask keeps this far from the edge of the grid
_BOUNDS_STEP = 0.02  # grid step (units of L) for the mask centroid and extent


@dataclass(frozen=True)
class PhantomConfig:
    """Size, resolution and maturity of the phantom.

    Attributes:
        shape: Grid size (I, J, K) in voxels.
        spacing_mm: Isotropic voxel size in mm.
        brain_length_mm: Fronto-occipital length of the cerebrum in mm, the age-like scale (about
            60 mm at 22 weeks to 100 mm at 34 weeks; see :func:`gestational_age_config`).
        folding: Cortical folding in [0, 1]: 0 is smooth (early gestation), 1 strongly folded
            (late gestation).
        seed: Seed (>= 0) of the folding pattern.

    Raises:
        ConfigFieldError: Naming the field, for a non-positive or non-integer size, a
            non-positive or non-finite spacing or length, folding outside [0, 1], a negative seed,
            or a brain (with its CSF and a two-voxel margin) that does not fit in the field of view
            (naming ``brain_length_mm``). NumPy numbers are accepted (stored as Python numbers).
    """

    shape: tuple[int, int, int] = (128, 128, 128)
    spacing_mm: float = 0.8
    brain_length_mm: float = 80.0
    folding: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        owner = "PhantomConfig"
        for name in ("shape", "spacing_mm", "brain_length_mm", "folding", "seed"):
            object.__setattr__(self, name, _plain(getattr(self, name)))
        shape = check_int_tuple(owner, "shape", self.shape, length=3, minimum=1, allow_list=True)
        for name in ("spacing_mm", "brain_length_mm"):
            check_number(owner, name, getattr(self, name), gt=0)
        check_fraction(owner, "folding", self.folding)
        check_int(owner, "seed", self.seed, minimum=0)
        object.__setattr__(self, "shape", shape)
        need = required_field_of_view_mm(self.brain_length_mm, self.spacing_mm)
        for axis, (n, needed) in enumerate(zip(self.shape, need, strict=True)):
            have = (n - 1) * self.spacing_mm
            if have < needed:
                raise ConfigFieldError(
                    owner,
                    "brain_length_mm",
                    f"short enough for the field of view (the brain does not fit: it needs "
                    f"{needed:.1f} mm along axis {axis} but 'shape'[{axis}]={n} x "
                    f"'spacing_mm'={self.spacing_mm} spans {have:.1f} mm; enlarge 'shape' or "
                    f"'spacing_mm' or shorten 'brain_length_mm')",
                    self.brain_length_mm,
                )


def _plain(value: object) -> object:
    """NumPy scalars and arrays as Python numbers and lists (the phantom accepts them)."""
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, tuple | list):
        return [_plain(item) for item in value]
    return value


def required_field_of_view_mm(brain_length_mm: float, spacing_mm: float) -> tuple[float, ...]:
    """Field of view a phantom needs along each axis.

    Args:
        brain_length_mm: Cerebral length L in mm.
        spacing_mm: Voxel size in mm.

    Returns:
        (3,) extents in mm (between the centres of the first and last voxels) that hold the mask,
        centred on its centroid, plus a margin of two voxels on each side for the blur.
    """
    _, half_extent = _mask_centroid_and_half_extent()
    return tuple(
        2.0 * (h * brain_length_mm + _BLUR_MARGIN_VOXELS * spacing_mm) for h in half_extent
    )


def gestational_age_config(weeks: float, **overrides: Any) -> PhantomConfig:
    """A phantom configuration for a gestational age.

    ``brain_length_mm`` and ``folding`` are interpolated linearly in :data:`GA_WEEKS` ->
    :data:`GA_BRAIN_LENGTH_MM` (52 mm at 20 weeks, 60 at 22, 81 at 28, 100 at 34, 109 at 38) and
    :data:`GA_FOLDING` (0 at 20 weeks, 0.05 at 22, 0.45 at 28, 0.85 at 34, 1 at 38). Unless
    ``shape`` is overridden, the grid is the smallest cube of 128 + 16 n voxels that holds the
    brain at the (default or overridden) spacing.

    Args:
        weeks: Gestational age in weeks, in [20, 38].
        **overrides: Any other :class:`PhantomConfig` fields (they win over the age's values).

    Returns:
        The configuration.

    Raises:
        ValueError: If ``weeks`` is outside [20, 38] or not finite, or the configuration is bad.
    """
    if not (is_finite_number(_plain(weeks)) and GA_WEEKS[0] <= weeks <= GA_WEEKS[-1]):
        raise ValueError(
            f"gestational_age_config(): 'weeks' must be in [{GA_WEEKS[0]:g}, "
            f"{GA_WEEKS[-1]:g}], got {weeks!r}"
        )
    fields: dict[str, Any] = {
        "brain_length_mm": float(np.interp(weeks, GA_WEEKS, GA_BRAIN_LENGTH_MM)),
        "folding": float(np.interp(weeks, GA_WEEKS, GA_FOLDING)),
        **overrides,
    }
    length, spacing = fields["brain_length_mm"], fields.get("spacing_mm", PhantomConfig.spacing_mm)
    valid = all(is_finite_number(_plain(v)) and v > 0 for v in (length, spacing))
    if "shape" not in fields and valid:
        voxels = max(required_field_of_view_mm(length, spacing)) / spacing + 1.0
        n = 128 + 16 * max(0, math.ceil((voxels - 128) / 16))
        fields["shape"] = (n, n, n)
    return PhantomConfig(**fields)


def phantom_affine(config: PhantomConfig) -> torch.Tensor:
    """The phantom's voxel -> world affine.

    Args:
        config: The phantom configuration.

    Returns:
        (4, 4) float64: diagonal ``spacing_mm``, with the centre of the grid at world (0, 0, 0).
    """
    affine = torch.eye(4, dtype=torch.float64)
    for axis, n in enumerate(config.shape):
        affine[axis, axis] = config.spacing_mm
        affine[axis, 3] = -config.spacing_mm * (n - 1) / 2.0
    return affine


def make_phantom_labels(config: PhantomConfig | None = None) -> Image:
    """Rasterise the phantom's anatomy as a label map.

    Args:
        config: The phantom configuration; ``None`` means ``PhantomConfig()``.

    Returns:
        (I, J, K) float32 image of :class:`PhantomLabel` ids (exact integers, so that it stays a
        floating-point :class:`~svr.image.Image`; use ``.data.long()`` for indexing), on the CPU,
        with :func:`phantom_affine`.
    """
    config = PhantomConfig() if config is None else config
    return Image(torch.from_numpy(_label_map(config).astype(np.float32)), phantom_affine(config))


def make_phantom(config: PhantomConfig | None = None) -> tuple[Image, Image]:
    """Make the phantom's T2w volume and brain mask.

    Args:
        config: The phantom configuration; ``None`` means ``PhantomConfig()``.

    Returns:
        ``(volume, mask)``: (I, J, K) float32 T2w-like intensities in [0, 1] and the (I, J, K)
        float32 0/1 brain mask, on the CPU, both with :func:`phantom_affine` (diagonal spacing,
        world origin at the centre of the grid and at the centroid of the mask).
    """
    config = PhantomConfig() if config is None else config
    labels = _label_map(config)
    lut = np.array([T2_INTENSITY[label] for label in PhantomLabel], dtype=np.float32)
    volume = ndimage.gaussian_filter(lut[labels], PARTIAL_VOLUME_SIGMA_VOXELS, mode="constant")
    volume = np.clip(volume, 0.0, 1.0, out=volume)
    mask = (labels != PhantomLabel.BACKGROUND).astype(np.float32)
    affine = phantom_affine(config)
    return Image(torch.from_numpy(volume), affine), Image(torch.from_numpy(mask), affine.clone())


# --- signed-distance functions of points q (3, N) in units of L; negative inside ---------------


def _ellipsoid(
    q: np.ndarray, centre: tuple[float, ...], axes: tuple[float | np.ndarray, ...]
) -> np.ndarray:
    """Approximate signed distance to an ellipsoid (exact on the surface, ~unit gradient near it).

    Args:
        q: (3, N) points.
        centre: (3,) centre.
        axes: (3,) semi-axes, each a number or an (N,) array.

    Returns:
        (N,) signed distances.
    """
    d = [(q[i] - centre[i]) / axes[i] for i in range(3)]
    k0 = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    e = [d[i] / axes[i] for i in range(3)]
    k1 = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    centre_value = np.full_like(k0, -min(float(np.min(a)) for a in axes))
    return np.divide(k0 * (k0 - 1.0), k1, out=centre_value, where=k1 > 0)


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (union of two shapes with a fillet of size ``k``)."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * np.float32(k / 4.0)


@cache
def _tube_centreline(
    spec: tuple[tuple[tuple[float, float, float], float], ...],
) -> tuple[np.ndarray, np.ndarray]:
    """A tube's centreline: a cubic spline through its control points, sampled every 0.002 L.

    Returns:
        (S, 3) centreline points and (S,) radii (linear in arc length between control points).
    """
    points = np.array([p for p, _ in spec], dtype=np.float64)
    radii = np.array([r for _, r in spec], dtype=np.float64)
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    s = np.linspace(0.0, chord[-1], int(np.ceil(chord[-1] / 0.002)) + 1)
    line = make_interp_spline(chord, points, k=min(3, len(spec) - 1))(s)
    return line, np.interp(s, chord, radii)


def _tube(q: np.ndarray, line: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Signed distance to a tube of varying radius: the union of balls along a dense centreline.

    Args:
        q: (3, N) points.
        line: (S, 3) densely sampled centreline.
        radii: (S,) ball radii.

    Returns:
        (N,) signed distances (within the sampling step of the exact union of balls; far
        outside the tube's bounding box, a positive constant).
    """
    out = np.ones(q.shape[1], dtype=np.float32)
    reach = radii.max() + 0.05
    low, high = line.min(0) - reach, line.max(0) + reach
    points = q.T
    near = np.flatnonzero(np.all((points > low) & (points < high), axis=1))
    if near.size:
        dist, idx = cKDTree(line).query(points[near], k=8)
        out[near] = np.minimum((dist - radii[idx]).min(axis=1), 1.0)
    return out


def _mirror(q: np.ndarray) -> np.ndarray:
    """Points mirrored in the midsagittal plane x = 0."""
    return np.stack([-q[0], q[1], q[2]])


def _cerebrum_shape(q: np.ndarray) -> np.ndarray:
    """The cerebral ellipsoid: narrower frontally, flatter below than above."""
    axes = (
        _CEREBRUM_HALF_WIDTH * (1.0 - 0.06 * q[1] / _CEREBRUM_HALF_LENGTH),
        _CEREBRUM_HALF_LENGTH,
        np.where(q[2] > 0, np.float32(_CEREBRUM_HALF_HEIGHT_UP), _CEREBRUM_HALF_HEIGHT_DOWN),
    )
    return _ellipsoid(q, (0.0, 0.0, 0.0), axes)


def _cerebellum(q: np.ndarray) -> np.ndarray:
    sd = _ellipsoid(q, *_CEREBELLUM[0])
    for centre, axes in _CEREBELLUM[1:]:
        sd = _smooth_min(sd, _ellipsoid(q, centre, axes), 0.03)
    return sd


def _brainstem(q: np.ndarray, carve_only: bool = False) -> np.ndarray:
    """The brainstem tube, or only its pons and medulla (which push the cerebrum away)."""
    line, radii = _tube_centreline(_BRAINSTEM)
    if carve_only:
        keep = line[:, 2] <= _BRAINSTEM_CARVE_BELOW_Z
        line, radii = line[keep], radii[keep]
    return _tube(q, line, radii)


def _outer(cerebrum_shape: np.ndarray, cerebellum: np.ndarray, brainstem: np.ndarray) -> np.ndarray:
    """The skull boundary: the unfolded brain with its extra-axial CSF layer."""
    sd = _smooth_min(_smooth_min(cerebrum_shape, cerebellum, 0.06), brainstem, 0.06)
    return sd - np.float32(_EXTRA_AXIAL_CSF)


def _fissure(q: np.ndarray) -> np.ndarray:
    """The interhemispheric fissure: a midline slab above an arched floor (open beyond it)."""
    y = np.abs(q[1])
    y0 = _CALLOSUM_HALF_LENGTH
    arch = (0.09 + 0.04 * (1.0 - (y / y0) ** 2) - q[2]) / np.float32(1.05)
    open_ = (0.09 - 3.0 * (y - y0) - q[2]) / np.float32(math.sqrt(10.0))
    return np.maximum(np.abs(q[0]) - _FISSURE_HALF_WIDTH, np.where(y < y0, arch, open_))


def _noise(q: np.ndarray, rng: np.random.Generator, wavelength: float) -> np.ndarray:
    """Smooth isotropic band-limited noise (random plane waves), zero mean and unit variance.

    Args:
        q: (3, N) points.
        rng: Source of the waves' directions, frequencies and phases (drawn in a fixed order).
        wavelength: Mean wavelength, in the units of ``q``.

    Returns:
        (N,) noise values.
    """
    directions = rng.normal(size=(_NOISE_WAVES, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    k = directions * (2.0 * np.pi / wavelength * rng.uniform(0.85, 1.15, size=(_NOISE_WAVES, 1)))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=(_NOISE_WAVES, 1))
    waves = np.cos(k.astype(np.float32) @ q + phase.astype(np.float32))
    return waves.sum(axis=0) * np.float32(math.sqrt(2.0 / _NOISE_WAVES))


def _lerp(ends: tuple[float, float], t: float) -> float:
    return ends[0] + (ends[1] - ends[0]) * t


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _sylvian_depth(q: np.ndarray, folding: float) -> np.ndarray:
    """Depth (units of L) of the broad lateral dimple of the Sylvian fissure."""
    lateral = np.abs(q[0]) / (_CEREBRUM_HALF_WIDTH * (1.0 - 0.12 * q[1]))
    gauss = np.exp(-(((q[1] - 0.04) / 0.13) ** 2) - ((q[2] + 0.03) / 0.09) ** 2)
    return np.float32(_lerp(_SYLVIAN_DEPTH, folding)) * _smoothstep((lateral - 0.55) / 0.3) * gauss


def _fold_depth(q: np.ndarray, folding: float, seed: int) -> np.ndarray:
    """How far (units of L) the gyral folding pushes the cerebral surface inwards."""
    if folding == 0.0:
        return np.zeros(q.shape[1], dtype=np.float32)
    rng = np.random.default_rng(seed)
    sulci = _noise(q, rng, _lerp(_GYRAL_WAVELENGTH, folding))
    depth_mod = np.clip(_noise(q, rng, 0.5), -1.0, 1.0)
    weight = _smoothstep(_ellipsoid(q, *_UNFOLDED_CORE) / 0.04)
    profile = np.exp(-((sulci / np.float32(_SULCUS_WIDTH)) ** 2))
    return np.float32(_SULCUS_DEPTH * folding) * weight * (0.6 + 0.4 * depth_mod) * profile


@cache
def _mask_centroid_and_half_extent() -> tuple[np.ndarray, np.ndarray]:
    """Centroid of the mask (anatomical frame) and its half-extent about it, in units of L."""
    axis = np.arange(-0.7, 0.7 + 1e-9, _BOUNDS_STEP, dtype=np.float32)
    q = np.stack(np.meshgrid(axis, axis, axis, indexing="ij")).reshape(3, -1)
    inside = q[:, _outer(_cerebrum_shape(q), _cerebellum(q), _brainstem(q)) < 0]
    inside = inside.astype(np.float64)
    centroid = inside.mean(axis=1)
    half = np.maximum(inside.max(axis=1) - centroid, centroid - inside.min(axis=1))
    return centroid, half + _BOUNDS_STEP


def _label_map(config: PhantomConfig) -> np.ndarray:
    """(I, J, K) uint8 label map of the phantom."""
    length, spacing = config.brain_length_mm, config.spacing_mm
    centroid, half = _mask_centroid_and_half_extent()
    shape = np.array(config.shape)
    # Only the box around the mask (plus the blur margin) is evaluated.
    centre_index = (shape - 1) / 2.0
    reach = np.ceil(half * length / spacing) + _BLUR_MARGIN_VOXELS
    lo = np.maximum(np.floor(centre_index - reach).astype(int), 0)
    hi = np.minimum(np.ceil(centre_index + reach).astype(int) + 1, shape)
    axes = [
        ((np.arange(a, b) - c) * spacing / length + m).astype(np.float32)
        for a, b, c, m in zip(lo, hi, centre_index, centroid, strict=True)
    ]
    box_shape = tuple(int(b - a) for a, b in zip(lo, hi, strict=True))
    q_box = np.stack(np.meshgrid(*axes, indexing="ij")).reshape(3, -1)
    cerebellum, brainstem = _cerebellum(q_box), _brainstem(q_box)
    inside = np.flatnonzero(_outer(_cerebrum_shape(q_box), cerebellum, brainstem) < 0)
    q, cerebellum, brainstem = q_box[:, inside], cerebellum[inside], brainstem[inside]
    labels = np.full(q.shape[1], PhantomLabel.CSF, dtype=np.uint8)

    # Cerebrum: the shape minus fissure, tentorial gap and lower brainstem, folded by moving the
    # surface inwards by the depth wherever it reaches.
    cerebrum = np.maximum(_cerebrum_shape(q), -_fissure(q))
    cerebrum = np.maximum(cerebrum, _TENTORIUM_GAP - cerebellum)
    cerebrum = np.maximum(cerebrum, _BRAINSTEM_GAP - _brainstem(q, carve_only=True))
    depth_max = _SULCUS_DEPTH * config.folding + _lerp(_SYLVIAN_DEPTH, config.folding)
    band = np.flatnonzero((cerebrum < 0) & (cerebrum > -depth_max))
    cerebrum[band] += _sylvian_depth(q[:, band], config.folding)
    cerebrum[band] += _fold_depth(q[:, band], config.folding, config.seed)
    tissue = cerebrum < 0

    # Cortex: within the ribbon thickness of the nearest non-tissue voxel centre (plus half a
    # voxel, since the surface lies between voxel centres).
    tissue_box = np.zeros(q_box.shape[1], dtype=bool)
    tissue_box[inside[tissue]] = True
    depth_mm = ndimage.distance_transform_edt(tissue_box.reshape(box_shape), sampling=spacing)
    thickness = min(max(0.025 * length, 1.5), 3.0)
    cortex = depth_mm.reshape(-1)[inside] < thickness + spacing / 2.0
    labels[tissue] = PhantomLabel.WHITE_MATTER
    labels[tissue & cortex] = PhantomLabel.CORTEX

    for centre, semi in _DEEP_GREY:
        labels[tissue & (_ellipsoid(q, centre, semi) < 0)] = PhantomLabel.DEEP_GREY
    labels[_ellipsoid(q, *_CAVUM) < 0] = PhantomLabel.CSF
    labels[brainstem < 0] = PhantomLabel.BRAINSTEM
    labels[cerebellum < 0] = PhantomLabel.CEREBELLUM
    labels[_ellipsoid(q, *_THIRD_VENTRICLE) < 0] = PhantomLabel.THIRD_VENTRICLE
    line, radii = _tube_centreline(_LATERAL_VENTRICLE)
    ventricles = np.minimum(_tube(q, line, radii), _tube(_mirror(q), line, radii))
    labels[ventricles < 0] = PhantomLabel.LATERAL_VENTRICLES

    box = np.zeros(q_box.shape[1], dtype=np.uint8)
    box[inside] = labels
    out = np.zeros(config.shape, dtype=np.uint8)
    out[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = box.reshape(box_shape)
    return out
