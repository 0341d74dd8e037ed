"""Rigid registration of a brain image to an atlas in canonical space (NCC over the brain mask).

Used to choose among candidate canonical frames of a stack or a reconstructed volume
(:func:`atlas_agreement`) and to refine one (:func:`fit_to_atlas`). A *frame* here is a (4, 4)
transform from the image's world mm to canonical mm (``docs/conventions.md``); the image moves
as one rigid body about the canonical origin.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from scipy.ndimage import gaussian_filter
from torch import Tensor

from svr.geometry import se3_compose, so3_exp
from svr.image import Image, sample_world, voxel_to_world
from svr.sampling.volume import CanonicalVolume
from svr.validation import check_int, check_number_tuple

__all__ = [
    "KEEP_MARGIN",
    "AtlasFitConfig",
    "atlas_agreement",
    "atlas_levels",
    "fit_to_atlas",
    "preferred_atlas",
]

KEEP_MARGIN = 0.05
"""How much higher another start's NCC (after the final fit) must be to replace the volume's own
frame: below the 0.09-0.22 by which the right frame beat the best wrong one on simulated cases,
above the noise between a frame and its twin where the brain matches the atlas poorly."""


@dataclass(frozen=True)
class AtlasFitConfig:
    """The rigid fit of an image to an atlas: levels of blur, iterations, voxels used.

    Attributes:
        blur_mm: Gaussian blur (standard deviation, mm) of the atlas at each level, coarse first.
        iterations: L-BFGS iterations per level, >= 1.
        max_points: Most mask voxels used (an even subsample of the rest), >= 100.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    blur_mm: tuple[float, ...] = (4.0, 2.0)
    iterations: int = 30
    max_points: int = 20000

    def __post_init__(self) -> None:
        owner = "AtlasFitConfig"
        blur = check_number_tuple(
            owner, "blur_mm", self.blur_mm, ge=0, allow_empty=False, allow_list=True
        )
        check_int(owner, "iterations", self.iterations, minimum=1)
        check_int(owner, "max_points", self.max_points, minimum=100)
        object.__setattr__(self, "blur_mm", blur)


def _mask_samples(stack: Image, mask: Tensor, max_points: int) -> tuple[Tensor, Tensor]:
    """World points (N, 3) float64 of a stack's mask voxels and their standardised intensities."""
    inside = mask > 0.5
    idx = torch.nonzero(inside).to(torch.float64)
    values = stack.data[inside].double()
    if len(idx) > max_points:
        keep = torch.linspace(0, len(idx) - 1, max_points).round().long()
        idx, values = idx[keep], values[keep]
    values = (values - values.mean()) / values.std().clamp_min(1e-9)
    return voxel_to_world(stack.affine, idx), values


def atlas_levels(atlas: CanonicalVolume, config: AtlasFitConfig | None = None) -> list[Image]:
    """The blurred copies of an atlas that :func:`fit_to_atlas` registers to, coarse first.

    Computing them once and passing them to several fits saves the blurring (about 1 s for a
    0.8 mm atlas) in each.

    Args:
        atlas: The atlas brain in canonical space.
        config: The fit's settings (their ``blur_mm``; default :class:`AtlasFitConfig`).

    Returns:
        One image per level of ``config.blur_mm``.
    """
    config = config or AtlasFitConfig()
    return [_blurred(atlas, sigma) for sigma in config.blur_mm]


def _blurred(atlas: CanonicalVolume, sigma_mm: float) -> Image:
    if sigma_mm <= 0:
        return atlas.image
    spacing = atlas.image.spacing.double().cpu().numpy()
    data = gaussian_filter(atlas.image.data.double().cpu().numpy(), sigma_mm / spacing)
    return Image(torch.from_numpy(data).float(), atlas.image.affine)


def _ncc(a: Tensor, b: Tensor) -> Tensor:
    a = a - a.mean(-1, keepdim=True)
    return (a * b).mean(-1) / a.std(-1).clamp_min(1e-9)


def atlas_agreement(
    stack: Image, mask: Tensor, frames: Tensor, atlas: CanonicalVolume, max_points: int = 20000
) -> Tensor:
    """How well each candidate frame puts the stack on the atlas: NCC over the mask's voxels.

    Args:
        stack: (I, J, K) stack in its scanner frame.
        mask: (I, J, K) brain mask on its grid.
        frames: (H, 4, 4) candidate frames (scanner mm -> canonical mm).
        atlas: A brain of about the same age in canonical space.
        max_points: Most mask voxels used.

    Returns:
        (H,) float64 normalised cross-correlations in [-1, 1].
    """
    points, values = _mask_samples(stack, mask, max_points)
    canonical = (
        points @ frames[:, :3, :3].transpose(1, 2).double() + frames[:, None, :3, 3].double()
    )
    sampled = sample_world(atlas.image, canonical.float()).double()
    return _ncc(sampled, values)


def fit_to_atlas(
    stack: Image,
    mask: Tensor,
    frame: Tensor,
    atlas: CanonicalVolume,
    config: AtlasFitConfig | None = None,
    levels: list[Image] | None = None,
) -> tuple[Tensor, float]:
    """Refine a stack's frame by rigid registration of its masked voxels to an atlas (NCC).

    The stack moves as one rigid body about the canonical origin; L-BFGS on the rotation vector
    and shift of the correction, coarse to fine over blurred copies of the atlas.

    Args:
        stack: (I, J, K) stack in its scanner frame.
        mask: (I, J, K) brain mask on its grid.
        frame: (4, 4) starting frame (scanner mm -> canonical mm).
        atlas: A brain of about the same age in canonical space.
        config: Levels and iterations.
        levels: The atlas's blurred copies for ``config`` (:func:`atlas_levels`), or ``None`` to
            make them here.

    Returns:
        The refined (4, 4) float64 frame and its NCC with the atlas at the finest level.

    Raises:
        ValueError: If ``levels`` does not have one image per level of ``config.blur_mm``.
    """
    config = config or AtlasFitConfig()
    if levels is None:
        levels = atlas_levels(atlas, config)
    if len(levels) != len(config.blur_mm):
        raise ValueError(
            f"fit_to_atlas(): 'levels' must have {len(config.blur_mm)} images (one per blur "
            f"level), got {len(levels)}"
        )
    points, values = _mask_samples(stack, mask, config.max_points)
    start = points @ frame[:3, :3].T.double() + frame[:3, 3].double()
    params = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    ncc = 0.0
    for level in levels:
        optimiser = torch.optim.LBFGS(
            [params], lr=1.0, max_iter=config.iterations, line_search_fn="strong_wolfe"
        )

        def closure(level: Image = level, optimiser: torch.optim.LBFGS = optimiser) -> Tensor:
            optimiser.zero_grad()
            moved = start @ so3_exp(params[:3]).T + params[3:] * 10.0
            loss = -_ncc(sample_world(level, moved), values)
            loss.backward()
            return loss

        optimiser.step(closure)
        with torch.no_grad():
            moved = start @ so3_exp(params[:3]).T + params[3:] * 10.0
            ncc = float(_ncc(sample_world(level, moved), values))
    correction = torch.eye(4, dtype=torch.float64)
    with torch.no_grad():
        correction[:3, :3] = so3_exp(params[:3])
        correction[:3, 3] = params[3:] * 10.0
    return se3_compose(correction, frame.double()), ncc


def preferred_atlas(ncc: Sequence[float], keep_margin: float = KEEP_MARGIN) -> int:
    """Which of several atlases to follow: the first unless another fits clearly better.

    Args:
        ncc: Each atlas's NCC after its fit, the preferred atlas first (at least one).
        keep_margin: NCC by which the best must beat the first to be chosen instead, >= 0.

    Returns:
        The index of the atlas to follow.

    Raises:
        ValueError: If ``ncc`` is empty or ``keep_margin`` < 0.
    """
    if not ncc:
        raise ValueError("preferred_atlas(): 'ncc' must hold at least one value")
    if not keep_margin >= 0:
        raise ValueError(f"preferred_atlas(): 'keep_margin' must be >= 0, got {keep_margin}")
    best = max(range(len(ncc)), key=lambda i: ncc[i])
    return best if ncc[best] > ncc[0] + keep_margin else 0
