"""Brain volumes in canonical space: masked, centred on the mask, intensity-normalised.

Canonical space (``docs/conventions.md``) is the volume's own world frame shifted so that the origin
is the centroid of the brain mask (the mean world position of the mask's voxels; the bench cases'
``atlas_centre_mm`` is the same point). Rotations about the canonical origin rotate the brain about
its centre, as in the paper.

Intensity rule: voxels outside the mask are set to 0 and the rest are divided by the
``percentile``-th percentile (default 99) of the intensities inside the mask, so that the brain's
bright end is ~1 whatever the scanner's scale; values are not clipped.

A volume may carry its tissue labels (an atlas folder's ``parcellation.nii.gz``,
:data:`ATLAS_LABELS`), on its grid and 0 outside the mask: what label-map synthesis
(:mod:`svr.sampling.synthesis`) draws new intensities from.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from svr.image import DEFAULT_PERCENTILE, Image, ImageError, load_nifti, voxel_to_world
from svr.validation import is_integer

ATLAS_LABELS = "parcellation.nii.gz"
"""The tissue label map beside an atlas folder's ``srr.nii.gz`` (1 white matter, 2 ventricles,
3 cerebellum, 4 extra-axial CSF, 5 cortical grey matter, 6 deep grey matter, 7 brainstem, 8
corpus callosum in the Fidon 2021, CRL 2017 and Wu 2021 atlases as laid out here)."""


@dataclass(frozen=True)
class CanonicalVolume:
    """A brain volume in canonical space.

    Attributes:
        image: Masked, normalised intensities; its affine maps voxels to canonical mm.
        mask: (I, J, K) bool brain mask on the same grid.
        centre_mm: (3,) float64 mask centroid in the source volume's world frame (mm); the
            canonical frame is the source frame translated by ``-centre_mm``.
        intensity_scale: The percentile value the intensities were divided by.
        labels: (I, J, K) int16 tissue labels on the same grid (0 outside the mask), or
            ``None`` (no label map).
    """

    image: Image
    mask: Tensor
    centre_mm: Tensor
    intensity_scale: float
    labels: Tensor | None = None

    @property
    def source_affine(self) -> Tensor:
        """(4, 4) voxel -> source-world affine (before centring)."""
        affine = self.image.affine.clone()
        affine[:3, 3] += self.centre_mm.to(affine)
        return affine

    def to(self, device: torch.device | str) -> CanonicalVolume:
        """A copy on ``device``."""
        return CanonicalVolume(
            self.image.to(device),
            self.mask.to(device),
            self.centre_mm.to(device),
            self.intensity_scale,
            None if self.labels is None else self.labels.to(device),
        )


def as_atlases(
    atlas: CanonicalVolume | Sequence[CanonicalVolume], caller: str, name: str = "atlas"
) -> tuple[CanonicalVolume, ...]:
    """One atlas or several (for example the two ages either side of a fetus's), as a tuple.

    Args:
        atlas: A canonical volume or a non-empty sequence of them.
        caller: The function to name in the error.
        name: The argument to name in the error.

    Returns:
        The atlases, at least one.

    Raises:
        TypeError: If ``atlas`` is neither, or holds something other than canonical volumes.
        ValueError: If the sequence is empty.
    """
    if isinstance(atlas, CanonicalVolume):
        return (atlas,)
    if not isinstance(atlas, Sequence) or isinstance(atlas, str | bytes):
        raise TypeError(
            f"{caller}(): '{name}' must be a CanonicalVolume or a sequence of them, got "
            f"{type(atlas).__name__}"
        )
    atlases = tuple(atlas)
    if not atlases:
        raise ValueError(f"{caller}(): '{name}' must hold at least one atlas, got none")
    for i, item in enumerate(atlases):
        if not isinstance(item, CanonicalVolume):
            raise TypeError(
                f"{caller}(): '{name}[{i}]' must be a CanonicalVolume, got {type(item).__name__}"
            )
    return atlases


def _label_map(labels: Image, volume: Image, brain: Tensor, name: str) -> Tensor:
    """``labels`` as int16 on ``volume``'s grid, 0 outside ``brain``; ValueError naming ``name``."""
    if labels.shape != volume.shape or not torch.allclose(
        labels.affine.to(volume.affine), volume.affine, atol=1e-4, rtol=0
    ):
        raise ValueError(
            f"{name}: labels and volume grids differ (shapes {labels.shape} and "
            f"{volume.shape}, or their affines)"
        )
    values = labels.data.to(torch.float64)
    rounded = values.round()
    if not bool(torch.isfinite(values).all()) or not torch.allclose(values, rounded, atol=1e-3):
        raise ValueError(f"{name}: the labels are not integers")
    if bool((rounded < 0).any()) or bool((rounded > torch.iinfo(torch.int16).max).any()):
        raise ValueError(f"{name}: the labels must be in [0, 32767]")
    return torch.where(brain, rounded, torch.zeros_like(rounded)).to(torch.int16)


def canonicalize(
    volume: Image,
    mask: Image,
    percentile: float = DEFAULT_PERCENTILE,
    name: str = "volume",
    labels: Image | None = None,
) -> CanonicalVolume:
    """Mask, centre and normalise a volume.

    Args:
        volume: Intensities.
        mask: Brain mask on the same grid (voxels > 0.5 are brain).
        percentile: In-mask intensity percentile mapped to 1, in (0, 100].
        name: How to name the inputs in error messages (e.g. the file names).
        labels: Tissue labels on the same grid (integers >= 0), kept as the volume's
            ``labels`` (0 outside the mask); ``None`` for none.

    Returns:
        The canonical volume, float32, on the inputs' device.

    Raises:
        ValueError: For grid mismatch, an empty mask, non-finite voxels, a bad percentile, a
            mask whose intensities are all zero, or labels that are not integers in [0, 32767].
    """
    if not 0 < percentile <= 100:
        raise ValueError(f"canonicalize(): 'percentile' must be in (0, 100], got {percentile}")
    if volume.shape != mask.shape or not torch.allclose(
        volume.affine, mask.affine.to(volume.affine), atol=1e-4, rtol=0
    ):
        raise ValueError(
            f"{name}: mask and volume grids differ (shapes {volume.shape} and "
            f"{mask.shape}, or their affines)"
        )
    if not bool(torch.isfinite(volume.data).all()):
        raise ValueError(f"{name}: the volume has NaN or Inf voxels")
    brain = mask.data > 0.5
    if not bool(brain.any()):
        raise ValueError(f"{name}: the mask is empty")
    scale = float(np.percentile(volume.data[brain].cpu().numpy(), percentile))
    if scale <= 0:
        raise ValueError(
            f"{name}: the {percentile}th percentile of the intensities in the mask "
            f"is {scale}; expected a positive value"
        )
    idx = torch.nonzero(brain).to(torch.float64)
    affine = volume.affine.to(torch.float64)
    centre = voxel_to_world(affine, idx).mean(0)
    canonical_affine = affine.clone()
    canonical_affine[:3, 3] -= centre
    data = torch.where(brain, volume.data / scale, torch.zeros_like(volume.data)).float()
    tissue = None if labels is None else _label_map(labels, volume, brain, name)
    return CanonicalVolume(Image(data, canonical_affine), brain, centre, scale, tissue)


def load_canonical_volume(
    volume_path: str | os.PathLike[str],
    mask_path: str | os.PathLike[str],
    percentile: float = DEFAULT_PERCENTILE,
    labels_path: str | os.PathLike[str] | None = None,
) -> CanonicalVolume:
    """Load a NIfTI brain volume and its mask (and tissue labels) into canonical space.

    Args:
        volume_path: The intensity volume (e.g. an atlas ``srr.nii.gz``).
        mask_path: Its brain mask (same grid).
        percentile: In-mask intensity percentile mapped to 1.
        labels_path: Its tissue label map (same grid; e.g. :func:`atlas_labels_path`), or
            ``None`` for a volume without labels.

    Returns:
        The canonical volume (CPU, float32).

    Raises:
        ImageError: Naming the file and the problem (missing, unreadable, not 3D, NaN/Inf, grid
            mismatch, empty mask, labels that are not integers).
    """
    volume, mask = load_nifti(volume_path), load_nifti(mask_path)
    labels = None if labels_path is None else load_nifti(labels_path)
    name = f"{volume_path} (mask {mask_path}" + (
        ")" if labels_path is None else f", labels {labels_path})"
    )
    try:
        return canonicalize(volume, mask, percentile, name=name, labels=labels)
    except ValueError as err:
        raise ImageError(str(err)) from err


def atlas_labels_path(volume_path: str | os.PathLike[str]) -> Path:
    """The tissue label map of an atlas folder's volume: :data:`ATLAS_LABELS` beside it.

    Raises:
        VolumeSourceError: If the file does not exist.
    """
    path = Path(volume_path).parent / ATLAS_LABELS
    if not path.exists():
        raise VolumeSourceError(f"{path} is missing (the tissue labels)")
    return path


class VolumeSourceError(ValueError):
    """The volumes asked for cannot be found (the message names the folder or files).

    Attributes:
        missing_ages: Gestational ages (weeks) asked for that have no volume; empty otherwise.
    """

    def __init__(self, message: str, missing_ages: Sequence[float] = ()) -> None:
        super().__init__(message)
        self.missing_ages = tuple(missing_ages)


def _atlas_entries(root: Path) -> list[tuple[float, Path, Path]]:
    """``(weeks, srr.nii.gz, mask.nii.gz)`` of each ``GA<weeks>*`` subfolder with a volume."""
    if not root.is_dir():
        raise VolumeSourceError(f"{root} is not a folder")
    found: list[tuple[float, Path, Path]] = []
    for sub in sorted(root.glob("GA*")):
        try:
            weeks = float(sub.name[2:4])
        except ValueError:
            raise VolumeSourceError(
                f"{sub} is not named GA<weeks> (e.g. GA28); move it out of {root}"
            ) from None
        if (sub / "srr.nii.gz").exists():
            found.append((weeks, sub / "srr.nii.gz", sub / "mask.nii.gz"))
    return found


def atlas_volume_paths(
    folder: str | os.PathLike[str],
    hold_out: Sequence[float] = (),
    only: Sequence[float] | None = None,
) -> list[tuple[Path, Path]]:
    """The ``(srr.nii.gz, mask.nii.gz)`` pairs of an atlas folder of ``GA<weeks>*`` subfolders.

    The layout is that of the sb-fidon2021 atlas (``GA28_operated/srr.nii.gz`` with its
    ``mask.nii.gz``); the gestational age is read from the two digits after ``GA``. Subfolders
    without ``srr.nii.gz`` are skipped.

    Args:
        folder: The atlas folder.
        hold_out: Gestational ages (weeks) to leave out.
        only: ``None`` for every age, else the gestational ages (weeks) to keep.

    Returns:
        The pairs, sorted by subfolder name.

    Raises:
        VolumeSourceError: If ``folder`` is not a folder, a ``GA*`` subfolder is not named
            ``GA<weeks>``, no volume is left, or an age in ``only`` has no volume.
    """
    root = Path(folder)
    found = _atlas_entries(root)
    if only is not None:
        missing = sorted(set(only) - {weeks for weeks, _, _ in found})
        if missing:
            ages = " ".join(f"{ga:g}" for ga in missing)
            raise VolumeSourceError(f"GA {ages}: no such GA*/srr.nii.gz in {root}", missing)
    pairs = [
        (volume, mask)
        for weeks, volume, mask in found
        if weeks not in hold_out and (only is None or weeks in only)
    ]
    if not pairs:
        raise VolumeSourceError(f"no GA*/srr.nii.gz volumes left in {root}")
    return pairs


def atlas_paths_near(
    folder: str | os.PathLike[str],
    weeks: float,
    window: float = 1.0,
    hold_out: Sequence[float] = (),
) -> list[tuple[Path, Path]]:
    """The ``(srr.nii.gz, mask.nii.gz)`` pairs of an atlas folder near a gestational age.

    Every volume whose age (the two digits after ``GA``) is within ``window`` weeks of
    ``weeks``, nearest first; where none is, those of the nearest age. A fetus of 28 weeks gets
    GA28, GA27 and GA29; one of 27.5 weeks GA27 and GA28.

    Args:
        folder: The atlas folder (the layout of :func:`atlas_volume_paths`).
        weeks: The fetus's gestational age (weeks, > 0).
        window: How far (weeks, >= 0) an atlas's age may be from ``weeks``.
        hold_out: Gestational ages (weeks) to leave out (an evaluation's own ages).

    Returns:
        The pairs, nearest age first (equally near: by subfolder name).

    Raises:
        VolumeSourceError: As :func:`atlas_volume_paths`.
        ValueError: If ``weeks`` is not positive or ``window`` is negative.
    """
    if not (math.isfinite(weeks) and weeks > 0):
        raise ValueError(f"atlas_paths_near(): 'weeks' must be a positive number, got {weeks}")
    if not (math.isfinite(window) and window >= 0):
        raise ValueError(f"atlas_paths_near(): 'window' must be >= 0 weeks, got {window}")
    root = Path(folder)
    found = [entry for entry in _atlas_entries(root) if entry[0] not in hold_out]
    if not found:
        raise VolumeSourceError(f"no GA*/srr.nii.gz volumes left in {root}")
    near = [entry for entry in found if abs(entry[0] - weeks) <= window]
    if not near:
        nearest = min(abs(entry[0] - weeks) for entry in found)
        near = [entry for entry in found if abs(entry[0] - weeks) == nearest]
    near.sort(key=lambda entry: abs(entry[0] - weeks))  # stable: by name where equally near
    return [(volume, mask) for _, volume, mask in near]


def load_volumes(
    pairs: Sequence[tuple[str | os.PathLike[str], str | os.PathLike[str]]] = (),
    phantom_ages: Sequence[float] = (28.0,),
    percentile: float = DEFAULT_PERCENTILE,
    labels: bool = False,
) -> tuple[list[CanonicalVolume], list[str]]:
    """Canonical volumes from ``(volume, mask)`` NIfTI pairs, else the built-in phantom.

    Args:
        pairs: ``(volume, mask)`` paths (e.g. from :func:`atlas_volume_paths`); when empty, one
            procedural phantom per age in ``phantom_ages`` (:mod:`svr.sampling.phantom`).
        phantom_ages: Gestational ages (weeks) of the phantoms, used only without ``pairs``.
        percentile: In-mask intensity percentile mapped to 1.
        labels: Also load each pair's tissue labels (:func:`atlas_labels_path`: atlas folders
            only); the phantoms have none.

    Returns:
        The volumes (CPU, float32) and a name for each: the volume's path, or ``"phantom GA
        <weeks>"``.

    Raises:
        ImageError: For an unusable file (the message names it).
        VolumeSourceError: If ``labels`` and a pair's label map is missing.
    """
    if pairs:
        volumes = [
            load_canonical_volume(v, m, percentile, atlas_labels_path(v) if labels else None)
            for v, m in pairs
        ]
        return volumes, [str(v) for v, _ in pairs]
    from svr.sampling.phantom import gestational_age_config, make_phantom

    volumes = [
        canonicalize(*make_phantom(gestational_age_config(ga)), percentile, name="phantom")
        for ga in phantom_ages
    ]
    return volumes, [f"phantom GA {ga:g}" for ga in phantom_ages]


def downsample_volume(volume: CanonicalVolume, factor: int) -> CanonicalVolume:
    """Average a canonical volume over ``factor``-cubed voxel blocks (a coarser copy, same frame).

    The canonical frame is kept: the new voxel centres are the means of the blocks' centres, so
    world positions are unchanged. The mask is the blocks' majority; a block inside it takes the
    most frequent of its non-zero labels. Meant for simulating coarse training data quickly
    (sampling a volume 8 times smaller is about 8 times faster).

    Args:
        volume: The volume.
        factor: Block side in voxels, >= 1 (1 returns ``volume``).

    Returns:
        The coarser volume.
    """
    if not (is_integer(factor) and factor >= 1):
        raise ValueError(f"downsample_volume(): 'factor' must be an int >= 1, got {factor!r}")
    if factor == 1:
        return volume
    both = torch.stack([volume.image.data.float(), volume.mask.float()])[None]
    pooled = torch.nn.functional.avg_pool3d(
        both, factor, stride=factor, ceil_mode=True, count_include_pad=False
    )[0]
    affine = volume.image.affine.to(torch.float64).clone()
    affine[:3, 3] += (factor - 1) / 2 * affine[:3, :3].sum(1)
    affine[:3, :3] *= factor
    mask = pooled[1] > 0.5
    labels = None if volume.labels is None else _majority_labels(volume.labels, mask, factor)
    return CanonicalVolume(
        Image(pooled[0].contiguous(), affine),
        mask,
        volume.centre_mm,
        volume.intensity_scale,
        labels,
    )


def _majority_labels(labels: Tensor, mask: Tensor, factor: int) -> Tensor:
    """The most frequent non-zero label of each ``factor``-cubed block (0 outside ``mask``)."""
    best = torch.zeros(mask.shape, dtype=torch.float32)
    out = torch.zeros(mask.shape, dtype=labels.dtype)
    for value in torch.unique(labels).tolist():
        if value == 0:
            continue
        share = torch.nn.functional.avg_pool3d(
            (labels == value).float()[None, None],
            factor,
            stride=factor,
            ceil_mode=True,
            count_include_pad=False,
        )[0, 0]
        more = share > best
        best = torch.where(more, share, best)
        out = torch.where(more, torch.tensor(value, dtype=labels.dtype), out)
    return torch.where(mask, out, torch.zeros_like(out))
