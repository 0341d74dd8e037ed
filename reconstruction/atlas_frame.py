"""The reconstructed volume brought into an atlas's frame: rigid registration from many starts.

A learned or per-stack canonical frame is only as good as its estimate (a few degrees, a few
millimetres, a half turn if a brain looked the same either way, or tens of degrees on a real scan
whose stacks the model was unsure of). :func:`align_to_atlas` registers the finished volume rigidly
to an atlas of about the same age from several starts: the frame it is in, that frame turned by 180
degrees about each axis, and the 8 frames of the volume's own brain-mask principal axes
(:func:`svr.models.stack_pose.mask_axis_hypotheses`; a whole reconstructed brain's axes are far
more reliable than a stack's), so that the result does not depend on how good the start was. Each
start is fitted coarsely, the best NCC wins and is fitted finely. (The stack-pose model does not
choose: on the real clinical scan it was confident of the frame turned by 180 degrees about z,
which the atlas's NCC ranked 0.004 below the right one.) The origin is then put
at the centroid of the volume's own brain mask, which is what canonical space means
(``docs/conventions.md``): an atlas of a neighbouring age or another cohort differs in shape, and
its fit pulled the centre by about 5 mm on sb28-moderate, where the mask's centroid does not depend
on it. Everything is relabelled in that frame: the volume's and mask's affines and every slice
pose. Nothing is resampled, so the volume's values are unchanged.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import torch
from torch import Tensor

from svr.geometry import rotation_angle, se3_compose, so3_exp
from svr.image import Image, voxel_to_world
from svr.models.stack_pose import (
    AtlasFitConfig,
    atlas_levels,
    fit_to_atlas,
    mask_axis_hypotheses,
)
from svr.reconstruction.config import ReconstructionResult
from svr.sampling.volume import CanonicalVolume

__all__ = ["COARSE_FIT", "FLIPS", "align_to_atlas", "atlas_transform"]

log = logging.getLogger(__name__)

FLIPS = ("none", "x", "y", "z")
"""The start hypotheses: the frame as it is, and turned by 180 degrees about x, y or z."""


def _flip(axis: str) -> Tensor:
    out = torch.eye(4, dtype=torch.float64)
    if axis != "none":
        vector = torch.zeros(3, dtype=torch.float64)
        vector["xyz".index(axis)] = math.pi
        out[:3, :3] = so3_exp(vector)
    return out


COARSE_FIT = AtlasFitConfig(blur_mm=(4.0, 2.0), iterations=15, max_points=4000)
"""The fit of every start: fewer iterations and a subsample of the mask, enough to rank them (a
single 4 mm level is not: on a smooth brain, wrong frames reach a higher NCC there)."""


def atlas_transform(
    volume: Image,
    mask: Tensor,
    atlas: CanonicalVolume,
    config: AtlasFitConfig | None = None,
) -> tuple[Tensor, str, dict[str, float]]:
    """The rigid transform from a volume's frame to an atlas's canonical frame.

    Every start (the volume's frame and its :data:`FLIPS`, then the 8 principal-axis frames of its
    brain mask, named ``"axes0"``..``"axes7"``) is fitted to the atlas with :data:`COARSE_FIT`.
    The best NCC wins and is fitted again with ``config``.

    Args:
        volume: The volume (its world frame anywhere; best about the canonical one).
        mask: Its (I, J, K) bool brain mask on its grid, at least 4 voxels.
        atlas: The atlas brain in canonical space.
        config: The final fit's settings (default :class:`AtlasFitConfig`).

    Returns:
        ``(G, start, scores)``: the (4, 4) float64 transform (volume world -> atlas canonical:
        the fitted rotation, and the translation that puts the mask's centroid at the origin),
        the start that won, and each start's NCC after the coarse fit.

    Raises:
        ValueError: If the mask has fewer than 4 voxels.
    """
    idx = torch.nonzero(mask).to(torch.float64)
    if len(idx) < 4:
        raise ValueError("atlas_transform(): 'mask' has fewer than 4 voxels")
    points = voxel_to_world(volume.affine.to(torch.float64), idx)
    names = list(FLIPS) + [f"axes{i}" for i in range(8)]
    starts = torch.cat([torch.stack([_flip(axis) for axis in FLIPS]), mask_axis_hypotheses(points)])
    levels = atlas_levels(atlas, COARSE_FIT)
    fitted, nccs = [], []
    for start in starts:
        frame, ncc = fit_to_atlas(volume, mask, start, atlas, COARSE_FIT, levels)
        fitted.append(frame)
        nccs.append(ncc)
    frames = torch.stack(fitted)
    scores = torch.tensor(nccs, dtype=torch.float64)
    won = int(torch.argmax(scores))
    final = config or AtlasFitConfig()
    reuse = levels if final.blur_mm == COARSE_FIT.blur_mm else None
    best, _ = fit_to_atlas(volume, mask, frames[won], atlas, final, reuse)
    centroid = points.mean(0)
    best = best.clone()
    best[:3, 3] = -best[:3, :3] @ centroid
    return best, names[won], {name: float(v) for name, v in zip(names, scores, strict=True)}


def align_to_atlas(
    result: ReconstructionResult,
    atlas: CanonicalVolume,
    config: AtlasFitConfig | None = None,
) -> ReconstructionResult:
    """A reconstruction relabelled in the atlas's canonical frame (see the module docstring).

    Args:
        result: A finished reconstruction (its frame best roughly canonical; any will do).
        atlas: The atlas brain in canonical space.
        config: The final fit's settings.

    Returns:
        The same result with the volume's, mask's and initial volume's affines and every slice
        pose premultiplied by the fitted transform.
    """
    volume = result.volume
    transform, start, scores = atlas_transform(volume, result.mask.data > 0.5, atlas, config)
    angle = math.degrees(rotation_angle(transform, torch.eye(4, dtype=transform.dtype)))
    log.info(
        "atlas frame: turned %.1f deg, shifted %.1f mm (start %s; scores %s)",
        angle,
        float(transform[:3, 3].norm()),
        start,
        ", ".join(f"{k} {v:.3f}" for k, v in scores.items()),
    )

    def moved(image: Image) -> Image:
        return Image(image.data, transform.to(image.affine) @ image.affine)

    slices = result.slices
    return dataclasses.replace(
        result,
        volume=moved(volume),
        mask=moved(result.mask),
        initial_volume=moved(result.initial_volume),
        slices=slices.with_poses(se3_compose(transform.to(slices.poses)[None], slices.poses)),
    )
