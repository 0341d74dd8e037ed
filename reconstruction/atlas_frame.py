"""The reconstructed volume brought into an atlas's frame: rigid registration with flips tested.

A learned or per-stack canonical frame is only as good as its estimate (a few degrees, a few
millimetres, or a half turn if a brain looked the same either way). :func:`align_to_atlas`
registers the finished volume rigidly to an atlas of about the same age, from the frame it is in
and from that frame turned by 180 degrees about each axis, keeps the best fit (NCC over the
volume's brain mask) and relabels everything in the atlas frame: the volume's and mask's affines
and every slice pose. Nothing is resampled, so the volume's values are unchanged.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import torch
from torch import Tensor

from svr.geometry import se3_compose, so3_exp
from svr.image import Image
from svr.models.stack_pose import AtlasFitConfig, fit_to_atlas
from svr.reconstruction.config import ReconstructionResult
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
    volume: Image, mask: Tensor, atlas: CanonicalVolume, config: AtlasFitConfig | None = None
) -> tuple[Tensor, str, dict[str, float]]:
    """The rigid transform from a volume's frame to an atlas's canonical frame.

    Args:
        volume: The volume (its world frame about the canonical one).
        mask: Its brain mask on its grid.
        atlas: The atlas brain in canonical space.
        config: The fit's settings.

    Returns:
        ``(G, flip, nccs)``: the (4, 4) float64 transform (volume world -> atlas canonical), the
        start hypothesis that won (:data:`FLIPS`) and the NCC each reached.
    """
    best, best_flip, nccs = None, "none", {}
    for axis in FLIPS:
        transform, ncc = fit_to_atlas(volume, mask, _flip(axis), atlas, config)
        nccs[axis] = ncc
        if best is None or ncc > nccs[best_flip]:
            best, best_flip = transform, axis
    assert best is not None
    return best, best_flip, nccs


def align_to_atlas(
    result: ReconstructionResult, atlas: CanonicalVolume, config: AtlasFitConfig | None = None
) -> ReconstructionResult:
    """A reconstruction relabelled in the atlas's canonical frame (see the module docstring).

    Args:
        result: A finished reconstruction (its frame roughly canonical).
        atlas: The atlas brain in canonical space.
        config: The fit's settings.

    Returns:
        The same result with the volume's, mask's and initial volume's affines and every slice
        pose premultiplied by the fitted transform.
    """
    volume = result.volume
    transform, flip, nccs = atlas_transform(volume, result.mask.data > 0.5, atlas, config)
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(transform[:3, :3].trace()) - 1) / 2))))
    log.info(
        "atlas frame: turned %.1f deg, shifted %.1f mm (start %s; NCC %s)",
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
