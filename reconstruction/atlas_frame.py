"""The reconstructed volume brought into an atlas's frame: rigid registration from many starts.

A learned or per-stack canonical frame is only as good as its estimate (a few degrees, a few
millimetres, a half turn if a brain looked the same either way, or tens of degrees where the
stacks' estimates were unsure). :func:`align_to_atlas` registers the finished volume rigidly to an
atlas of about the same age from several starts: the frame it is in, that frame turned by 180
degrees about each axis, and the 8 frames of the volume's own brain-mask principal axes
(:func:`~svr.reconstruction.initialisation.stack_pose.mask_axis_hypotheses`), so that a wrong
start is found and left. Each start is fitted coarsely; the volume's own frame and the two best
distinct others are fitted finely, and another frame replaces the volume's own only if it fits
the atlas clearly better (:data:`KEEP_MARGIN`): where a brain matches the atlas poorly (another
anatomy, real contrast), the right frame and its front-back twin fit within noise of each other,
and the frame the learned stack poses agree on is the better evidence.

The origin is then put at the centre of the brain, which is what canonical space means
(``docs/conventions.md``), as the slices' brain masks give it
(:func:`svr.reconstruction.slices.mask_centre`): an atlas of another age or cohort differs in
shape and would pull the centre, and the volume's coverage mask reaches past the brain (the slice
profile), more on one side than the other. Everything is relabelled in that frame: the volume's
and mask's affines and every slice pose. Nothing is resampled, so the volume's values are
unchanged.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from svr.geometry import half_turns, rotation_angle
from svr.image import Image, voxel_to_world
from svr.reconstruction.atlas_fit import (
    KEEP_MARGIN,
    AtlasFitConfig,
    atlas_levels,
    fit_to_atlas,
    preferred_atlas,
)
from svr.reconstruction.initialisation.stack_pose import mask_axis_hypotheses
from svr.reconstruction.result import ReconstructionResult, relabelled
from svr.reconstruction.slices import mask_centre
from svr.sampling.volume import CanonicalVolume, as_atlases

__all__ = [
    "COARSE_FIT",
    "FLIPS",
    "AtlasChoice",
    "AtlasFit",
    "align_to_atlas",
    "atlas_starts",
    "atlas_transform",
    "atlas_turn_line",
    "best_atlas_transform",
]

log = logging.getLogger(__name__)

FLIPS = ("none", "x", "y", "z")
"""The start hypotheses: the frame as it is, and turned by 180 degrees about x, y or z."""


def _flip(axis: str) -> Tensor:
    if axis == "none":
        return torch.eye(4, dtype=torch.float64)
    return half_turns()["xyz".index(axis)]


COARSE_FIT = AtlasFitConfig(blur_mm=(4.0, 2.0), iterations=15, max_points=4000)
"""The fit of every start: fewer iterations and a subsample of the mask, enough to rank them (a
single 4 mm level is not: on a smooth brain, wrong frames reach a higher NCC there)."""

DISTINCT_DEG = 20.0
"""Fitted frames closer than this (degrees) are the same frame."""


class AtlasFit(NamedTuple):
    """What :func:`atlas_transform` found.

    Attributes:
        transform: (4, 4) float64, volume world -> atlas canonical (the fitted rotation, and the
            translation that puts the brain mask's centroid at the origin).
        start: The start whose fit won (``"none"``: the volume's own frame).
        scores: Each start's NCC after the coarse fit.
        final: The NCC after the final fit of each start fitted finely (the volume's own frame
            and the best distinct others).
    """

    transform: Tensor
    start: str
    scores: dict[str, float]
    final: dict[str, float]


def _mask_points(volume: Image, mask: Tensor, caller: str) -> Tensor:
    """World points (N, 3) float64 of a volume's mask voxels, at least 4."""
    idx = torch.nonzero(mask).to(torch.float64)
    if len(idx) < 4:
        raise ValueError(f"{caller}(): 'mask' has fewer than 4 voxels")
    return voxel_to_world(volume.affine.to(torch.float64), idx)


def atlas_starts(volume: Image, mask: Tensor) -> dict[str, Tensor]:
    """The starting frames of :func:`atlas_transform`, by name.

    Args:
        volume: The volume (its world frame anywhere).
        mask: Its (I, J, K) bool brain mask on its grid, at least 4 voxels.

    Returns:
        ``"none"`` (the volume's own frame, the identity), ``"x"``, ``"y"``, ``"z"`` (that frame
        turned by 180 degrees about the axis), then ``"axes0"``..``"axes7"`` (the principal-axis
        frames of the mask,
        :func:`~svr.reconstruction.initialisation.stack_pose.mask_axis_hypotheses`): (4, 4) float64
        transforms, volume world -> a candidate canonical frame.

    Raises:
        ValueError: If the mask has fewer than 4 voxels.
    """
    return _starts(_mask_points(volume, mask, "atlas_starts"))


def _starts(points: Tensor) -> dict[str, Tensor]:
    """:func:`atlas_starts` from the mask's (N, 3) world points."""
    out = {axis: _flip(axis) for axis in FLIPS}
    for i, frame in enumerate(mask_axis_hypotheses(points)):
        out[f"axes{i}"] = frame
    return out


def atlas_transform(
    volume: Image,
    mask: Tensor,
    atlas: CanonicalVolume,
    config: AtlasFitConfig | None = None,
    keep_margin: float = KEEP_MARGIN,
    alternatives: int = 2,
    centre: Tensor | None = None,
) -> AtlasFit:
    """The rigid transform from a volume's frame to an atlas's canonical frame.

    Every start (the volume's frame and its :data:`FLIPS`, then the 8 principal-axis frames of its
    brain mask, named ``"axes0"``..``"axes7"``) is fitted to the atlas with :data:`COARSE_FIT`.
    The volume's own frame and the ``alternatives`` best-scored starts whose fits are distinct
    from it and from each other (:data:`DISTINCT_DEG`) are fitted again with ``config``. The best
    of the others replaces the volume's own frame if its NCC is higher by more than
    ``keep_margin``.

    Args:
        volume: The volume (its world frame anywhere; best about the canonical one).
        mask: Its (I, J, K) bool brain mask on its grid, at least 4 voxels.
        atlas: The atlas brain in canonical space.
        config: The final fit's settings (default :class:`AtlasFitConfig`).
        keep_margin: NCC by which another frame must beat the volume's own, >= 0 (0: the best
            final NCC wins).
        alternatives: How many other starts are fitted finely, >= 1.
        centre: (3,) the brain's centre in the volume's world frame (mm), put at the origin;
            default the centroid of ``mask``.

    Returns:
        The :class:`AtlasFit` found.

    Raises:
        ValueError: If the mask has fewer than 4 voxels, ``keep_margin`` < 0 or
            ``alternatives`` < 1.
    """
    if not keep_margin >= 0:
        raise ValueError(f"atlas_transform(): 'keep_margin' must be >= 0, got {keep_margin}")
    if alternatives < 1:
        raise ValueError(f"atlas_transform(): 'alternatives' must be >= 1, got {alternatives}")
    points = _mask_points(volume, mask, "atlas_transform")
    named = _starts(points)
    names, starts = list(named), list(named.values())
    levels = atlas_levels(atlas, COARSE_FIT)
    fitted, nccs = [], []
    for start in starts:
        frame, ncc = fit_to_atlas(volume, mask, start, atlas, COARSE_FIT, levels)
        fitted.append(frame)
        nccs.append(ncc)
    scores = {name: float(v) for name, v in zip(names, nccs, strict=True)}
    final_config = config or AtlasFitConfig()
    reuse = levels if final_config.blur_mm == COARSE_FIT.blur_mm else None
    best, best_ncc = fit_to_atlas(volume, mask, fitted[0], atlas, final_config, reuse)
    own_ncc, won = best_ncc, 0
    final = {names[0]: own_ncc}
    seen = [best]
    limit = math.radians(DISTINCT_DEG)
    for i in sorted(range(1, len(names)), key=lambda k: -nccs[k]):
        if len(final) > alternatives:
            break
        if any(float(rotation_angle(fitted[i], other)) < limit for other in seen):
            continue
        frame, ncc = fit_to_atlas(volume, mask, fitted[i], atlas, final_config, reuse)
        seen.append(frame)
        if float(rotation_angle(frame, seen[0])) < limit:
            continue  # the fine fit went back to the volume's own frame
        final[names[i]] = ncc
        if ncc > own_ncc + keep_margin and ncc > best_ncc:
            best, best_ncc, won = frame, ncc, i
    best = best.clone()
    origin = points.mean(0) if centre is None else centre.to(points)
    best[:3, 3] = -best[:3, :3] @ origin
    return AtlasFit(best, names[won], scores, final)


class AtlasChoice(NamedTuple):
    """What :func:`best_atlas_transform` found.

    Attributes:
        chosen: The winning atlas's index in the atlases given.
        fit: Its :class:`AtlasFit`.
        ncc: Each atlas's NCC after its final fit (of the frame its own fit chose), in order.
    """

    chosen: int
    fit: AtlasFit
    ncc: tuple[float, ...]


def best_atlas_transform(
    volume: Image,
    mask: Tensor,
    atlases: CanonicalVolume | Sequence[CanonicalVolume],
    config: AtlasFitConfig | None = None,
    centre: Tensor | None = None,
    keep_margin: float = KEEP_MARGIN,
) -> AtlasChoice:
    """:func:`atlas_transform` to each of several atlases; the first unless another fits better.

    Each atlas (for example the fetus's age and the weeks either side, the nearest first) gets
    its own :func:`atlas_transform`. The first atlas's frame is kept unless the best of the
    others fits the volume better by more than ``keep_margin`` (NCC after the final fit), as
    :func:`atlas_transform` keeps a volume's own frame: where a brain matches no atlas well,
    their fits are within noise of each other and the first, the age-matched one, is the better
    evidence; where the age's own atlas is missing, a neighbouring age whose brain is clearly
    more like the fetus's sets the frame.

    Args:
        volume: The volume (its world frame anywhere; best about the canonical one).
        mask: Its (I, J, K) bool brain mask on its grid, at least 4 voxels.
        atlases: One atlas or several, in canonical space, the preferred first.
        config: The final fits' settings (default :class:`AtlasFitConfig`).
        centre: (3,) the brain's centre in the volume's world frame (mm); see
            :func:`atlas_transform`.
        keep_margin: NCC by which another atlas must fit better than the first, >= 0 (0: the
            best fit wins).

    Returns:
        The :class:`AtlasChoice`.

    Raises:
        ValueError: If the mask has fewer than 4 voxels, ``atlases`` is empty or
            ``keep_margin`` < 0.
        TypeError: If ``atlases`` holds something other than canonical volumes.
    """
    if not keep_margin >= 0:
        raise ValueError(f"best_atlas_transform(): 'keep_margin' must be >= 0, got {keep_margin}")
    found = [
        atlas_transform(volume, mask, atlas, config, centre=centre)
        for atlas in as_atlases(atlases, "best_atlas_transform", "atlases")
    ]
    fits = tuple(float(item.final[item.start]) for item in found)
    best = preferred_atlas(fits, keep_margin)
    if len(found) > 1:
        log.info(
            "atlas frame: atlas %d of %d (final NCC %s; another than the first only if higher "
            "by %g)",
            best + 1,
            len(found),
            ", ".join(f"{v:.3f}" for v in fits),
            keep_margin,
        )
    return AtlasChoice(best, found[best], fits)


def align_to_atlas(
    result: ReconstructionResult,
    atlas: CanonicalVolume | Sequence[CanonicalVolume],
    config: AtlasFitConfig | None = None,
    max_turn_deg: float | None = None,
) -> ReconstructionResult:
    """A reconstruction relabelled in the atlas's canonical frame (see the module docstring).

    Args:
        result: A finished reconstruction (its frame best roughly canonical; any will do).
        atlas: The atlas brain in canonical space, or several, the preferred first (the first
            unless another fits clearly better, :func:`best_atlas_transform`).
        config: The final fit's settings.
        max_turn_deg: The largest turn (degrees) the fit may make of a frame that other evidence
            already supports (a learned frame with a clear margin): a fit that turns it farther
            went to another optimum (an atlas of another anatomy or contrast fits many frames
            about as well) and only its centring is kept. ``None``: no limit.

    Returns:
        The same result with the volume's, mask's and initial volume's affines and every slice
        pose premultiplied by the fitted transform (:func:`~svr.reconstruction.result.relabelled`),
        each atlas's NCC after its fit (``atlas_ncc``), the index of the atlas whose frame it took
        (``atlas_chosen``) and the fit's margin: the NCC of the frame kept minus the best NCC of a
        distinct frame fitted finely (``atlas_margin``; ``None`` where no distinct frame was),
        and the fit's turn and whether it was applied (``atlas_turn_deg``, ``atlas_turn_applied``).
    """
    volume = result.volume
    kept = ~result.excluded.to(result.slices.device)
    centre = mask_centre(result.slices, kept if bool(kept.any()) else None)
    choice = best_atlas_transform(volume, result.mask.data > 0.5, atlas, config, centre=centre)
    found = choice.fit
    transform = found.transform
    angle = math.degrees(rotation_angle(transform, torch.eye(4, dtype=transform.dtype)))
    log.info(
        "atlas frame: turned %.1f deg, shifted %.1f mm (start %s; final NCC %s; coarse %s)",
        angle,
        float(transform[:3, 3].norm()),
        found.start,
        ", ".join(f"{k} {v:.3f}" for k, v in found.final.items()),
        ", ".join(f"{k} {v:.3f}" for k, v in found.scores.items()),
    )
    others = [ncc for name, ncc in found.final.items() if name != found.start]
    margin = found.final[found.start] - max(others) if others else None
    applied = max_turn_deg is None or angle <= max_turn_deg
    if not applied:
        log.warning(
            "atlas frame: the fit turned the volume's frame by %.1f deg, more than %g deg from a "
            "frame the stacks' learned poses support: only its centring is kept",
            angle,
            max_turn_deg,
        )
        transform = torch.eye(4, dtype=transform.dtype)
        transform[:3, 3] = -centre.to(transform)
    return dataclasses.replace(
        relabelled(result, transform),
        atlas_ncc=choice.ncc,
        atlas_chosen=choice.chosen,
        atlas_margin=margin,
        atlas_turn_deg=angle,
        atlas_turn_applied=applied,
    )


def atlas_turn_line(result: ReconstructionResult) -> str:
    """The log's and QA page's line on the atlas fit's turn, or ``""`` without an atlas.

    Args:
        result: A reconstruction (its ``atlas_turn_deg`` and ``atlas_turn_applied``).

    Returns:
        For example ``"atlas fit: turned 4.7 deg"`` or ``"atlas fit: would turn 32.8 deg (not
        applied)"``.
    """
    if result.atlas_turn_deg is None:
        return ""
    if result.atlas_turn_applied is False:
        return f"atlas fit: would turn {result.atlas_turn_deg:.1f} deg (not applied)"
    return f"atlas fit: turned {result.atlas_turn_deg:.1f} deg"
