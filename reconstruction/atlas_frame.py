"""The reconstructed volume brought into an atlas's frame: rigid registration with flips tested.

A learned or per-stack canonical frame is only as good as its estimate (a few degrees, a few
millimetres, or a half turn if a brain looked the same either way). :func:`align_to_atlas`
registers the finished volume rigidly to an atlas of about the same age, from the frame it is in
and from that frame turned by 180 degrees about each axis, and keeps the best fit (NCC over the
volume's brain mask) for the orientation. The origin is then put at the centroid of the volume's
own brain mask, which is what canonical space means (``docs/conventions.md``): an atlas of a
neighbouring age or another cohort differs in shape, and its fit pulled the centre by about 5 mm on
sb28-moderate, where the mask's centroid does not depend on it. Everything is relabelled in that
frame: the volume's and mask's affines and every slice pose. Nothing is resampled, so the volume's
values are unchanged.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import torch
from torch import Tensor

from svr.geometry import rotation_angle, se3_compose, so3_exp
from svr.image import Image, voxel_to_world
from svr.models.stack_pose import AtlasFitConfig, StackPoseNet, fit_to_atlas, refine_frames
from svr.reconstruction.config import ReconstructionResult
from svr.sampling.blocks import coarsen_stack
from svr.sampling.volume import CanonicalVolume

__all__ = ["FLIPS", "align_to_atlas", "atlas_transform"]

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


def atlas_transform(
    volume: Image,
    mask: Tensor,
    atlas: CanonicalVolume,
    config: AtlasFitConfig | None = None,
    model: StackPoseNet | None = None,
    max_fit_turn_deg: float = 15.0,
) -> tuple[Tensor, str, dict[str, float]]:
    """The rigid transform from a volume's frame to an atlas's canonical frame.

    Without a model, each start (:data:`FLIPS`) is fitted to the atlas and the best NCC wins.
    With a stack-pose model, the model scores the starts (the volume seen in each; the flips of
    a young brain's smooth atlas can fit almost equally well, 0.429 and 0.429 on a GA 23 case),
    and the atlas fit from the winner is kept if it turns it by at most ``max_fit_turn_deg``.

    Args:
        volume: The volume (its world frame about the canonical one).
        mask: Its brain mask on its grid.
        atlas: The atlas brain in canonical space.
        config: The fit's settings.
        model: A stack-pose network to choose among the flips, or ``None``.
        max_fit_turn_deg: With a model, the largest turn the atlas fit may make.

    Returns:
        ``(G, flip, scores)``: the (4, 4) float64 transform (volume world -> atlas canonical:
        the fitted rotation, and the translation that puts the mask's centroid at the origin),
        the start hypothesis that won (:data:`FLIPS`) and each start's score (the NCC it reached,
        or the model's logit).
    """
    best, best_flip, nccs = None, "none", {}
    if model is None:
        for axis in FLIPS:
            transform, ncc = fit_to_atlas(volume, mask, _flip(axis), atlas, config)
            nccs[axis] = ncc
            if best is None or ncc > nccs[best_flip]:
                best, best_flip = transform, axis
    else:
        image, fractions = coarsen_stack(volume, mask, model.config.in_plane_mm)
        starts = torch.stack([_flip(axis) for axis in FLIPS])
        _, scores = refine_frames(model, image, fractions, starts, iterations=0)
        nccs = {axis: float(score) for axis, score in zip(FLIPS, scores, strict=True)}
        best_flip = FLIPS[int(torch.argmax(scores))]
        start = _flip(best_flip)
        fitted, _ = fit_to_atlas(volume, mask, start, atlas, config)
        turn = math.degrees(rotation_angle(fitted, start))
        best = fitted if turn <= max_fit_turn_deg else start
        if turn > max_fit_turn_deg:
            log.info("atlas frame: the atlas fit turned %.0f deg; kept the stacks' frame", turn)
    assert best is not None
    idx = torch.nonzero(mask).to(torch.float64)
    centroid = voxel_to_world(volume.affine.to(torch.float64), idx).mean(0)
    best = best.clone()
    best[:3, 3] = -best[:3, :3] @ centroid
    return best, best_flip, nccs


def align_to_atlas(
    result: ReconstructionResult,
    atlas: CanonicalVolume,
    config: AtlasFitConfig | None = None,
    model: StackPoseNet | None = None,
) -> ReconstructionResult:
    """A reconstruction relabelled in the atlas's canonical frame (see the module docstring).

    Args:
        result: A finished reconstruction (its frame roughly canonical).
        atlas: The atlas brain in canonical space.
        config: The fit's settings.
        model: A stack-pose network to choose among the flips (:func:`atlas_transform`).

    Returns:
        The same result with the volume's, mask's and initial volume's affines and every slice
        pose premultiplied by the fitted transform.
    """
    volume = result.volume
    transform, flip, nccs = atlas_transform(volume, result.mask.data > 0.5, atlas, config, model)
    angle = math.degrees(rotation_angle(transform, torch.eye(4, dtype=transform.dtype)))
    log.info(
        "atlas frame: turned %.1f deg, shifted %.1f mm (start %s; scores %s)",
        angle,
        float(transform[:3, 3].norm()),
        flip,
        ", ".join(f"{k} {v:.3f}" for k, v in nccs.items()),
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
