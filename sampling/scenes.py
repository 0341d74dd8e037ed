"""Whole-uterus scenes around an atlas brain, for training brain segmentation without real scans.

A clinical fetal stack shows the whole maternal abdomen; the brain is a small part of it. No real
whole-uterus scan may be used for training (issue 14), so :func:`make_scene` builds one by domain
randomisation (SynthSeg-style: random shapes, random intensities) around a canonical atlas brain:

1. the brain, resampled at a random isotropic scale (other sizes and ages), intensities raised to
   a random gamma;
2. the fetal head around it, as shells by distance from the brain surface: extra-axial CSF
   (bright on T2), the skull (dark) and the scalp;
3. the fetal body, an ellipsoid next to the head (with ``face``: below and behind it, where the
   neck is, and a face under the front of the brain: soft tissue holding two eyes, bright
   vitreous in a dark rim with a dark lens), and the amniotic fluid, a larger ellipsoid around
   them (bright);
4. maternal tissue around them, inside an abdomen (an ellipsoid with a randomly perturbed
   boundary; air, 0, outside): a random label field (the arg-max of smoothed noise channels) with
   a random intensity per label and a smooth texture.

The result is a :class:`~svr.sampling.volume.CanonicalVolume` whose ``image`` holds the whole
scene (it is *not* zero outside the brain) and whose ``mask`` is the brain only (or, with
``intracranial_mask``, the brain and the CSF around it: all inside the skull), on a grid
centred on the brain. :func:`svr.sampling.simulate.simulate_case` cuts motion-corrupted
thick-slice stacks from it as from any volume (``margin_mm`` sets how much of the scene a stack
sees; bias fields, noise and signal voids come from there), and each stack's brain mask is the
training target. Intensities are relative to the brain's 99th percentile (1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from svr.errors import ConfigFieldError
from svr.geometry import quat_to_matrix
from svr.image import Image, sample_world, voxel_centres
from svr.sampling.volume import CanonicalVolume
from svr.validation import check_bool, check_number, check_range, is_integer

__all__ = ["SceneConfig", "make_scene"]


@dataclass(frozen=True)
class SceneConfig:
    """How :func:`make_scene` builds a scene (ranges are drawn uniformly unless said otherwise).

    Attributes:
        extent_mm: Edge of the cubic scene, mm (centred on the brain), > 0.
        spacing_mm: Isotropic voxel size of the scene, mm, > 0.
        brain_scale: Range of the brain's isotropic scale factor (drawn log-uniformly).
        gamma: Range of the gamma applied to the brain's intensities.
        csf_mm: Range of the extra-axial CSF thickness, mm.
        skull_mm: Range of the skull thickness, mm.
        scalp_mm: Range of the scalp thickness, mm.
        fluid_margin_mm: Range of the amniotic fluid's extent beyond the head, mm.
        abdomen_margin_mm: Range of the maternal abdomen's extent beyond the fluid, mm; air (0)
            outside it.
        irregularity: Relative amplitude of the smooth random perturbation of the fluid's and
            the abdomen's boundaries, >= 0.
        maternal_labels: Range (inclusive) of the number of maternal tissue labels.
        maternal_smoothness_mm: Range of the smoothing of the maternal label field, mm.
        csf_intensity: Range of the CSF and amniotic fluid intensity.
        skull_intensity: Range of the skull intensity.
        tissue_intensity: Range of the scalp, body and maternal tissue intensities.
        texture: Relative standard deviation of the smooth multiplicative texture, >= 0.
        distractors: Range (inclusive) of the number of random organs: ellipsoids of random size
            and intensity in the maternal tissue and the fetal body, half of them with a rim of
            another intensity (bowel, bladder, spine, kidneys: ring-like structures that are
            not the brain).
        distractor_mm: Range of an organ's semi-axes, mm.
        body_scale: Range of the fetal body's semi-axes relative to the brain's radius (the
            longest axis is 1.5 times longer).
        intracranial_mask: Whether the scene's mask also holds the extra-axial CSF (everything
            inside the skull, as manual fetal brain masks are drawn), not the brain alone.
        skull_in_mask: Whether the intracranial mask reaches the skull's outer edge (manual
            masks drawn around the skull's dark rim); needs ``intracranial_mask``.
        face: Whether the head has a face (soft tissue and two eyes below the front of the
            brain, outside the skull) and the body hangs from a neck (below and behind the
            brain) rather than in a random direction. Needs the brain in RAS orientation
            (canonical +y anterior, +z superior), as the atlas is; its random draws come from
            their own stream, so scenes without it are unchanged.
        spinal_cord: Whether the brainstem below the skull base (the planes under the lowest
            one whose brain cross-section is at least ``CORD_AREA_FRACTION`` of the largest)
            is the spinal cord: outside the head and its mask, in a canal of CSF and bone
            through whatever is beneath the head (the neck with ``face``), as manual masks end
            at the skull base. Needs the brain in RAS orientation.

    Raises:
        ConfigFieldError: On construction, naming the field, for an invalid value.
    """

    extent_mm: float = 320.0
    spacing_mm: float = 2.0
    brain_scale: tuple[float, float] = (0.85, 1.15)
    gamma: tuple[float, float] = (0.7, 1.4)
    csf_mm: tuple[float, float] = (1.5, 5.0)
    skull_mm: tuple[float, float] = (1.5, 4.0)
    scalp_mm: tuple[float, float] = (1.5, 4.0)
    fluid_margin_mm: tuple[float, float] = (10.0, 45.0)
    abdomen_margin_mm: tuple[float, float] = (15.0, 80.0)
    irregularity: float = 0.15
    maternal_labels: tuple[int, int] = (3, 8)
    maternal_smoothness_mm: tuple[float, float] = (6.0, 20.0)
    csf_intensity: tuple[float, float] = (1.0, 2.0)
    skull_intensity: tuple[float, float] = (0.02, 0.3)
    tissue_intensity: tuple[float, float] = (0.1, 1.2)
    texture: float = 0.1
    distractors: tuple[int, int] = (0, 0)
    distractor_mm: tuple[float, float] = (4.0, 30.0)
    body_scale: tuple[float, float] = (0.9, 1.6)
    intracranial_mask: bool = False
    skull_in_mask: bool = False
    face: bool = False
    spinal_cord: bool = False

    def __post_init__(self) -> None:
        owner = "SceneConfig"
        for name in ("extent_mm", "spacing_mm"):
            check_number(owner, name, getattr(self, name), gt=0)
        for name in (
            "brain_scale",
            "gamma",
            "csf_mm",
            "skull_mm",
            "scalp_mm",
            "fluid_margin_mm",
            "abdomen_margin_mm",
            "maternal_smoothness_mm",
            "csf_intensity",
            "skull_intensity",
            "tissue_intensity",
            "distractor_mm",
            "body_scale",
        ):
            check_range(owner, name, getattr(self, name), gt=0)
        for name, least in (("maternal_labels", 1), ("distractors", 0)):  # also lists, as before
            value = check_range(
                owner, name, getattr(self, name), ge=least, integer=True, allow_list=True
            )
            object.__setattr__(self, name, value)
        for name in ("texture", "irregularity"):
            check_number(owner, name, getattr(self, name), ge=0)
        for name in ("intracranial_mask", "skull_in_mask", "face", "spinal_cord"):
            check_bool(owner, name, getattr(self, name))
        if self.skull_in_mask and not self.intracranial_mask:
            raise ConfigFieldError(
                owner, "skull_in_mask", "False without 'intracranial_mask'", self.skull_in_mask
            )


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


def _smooth_noise(
    rng: np.random.Generator, shape: tuple[int, ...], sigma_voxels: float
) -> np.ndarray:
    """Zero-mean, unit-std Gaussian noise smoothed by a Gaussian of ``sigma_voxels``."""
    field = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_voxels, mode="wrap")
    return (field - field.mean()) / max(float(field.std()), 1e-12)


def _ellipsoid(
    points: np.ndarray,
    centre: np.ndarray,
    radii: np.ndarray,
    rotation: np.ndarray,
    perturbation: np.ndarray | float = 0.0,
) -> np.ndarray:
    """Bool mask of the points inside an ellipsoid (radii along the columns of ``rotation``).

    ``perturbation`` (scalar or per point) moves the boundary: inside where the ellipsoid's
    level ``sum((local / radii) ** 2)`` is at most ``1 + perturbation``.
    """
    local = (points - centre) @ rotation
    return ((local / radii) ** 2).sum(axis=-1) <= 1.0 + perturbation


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix uniform on SO(3) (a normalised 4D Gaussian quaternion)."""
    return quat_to_matrix(torch.from_numpy(rng.standard_normal(4))).numpy()


def _paint_organs(
    scene: np.ndarray,
    xyz: np.ndarray,
    region: np.ndarray,
    count: int,
    cfg: SceneConfig,
    rng: np.random.Generator,
) -> None:
    """Paint ``count`` random ellipsoids (half with a rim) centred in ``region``, in place."""
    inside = np.argwhere(region)
    if count == 0 or len(inside) == 0:
        return
    spacing = cfg.spacing_mm
    for _ in range(count):
        centre_index = inside[int(rng.integers(len(inside)))]
        radii = rng.uniform(*cfg.distractor_mm, size=3)
        rim = float(rng.uniform(1.0, 4.0)) if rng.random() < 0.5 else 0.0
        reach = math.ceil((radii.max() + rim) / spacing) + 1
        box = tuple(
            slice(max(int(c) - reach, 0), min(int(c) + reach + 1, n))
            for c, n in zip(centre_index, scene.shape, strict=True)
        )
        local = xyz[box]
        rotation = _random_rotation(rng)
        centre = xyz[tuple(centre_index)]
        core_value = float(rng.uniform(0.05, max(cfg.csf_intensity)))
        if rim > 0:
            outer = _ellipsoid(local, centre, radii + rim, rotation)
            scene[box] = np.where(outer, _uniform(rng, cfg.skull_intensity), scene[box])
        core = _ellipsoid(local, centre, radii, rotation)
        scene[box] = np.where(core, core_value, scene[box])


# ``spinal_cord``: the head ends at the lowest axial plane whose brain cross-section is at least
# this fraction of the largest (the medulla below it is a few per cent; the cerebellum more).
CORD_AREA_FRACTION = 0.05


def _split_cord(brain_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(head brain, spinal cord): the brain's voxels above and below the skull base.

    Args:
        brain_mask: (n, n, n) bool on a grid whose third axis points up (RAS).
    """
    area = brain_mask.sum(axis=(0, 1))
    if not area.any():
        return brain_mask, np.zeros_like(brain_mask)
    base = int(np.nonzero(area >= CORD_AREA_FRACTION * area.max())[0][0])
    below = np.arange(brain_mask.shape[2]) < base  # (n,) planes under the base
    return brain_mask & ~below, brain_mask & below


def _neck_direction(rng: np.random.Generator) -> np.ndarray:
    """A unit vector below and behind the brain (canonical RAS: -z inferior, -y posterior)."""
    direction = np.array([0.0, -0.5, -1.0]) + 0.35 * rng.standard_normal(3)
    return direction / np.linalg.norm(direction)


def _paint_face(
    scene: np.ndarray,
    xyz: np.ndarray,
    brain_mask: np.ndarray,
    distance: np.ndarray,
    skull: float,
    cfg: SceneConfig,
    rng: np.random.Generator,
) -> None:
    """Paint a face below the front of the brain, in place, beyond the skull.

    The brain's extent gives the sizes: the face is an ellipsoid of soft tissue under the frontal
    lobes; each eye (radius 8-12 % of the brain's length, about a fetal eye's proportion) sits
    under the front of the brain, off the midline, with a dark rim (sclera) and a dark lens at
    its front.

    Args:
        scene: (n, n, n) intensities, modified.
        xyz: (n, n, n, 3) canonical mm (RAS).
        brain_mask: (n, n, n) bool, the brain.
        distance: (n, n, n) distance from the brain, mm.
        skull: Distance of the skull's outer edge from the brain, mm.
        cfg: Intensity ranges.
        rng: The face's random stream.
    """
    points = xyz[brain_mask]
    if len(points) == 0:
        return
    outside = distance > skull
    low, high = points.min(axis=0), points.max(axis=0)
    width, length, height = high - low
    middle = (low + high) / 2
    front = high[1]
    frontal = points[points[:, 1] > front - 0.25 * length]
    floor = float(frontal[:, 2].min())  # the underside of the frontal lobes
    face_centre = np.array(
        [
            middle[0],
            front - _uniform(rng, (0.1, 0.3)) * length,
            floor - skull - _uniform(rng, (0.05, 0.2)) * height,
        ]
    )
    face_radii = np.array(
        [
            _uniform(rng, (0.3, 0.45)) * width,
            _uniform(rng, (0.25, 0.4)) * length,
            _uniform(rng, (0.3, 0.45)) * height,
        ]
    )
    tilt = quat_to_matrix(torch.from_numpy(np.r_[1.0, 0.15 * rng.standard_normal(3)])).numpy()
    face = _ellipsoid(xyz, face_centre, face_radii, tilt) & outside
    scene[face] = _uniform(rng, cfg.tissue_intensity)
    radius = _uniform(rng, (0.08, 0.12)) * length
    rim = _uniform(rng, (0.5, 1.5))
    vitreous = _uniform(rng, cfg.csf_intensity)
    sclera, lens = _uniform(rng, cfg.skull_intensity), _uniform(rng, cfg.skull_intensity)
    for side in (-1.0, 1.0):
        centre = np.array(
            [
                middle[0] + side * _uniform(rng, (0.15, 0.25)) * width,
                front - _uniform(rng, (0.05, 0.2)) * length,
                floor - skull - _uniform(rng, (0.6, 1.2)) * radius,
            ]
        )
        from_centre = np.linalg.norm(xyz - centre, axis=-1)
        scene[(from_centre <= radius + rim) & outside] = sclera
        scene[(from_centre <= radius) & outside] = vitreous
        lens_centre = centre + np.array([0.0, 0.7 * radius, 0.0])
        scene[(np.linalg.norm(xyz - lens_centre, axis=-1) <= 0.3 * radius) & outside] = lens


def _scaled_brain(
    brain: CanonicalVolume,
    points: torch.Tensor,
    cfg: SceneConfig,
    rng: np.random.Generator,
    seed: int,
    tissue_labels: torch.Tensor | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Step 1: the brain's intensities and mask at the scene's points, at a random scale.

    The scene at x shows the brain at x / scale; its intensities are raised to a random gamma,
    or, with ``tissue_labels``, replaced by a random intensity per label from the stream
    ``[seed, 1]`` (SynthSeg-style), slightly blurred.

    Returns:
        (n, n, n) float64 intensities and (n, n, n) bool brain mask.
    """
    low, high = (math.log(v) for v in cfg.brain_scale)
    scale = math.exp(rng.uniform(low, high))
    source = brain.to("cpu")
    moved = (points / scale).float()
    intensity = sample_world(source.image, moved).numpy().astype(np.float64)
    brain_mask = (
        sample_world(Image(source.mask.float(), source.image.affine), moved, "nearest").numpy()
        > 0.5
    )
    intensity = np.clip(intensity, 0.0, None) ** _uniform(rng, cfg.gamma)
    if tissue_labels is not None:  # SynthSeg-style: a random intensity per label, own stream
        label_rng = np.random.default_rng([seed, 1])
        sampled = sample_world(Image(tissue_labels.float(), source.image.affine), moved, "nearest")
        tissue = sampled.numpy().astype(np.int64)
        values = label_rng.uniform(0.1, 1.0, size=int(tissue.max()) + 1)
        synthetic = ndimage.gaussian_filter(values[tissue], 0.5)
        intensity = np.where(brain_mask, synthetic, intensity)
    return intensity, brain_mask


def _body_and_fluid(
    xyz: np.ndarray,
    radius: float,
    scalp: float,
    cfg: SceneConfig,
    rng: np.random.Generator,
    face_rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 3: the fetal body beside the head, the amniotic fluid and the abdomen around them.

    The body lies in a random direction from the head (with ``face``: below and behind it,
    drawn from ``face_rng``); the fluid and the abdomen are perturbed ellipsoids.

    Returns:
        (n, n, n) bool masks of the body, the fluid and the abdomen.
    """
    n = xyz.shape[0]
    direction = rng.standard_normal(3)
    direction /= np.linalg.norm(direction)
    if cfg.face:
        direction = _neck_direction(face_rng)
    body_radii = radius * rng.uniform(*cfg.body_scale, size=3) * np.array([1.0, 1.0, 1.5])
    body_centre = direction * (radius + scalp + body_radii[2] * rng.uniform(0.6, 0.9))
    body = _ellipsoid(xyz, body_centre, body_radii, _random_rotation(rng))
    margin = _uniform(rng, cfg.fluid_margin_mm)
    fluid_centre = body_centre * rng.uniform(0.3, 0.6)
    fluid_radii = (np.linalg.norm(body_centre - fluid_centre) + radius + margin) * rng.uniform(
        0.9, 1.2, size=3
    )
    wobble = cfg.irregularity * _smooth_noise(rng, (n, n, n), 15.0 / cfg.spacing_mm)
    fluid = _ellipsoid(xyz, fluid_centre, fluid_radii, _random_rotation(rng), wobble)
    abdomen_radii = fluid_radii + rng.uniform(*cfg.abdomen_margin_mm, size=3)
    wobble = cfg.irregularity * _smooth_noise(rng, (n, n, n), 25.0 / cfg.spacing_mm)
    abdomen = _ellipsoid(xyz, fluid_centre, abdomen_radii, _random_rotation(rng), wobble)
    return body, fluid, abdomen


def _maternal_labels(n: int, cfg: SceneConfig, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Step 4: a random label field (arg-max of smoothed noise channels) and its label count."""
    labels = int(rng.integers(cfg.maternal_labels[0], cfg.maternal_labels[1] + 1))
    sigma = _uniform(rng, cfg.maternal_smoothness_mm) / cfg.spacing_mm
    channels = np.stack([_smooth_noise(rng, (n, n, n), sigma) for _ in range(labels)])
    return channels.argmax(axis=0), labels


def _paint_cord(
    scene: np.ndarray, cord: np.ndarray, beneath: np.ndarray, cfg: SceneConfig, seed: int
) -> None:
    """Paint a canal around the spinal cord, in place: CSF, then bone (stream ``[seed, 3]``).

    Args:
        scene: (n, n, n) intensities, modified where ``beneath``.
        cord: (n, n, n) bool, the spinal cord.
        beneath: (n, n, n) bool, what lies beyond the head's scalp.
        cfg: Thickness is drawn here; intensity ranges from it.
        seed: The scene's seed.
    """
    cord_rng = np.random.default_rng([seed, 3])
    around = ndimage.distance_transform_edt(~cord, sampling=cfg.spacing_mm)
    fluid_mm = _uniform(cord_rng, (0.5, 2.0))
    bone_mm = fluid_mm + _uniform(cord_rng, (1.0, 4.0))
    scene[(around <= bone_mm) & beneath] = _uniform(cord_rng, cfg.skull_intensity)
    scene[(around <= fluid_mm) & beneath] = _uniform(cord_rng, cfg.csf_intensity)


def make_scene(
    brain: CanonicalVolume,
    config: SceneConfig | None = None,
    seed: int = 0,
    tissue_labels: torch.Tensor | None = None,
) -> CanonicalVolume:
    """A random whole-uterus scene around ``brain`` (module docstring).

    Args:
        brain: A canonical brain volume (e.g. an atlas age, :func:`load_canonical_volume`).
        config: The scene's ranges; ``None`` for ``SceneConfig()``.
        seed: Seed of every random choice (a scene is a pure function of its inputs and seed).
        tissue_labels: Optional (I, J, K) tissue labels on ``brain``'s grid (e.g. the atlas
            parcellation): the brain's intensities are then replaced by a random intensity per
            label (SynthSeg-style domain randomisation), slightly blurred.

    Returns:
        The scene: ``image`` (float32, the whole scene, brain 99th percentile ~1) and ``mask``
        (the brain, or all inside the skull with ``intracranial_mask``; bool) on a cubic grid
        of ``config.spacing_mm`` centred on the brain's
        canonical origin; ``centre_mm`` zero and ``intensity_scale`` 1.

    Raises:
        ValueError: If ``seed`` is negative.
    """
    cfg = SceneConfig() if config is None else config
    if not (is_integer(seed) and seed >= 0):
        raise ValueError(f"make_scene(): 'seed' must be an integer >= 0, got {seed!r}")
    rng = np.random.default_rng(seed)
    n = math.ceil(cfg.extent_mm / cfg.spacing_mm)
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] *= cfg.spacing_mm
    affine[:3, 3] = -(n - 1) / 2 * cfg.spacing_mm
    points = voxel_centres(Image(torch.zeros(n, n, n), affine))  # (n, n, n, 3) canonical mm
    # 1. The brain at a random scale.
    intensity, brain_mask = _scaled_brain(brain, points, cfg, rng, seed, tissue_labels)

    # 2. The head: shells by distance from the brain surface.
    # (with ``spinal_cord`` the head holds the brain above the skull base only)
    head_brain, cord = (brain_mask, np.zeros_like(brain_mask))
    if cfg.spinal_cord:
        head_brain, cord = _split_cord(brain_mask)
    distance = ndimage.distance_transform_edt(~head_brain, sampling=cfg.spacing_mm)
    csf = _uniform(rng, cfg.csf_mm)
    skull = csf + _uniform(rng, cfg.skull_mm)
    scalp = skull + _uniform(rng, cfg.scalp_mm)
    xyz = points.numpy()
    radius = float(np.linalg.norm(xyz[head_brain], axis=-1).max()) if head_brain.any() else 30.0

    # 3. Body and amniotic fluid.
    face_rng = np.random.default_rng([seed, 2])  # (own stream: scenes without faces unchanged)
    body, fluid, abdomen = _body_and_fluid(xyz, radius, scalp, cfg, rng, face_rng)

    # 4. Maternal tissue: a random label field with random intensities.
    maternal_label, labels = _maternal_labels(n, cfg, rng)
    tissue_values = rng.uniform(*cfg.tissue_intensity, size=labels)
    scene = tissue_values[maternal_label]

    # Paint from the outside in.
    scene = np.where(abdomen | fluid, scene, 0.0)
    # (no draw without organs: scenes made before organs existed stay the same)
    organs = (
        int(rng.integers(cfg.distractors[0], cfg.distractors[1] + 1)) if cfg.distractors[1] else 0
    )
    scene = np.where(fluid, _uniform(rng, cfg.csf_intensity), scene)
    if organs:  # a textured body (its own intensities on the label field) holding organs
        body_values = rng.uniform(*cfg.tissue_intensity, size=labels)
        scene = np.where(body, body_values[maternal_label], scene)
        _paint_organs(scene, xyz, (abdomen | fluid) & (distance > scalp), organs, cfg, rng)
    else:
        scene = np.where(body, _uniform(rng, cfg.tissue_intensity), scene)
    if cfg.face:
        _paint_face(scene, xyz, head_brain, distance, skull, cfg, face_rng)
    scene = np.where(distance <= scalp, _uniform(rng, cfg.tissue_intensity), scene)
    scene = np.where(distance <= skull, _uniform(rng, cfg.skull_intensity), scene)
    scene = np.where(distance <= csf, _uniform(rng, cfg.csf_intensity), scene)
    if cord.any():  # a canal through what is beneath the head (own stream)
        _paint_cord(scene, cord, distance > scalp, cfg, seed)
    if cfg.texture > 0:
        texture = 1.0 + cfg.texture * _smooth_noise(rng, (n, n, n), 2.0 / cfg.spacing_mm)
        scene = scene * np.clip(texture, 0.2, None)
    scene = np.where(brain_mask, intensity, scene)  # (the cord's too: it is neural tissue)
    reach = skull if cfg.skull_in_mask else csf
    mask = (head_brain | (distance <= reach)) if cfg.intracranial_mask else head_brain
    return CanonicalVolume(
        Image(torch.from_numpy(scene.astype(np.float32)), affine),
        torch.from_numpy(mask),
        torch.zeros(3, dtype=torch.float64),
        1.0,
    )
