"""Tissue labels of a reconstruction by multi-atlas segmentation.

The atlases of the ages nearest the fetus's (``--gestational-age``, from one or more atlas
folders in the ``GA<weeks>*/{srr,mask,parcellation}.nii.gz`` layout) are each registered to the
reconstruction (:mod:`svr.tissue.registration`: affine; then, on the reconstruction cut to the
atlases' brains, affine and demons again), their label maps pulled
onto the reconstruction's own grid as per-label probabilities and fused by locally weighted
voting (:mod:`svr.tissue.fusion`). What comes back says how sure it is: each atlas's fit, the
fused probability and the atlases' agreement per voxel, and a verdict.

A volume that is not in an atlas frame (its brain turned by more than
``TissueConfig.max_rotation_deg`` from every atlas, or the affine fit fails) is refused
with :class:`NotInAtlasFrameError`: labels would be pulled from the wrong places.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import SimpleITK as sitk  # noqa: N813 (the usual alias)

from svr.image import Image, load_nifti
from svr.sampling.volume import atlas_labels_path, atlas_paths_near
from svr.tissue.fusion import FusedLabels, fuse_labels, local_weights
from svr.tissue.labels import TISSUE_LABELS
from svr.tissue.registration import (
    AtlasRegistrationConfig,
    AtlasWarp,
    register_atlas,
    resample_like,
    rotation_degrees,
)
from svr.tissue.sitk_images import from_sitk, to_sitk
from svr.validation import (
    check_bool,
    check_instance,
    check_int,
    check_number,
    check_number_tuple,
)

__all__ = [
    "AtlasFit",
    "NotInAtlasFrameError",
    "TissueConfig",
    "TissueSegmentation",
    "atlas_age",
    "segment_volume",
    "select_atlases",
]

log = logging.getLogger(__name__)

N_LABELS = len(TISSUE_LABELS) + 1
"""Label values 0 (background) to 8."""


class NotInAtlasFrameError(ValueError):
    """The volume's brain is not in an atlas frame (the message says how far it is)."""


@dataclass(frozen=True)
class TissueConfig:
    """How a reconstruction's tissue labels are found.

    Attributes:
        window_weeks: Atlases whose age is within this many weeks of the fetus's are used
            (the nearest age when none is), >= 0.
        max_atlases: At most this many, nearest age first, >= 1.
        hold_out: Atlas ages (weeks) never used (evaluations on an atlas's own ages).
        registration: How each atlas is registered.
        fusion_sigma_mm: Window of the local vote weights (mm, > 0).
        fusion_power: Exponent of the local vote weights (>= 0; 0: majority voting).
        max_rotation_deg: A volume whose best atlas fit turns it more than this is not in an
            atlas frame (an error), degrees.
        min_ncc: Below this correlation of the best-fitting atlas after the affine step the
            volume is not in an atlas frame either (an error).
        trusted_ncc: Below this correlation after the deformable step the labels are flagged
            as not to be trusted (a warning, the labels are still written).
        trusted_agreement: Below this mean agreement of the atlases inside the brain the labels
            are flagged too.
        trim_to_affine_brain: Label only the voxels inside most atlases' brain masks after the
            (last) affine step (0 elsewhere): a reconstruction's brain mask is often looser than
            the brain, and the deformable step stretches the atlases over what lies inside it.
        refine_brain: Register twice: first the affine step alone, then everything again on
            the volume cut to where any atlas's brain lies after that step, as the atlases
            themselves are cut to their brains (a loose mask's non-brain signal otherwise
            draws every atlas outwards, and each label's volume with it).

    Raises:
        ConfigFieldError: On construction, naming the field, for a value out of range.
    """

    window_weeks: float = 1.0
    max_atlases: int = 3
    hold_out: tuple[float, ...] = ()
    registration: AtlasRegistrationConfig = field(default_factory=AtlasRegistrationConfig)
    fusion_sigma_mm: float = 2.0
    fusion_power: float = 1.0
    max_rotation_deg: float = 25.0
    min_ncc: float = 0.4
    trusted_ncc: float = 0.8
    trusted_agreement: float = 0.8
    trim_to_affine_brain: bool = True
    refine_brain: bool = True

    def __post_init__(self) -> None:
        owner = "TissueConfig"
        check_number(owner, "window_weeks", self.window_weeks, ge=0)
        check_int(owner, "max_atlases", self.max_atlases, minimum=1)
        check_number(owner, "fusion_sigma_mm", self.fusion_sigma_mm, gt=0)
        check_number(owner, "fusion_power", self.fusion_power, ge=0)
        check_number(owner, "max_rotation_deg", self.max_rotation_deg, gt=0, le=180)
        for name in ("min_ncc", "trusted_ncc", "trusted_agreement"):
            check_number(owner, name, getattr(self, name), ge=0, le=1)
        hold_out = check_number_tuple(owner, "hold_out", self.hold_out, gt=0, allow_list=True)
        object.__setattr__(self, "hold_out", hold_out)
        check_instance(owner, "registration", self.registration, AtlasRegistrationConfig)
        check_bool(owner, "trim_to_affine_brain", self.trim_to_affine_brain)
        check_bool(owner, "refine_brain", self.refine_brain)


class AtlasFit(NamedTuple):
    """How one atlas fitted the reconstruction.

    Attributes:
        path: The atlas's ``srr.nii.gz``.
        weeks: Its gestational age.
        rotation: (3, 3) the affine's rotation (RAS): the volume's directions to the atlas's.
        scale: The affine's mean scale (atlas size over the reconstruction's brain).
        ncc_affine: Correlation after the first affine step, over the volume's own brain.
        ncc: Correlation after the last (deformable) step, over the brain it was registered on
            (with ``refine_brain``, the volume cut to the atlases' brains).
        weight: Its mean vote weight inside the brain.
    """

    path: Path
    weeks: float
    rotation: np.ndarray
    scale: float
    ncc_affine: float
    ncc: float
    weight: float

    @property
    def rotation_deg(self) -> float:
        """The rotation's angle (degrees): the volume's frame against the atlas's."""
        return rotation_degrees(self.rotation)


class TissueSegmentation(NamedTuple):
    """A reconstruction's tissue labels and how sure they are.

    Attributes:
        labels: (I, J, K) uint8 labels on the volume's grid (0 outside its brain).
        probability: (I, J, K) fused probability of each voxel's label.
        agreement: (I, J, K) fraction of the atlases that chose the same label.
        atlases: One fit per atlas used.
        atlas_volumes_ml: Per atlas, each label's volume (mL) it alone would give (its warped
            labels on the volume's grid): their spread is the atlases' disagreement.
        problems: What failed the checks (:class:`TissueConfig`), one line each; empty when
            the labels can be trusted.
    """

    labels: np.ndarray
    probability: np.ndarray
    agreement: np.ndarray
    atlases: list[AtlasFit]
    atlas_volumes_ml: list[dict[int, float]]
    problems: list[str]

    @property
    def trusted(self) -> bool:
        """Whether the labels pass every check."""
        return not self.problems


def atlas_age(path: str | os.PathLike[str]) -> float:
    """The gestational age (weeks) of an atlas volume: the digits after ``GA`` of its folder."""
    match = re.match(r"GA(\d+(?:\.\d+)?)", Path(path).parent.name)
    if match is None:
        raise ValueError(f"{Path(path).parent}: not named GA<weeks> (e.g. GA28)")
    return float(match.group(1))


def select_atlases(
    folders: Sequence[str | os.PathLike[str]], weeks: float, config: TissueConfig
) -> list[tuple[Path, Path, Path]]:
    """The ``(srr, mask, parcellation)`` paths of the atlases to use, nearest age first.

    Args:
        folders: Atlas folders (each of ``GA<weeks>*`` subfolders).
        weeks: The fetus's gestational age.
        config: ``window_weeks``, ``max_atlases`` and ``hold_out``.

    Returns:
        At most ``max_atlases`` triples over all folders, the nearest ages first.

    Raises:
        VolumeSourceError: A folder is missing, holds no atlas or lacks a parcellation.
    """
    found: list[tuple[float, Path, Path]] = []
    for folder in folders:
        for volume, mask in atlas_paths_near(folder, weeks, config.window_weeks, config.hold_out):
            found.append((abs(atlas_age(volume) - weeks), volume, mask))
    found.sort(key=lambda entry: entry[0])
    return [
        (volume, mask, atlas_labels_path(volume)) for _, volume, mask in found[: config.max_atlases]
    ]


def _one_hot_warped(
    labels: sitk.Image, reference: sitk.Image, transform: sitk.Transform
) -> np.ndarray:
    """(L, I, J, K) float32 probability of each label value, warped onto ``reference``."""
    field = sitk.TransformToDisplacementField(
        transform,
        sitk.sitkVectorFloat64,
        reference.GetSize(),
        reference.GetOrigin(),
        reference.GetSpacing(),
        reference.GetDirection(),
    )
    dense = sitk.DisplacementFieldTransform(field)
    out = []
    for value in range(N_LABELS):
        indicator = sitk.Cast(labels == value, sitk.sitkFloat32)
        out.append(from_sitk(resample_like(indicator, reference, dense)))
    probability = np.stack(out).astype(np.float32)
    # outside the atlas's grid nothing was sampled: background
    probability[0] += np.clip(1.0 - probability.sum(0), 0.0, 1.0)
    return probability


class _Atlas(NamedTuple):
    """One atlas age loaded for registration."""

    path: Path
    weeks: float
    image: sitk.Image  # its brain (srr times mask), float32
    mask: sitk.Image  # uint8
    labels: sitk.Image


def _load_atlas(srr: Path, mask_path: Path, parcellation: Path) -> _Atlas:
    atlas = load_nifti(srr)
    mask = load_nifti(mask_path).data.numpy() > 0.5
    affine = atlas.affine.numpy()
    return _Atlas(
        srr,
        atlas_age(srr),
        to_sitk(atlas.data.numpy() * mask, affine),
        to_sitk(mask.astype(np.uint8), affine),
        to_sitk(load_nifti(parcellation).data.numpy().round(), affine),
    )


def _register_atlases(
    array: np.ndarray,
    brain: np.ndarray,
    affine: np.ndarray,
    atlases: list[_Atlas],
    registration: AtlasRegistrationConfig,
) -> list[AtlasWarp]:
    """Each atlas registered to the volume ``array`` (0 outside ``brain``)."""
    fixed = to_sitk(array, affine)
    fixed_mask = to_sitk(brain.astype(np.uint8), affine)
    return [register_atlas(fixed, fixed_mask, a.image, a.mask, registration) for a in atlases]


def _affine_brains(
    atlases: list[_Atlas], warps: list[AtlasWarp], reference: sitk.Image
) -> list[np.ndarray]:
    """(I, J, K) each atlas's brain mask pulled onto ``reference``'s grid by its affine alone."""
    return [
        from_sitk(resample_like(atlas.mask, reference, warp.affine))
        for atlas, warp in zip(atlases, warps, strict=True)
    ]


def _check_frame(warps: list[AtlasWarp], config: TissueConfig, name: str) -> None:
    """Refuse a volume that no atlas fits without a large turn (:class:`NotInAtlasFrameError`)."""
    best = max(warps, key=lambda warp: warp.ncc_affine)
    if best.rotation_deg > config.max_rotation_deg or best.ncc_affine < config.min_ncc:
        raise NotInAtlasFrameError(
            f"{name}: not in an atlas frame (the best atlas fit turns it "
            f"{best.rotation_deg:.0f} deg, correlation {best.ncc_affine:.2f}); "
            "reconstruct it with --registration cnn and an --atlas-volume, or give its "
            "atlas-frame output"
        )


def segment_volume(
    volume: Image,
    atlas_dirs: Sequence[str | os.PathLike[str]],
    weeks: float,
    config: TissueConfig | None = None,
    mask: np.ndarray | None = None,
    name: str = "volume",
) -> TissueSegmentation:
    """Tissue labels of a reconstruction in the atlases' label set, on its own grid.

    Args:
        volume: The reconstruction (T2w, in an atlas frame up to a few degrees).
        atlas_dirs: Atlas folders (``GA<weeks>*/{srr,mask,parcellation}.nii.gz``).
        weeks: The fetus's gestational age (weeks, > 0).
        config: Settings (defaults: :class:`TissueConfig`).
        mask: (I, J, K) bool brain on the volume's grid; default: its nonzero voxels.
        name: How errors name the volume (its file).

    Returns:
        The labels and how sure they are.

    Raises:
        NotInAtlasFrameError: If no atlas fits the brain without turning it more than
            ``max_rotation_deg`` or its correlation stays under ``min_ncc``.
        VolumeSourceError: If an atlas folder is missing or has no atlas near the age.
        ValueError: If ``mask`` is empty or not on the volume's grid.
    """
    config = config or TissueConfig()
    array = volume.data.detach().cpu().numpy().astype(np.float32)
    affine = volume.affine.detach().cpu().numpy()
    brain = array > 0 if mask is None else np.asarray(mask, dtype=bool)
    if brain.shape != array.shape:
        raise ValueError(f"{name}: mask shape {brain.shape} is not the volume's {array.shape}")
    if not brain.any():
        raise ValueError(f"{name}: the brain is empty (no voxel above 0 or in the mask)")
    array = np.where(brain, array, 0.0).astype(np.float32)
    atlases = [_load_atlas(*paths) for paths in select_atlases(atlas_dirs, weeks, config)]
    # with a second pass the first needs the affine step alone
    first = _register_atlases(
        array,
        brain,
        affine,
        atlases,
        replace(config.registration, deformable=False)
        if config.refine_brain
        else config.registration,
    )
    _check_frame(first, config, name)
    fixed = to_sitk(array, affine)
    affine_brains = _affine_brains(atlases, first, fixed)
    warps = first
    if config.refine_brain:
        # the atlases are brains cut out by their masks; cut the volume alike, keeping every
        # voxel that one of them calls brain after the affine step, and register again (a loose
        # mask's non-brain signal otherwise draws every atlas outwards)
        cut = brain & (np.max(affine_brains, axis=0) >= 0.5)
        if cut.any():
            warps = _register_atlases(
                np.where(cut, array, 0.0).astype(np.float32),
                cut,
                affine,
                atlases,
                config.registration,
            )
            affine_brains = _affine_brains(atlases, warps, fixed)
    pairs = list(zip(atlases, warps, strict=True))
    probabilities = [_one_hot_warped(a.labels, fixed, w.transform) for a, w in pairs]
    images = [from_sitk(resample_like(a.image, fixed, w.transform)) for a, w in pairs]
    fits = [
        AtlasFit(
            atlas.path, atlas.weeks, warp.rotation, warp.scale, check.ncc_affine, warp.ncc, 0.0
        )
        for atlas, warp, check in zip(atlases, warps, first, strict=True)
    ]
    for fit in fits:
        log.info(
            "atlas %s: turned %.1f deg, scale %.3f, NCC %.3f affine, %.3f deformable",
            fit.path.parent.name,
            fit.rotation_deg,
            fit.scale,
            fit.ncc_affine,
            fit.ncc,
        )
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    sx, sy, sz = (float(config.fusion_sigma_mm / step) for step in spacing)
    weights = local_weights(array, images, brain, (sx, sy, sz), config.fusion_power)
    fused: FusedLabels = fuse_labels(probabilities, weights, brain)
    if config.trim_to_affine_brain:
        # the demons stretch the atlas brains over non-brain signal inside a loose mask: keep
        # labels only where most atlases' brains lie after the affine step alone
        outside = np.mean(affine_brains, axis=0) < 0.5
        fused = fused._replace(labels=np.where(outside, 0, fused.labels).astype(np.uint8))
    fits = [
        fit._replace(weight=float(w[brain].mean())) for fit, w in zip(fits, weights, strict=True)
    ]
    voxel_ml = float(abs(np.linalg.det(affine[:3, :3]))) / 1000.0
    atlas_volumes = [
        {
            label.value: float((np.argmax(p, axis=0)[brain] == label.value).sum() * voxel_ml)
            for label in TISSUE_LABELS
        }
        for p in probabilities
    ]
    problems = []
    best_ncc = max(fit.ncc for fit in fits)
    if best_ncc < config.trusted_ncc:
        problems.append(
            f"the atlases fit the volume poorly (best correlation {best_ncc:.2f} < "
            f"{config.trusted_ncc})"
        )
    agreement = float(fused.agreement[brain].mean())
    if agreement < config.trusted_agreement:
        problems.append(
            f"the atlases disagree (mean agreement {agreement:.2f} < {config.trusted_agreement})"
        )
    return TissueSegmentation(
        fused.labels,
        fused.probability,
        fused.agreement,
        fits,
        atlas_volumes,
        problems,
    )
