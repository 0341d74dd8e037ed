"""A stack's slices registered one by one to an atlas, from the stack's learned transform.

The stack-pose network
(:func:`~svr.reconstruction.initialisation.stack_pose.estimate_stack_pose`) places a stack as one
rigid body. Where the atlas matches the brain, each slice can then be registered on its own to
the atlas (rigid slice-to-volume registration,
:func:`svr.reconstruction.registration.register_rigid`, started from the stack's transform), so
the slices follow the fetus's motion within the stack, and the stack's pose becomes the robust
mean of the poses its registered slices imply (:func:`svr.sampling.blocks.stack_pose_from_slices`:
how a stack's true pose is defined).

An atlas of another brain can pull slices wrong, so the fit is kept only where the registered
slices match the atlas well: their mean NCC with their simulation from the atlas at least
:data:`ATLAS_SLICES_MIN_NCC`; otherwise the stack keeps its start transform and its slices follow
it.

Transforms follow :mod:`svr.sampling.blocks`: ``to_canonical`` ``E`` maps scanner mm to canonical
mm, a *stack pose* ``P = E o F`` maps the stack frame ``F`` to canonical mm, and a k-plane's
canonical pose maps its plane coordinates (origin at the plane's centre voxel,
:func:`svr.image.stack_slice_poses`) to canonical mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from svr.geometry import se3_compose, se3_inverse
from svr.image import Image, intensity_scale, stack_slice_poses
from svr.reconstruction.operators import SliceProjector, VolumeGrid
from svr.reconstruction.registration import RegistrationConfig, register_rigid, slice_ncc
from svr.reconstruction.slices import Stack, extract_slices
from svr.sampling.blocks import stack_frame, stack_pose_from_slices
from svr.sampling.volume import CanonicalVolume
from svr.validation import check_int, check_number

__all__ = ["ATLAS_SLICES_MIN_NCC", "AtlasSliceConfig", "AtlasSliceFit", "fit_slices_to_atlas"]

ATLAS_SLICES_MIN_NCC = 0.6
"""The registered slices' mean NCC with the atlas below which the fit is not kept (the gate
that put the most simulated held-out stacks within 10 degrees; stacks whose brain matches the
atlas well fit at 0.6-0.9, a neighbouring age of another brain or a real scan at 0.04-0.55)."""


@dataclass(frozen=True)
class AtlasSliceConfig:
    """Settings of :func:`fit_slices_to_atlas`.

    Attributes:
        min_ncc: The registered slices' mean NCC with the atlas at or above which the fit is
            kept (in [-1, 1]).
        levels: Registration levels, coarse to fine (>= 1).
        iterations: Levenberg-Marquardt steps per level (>= 1).
        psf_samples: PSF nodes along the slice normal (odd, >= 1).

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    min_ncc: float = ATLAS_SLICES_MIN_NCC
    levels: int = 3
    iterations: int = 6
    psf_samples: int = 3

    def __post_init__(self) -> None:
        owner = "AtlasSliceConfig"
        check_number(owner, "min_ncc", self.min_ncc, ge=-1.0, le=1.0)
        check_int(owner, "levels", self.levels, minimum=1)
        check_int(owner, "iterations", self.iterations, minimum=1)
        check_int(owner, "psf_samples", self.psf_samples, minimum=1)


class AtlasSliceFit(NamedTuple):
    """A stack's slices fitted to an atlas.

    Attributes:
        to_canonical: (4, 4) float64 scanner -> canonical transform of the stack: the robust mean
            of its registered slices where kept, else the start transform.
        pose: (4, 4) float64 stack pose (stack frame mm -> canonical mm), ``to_canonical o F``.
        plane_poses: (K, 4, 4) float64 canonical pose of every k-plane of the stack: registered
            for the planes with brain where the fit is kept, else ``to_canonical o`` its scanner
            pose.
        ncc: The registered slices' mean NCC with their simulation from the atlas.
        kept: Whether the fit was kept (``ncc >= min_ncc``).
    """

    to_canonical: Tensor
    pose: Tensor
    plane_poses: Tensor
    ncc: float
    kept: bool


def fit_slices_to_atlas(
    stack: Image,
    mask: Tensor,
    to_canonical: Tensor,
    atlas: CanonicalVolume,
    thickness_mm: float | None = None,
    config: AtlasSliceConfig | None = None,
) -> AtlasSliceFit:
    """Register each slice of a stack to an atlas from a frame; keep it where it matches.

    Args:
        stack: (I, J, K) stack in its scanner frame (k indexes slices).
        mask: (I, J, K) brain mask on the stack's grid (bool, or fractions > 0.5 inside).
        to_canonical: (4, 4) start scanner -> canonical transform (the model's estimate).
        atlas: A brain of about the stack's age in canonical space.
        thickness_mm: Slice thickness (mm); default the slice spacing.
        config: Gate and registration settings (default :class:`AtlasSliceConfig`).

    Returns:
        The fit.

    Raises:
        ValueError: If ``mask`` does not match the stack's shape or has no brain voxel,
            ``to_canonical`` is not (4, 4), or the stack is zero in the brain, naming the argument.
    """
    config = config or AtlasSliceConfig()
    if tuple(mask.shape) != tuple(stack.shape):
        raise ValueError(
            f"fit_slices_to_atlas(): 'mask' must have the stack's shape {tuple(stack.shape)}, "
            f"got {tuple(mask.shape)}"
        )
    if tuple(to_canonical.shape) != (4, 4):
        raise ValueError(
            f"fit_slices_to_atlas(): 'to_canonical' must be (4, 4), got {tuple(to_canonical.shape)}"
        )
    inside = (mask > 0.5) if mask.dtype != torch.bool else mask
    inside = inside.cpu()
    if not bool(inside.any()):
        raise ValueError("fit_slices_to_atlas(): 'mask' has no brain voxel")
    device = atlas.image.data.device
    to_canonical = to_canonical.to(torch.float64).cpu()
    affine = stack.affine.to(torch.float64).cpu()
    data = stack.data.cpu().float() * inside
    scale = intensity_scale(data[inside], "fit_slices_to_atlas(): 'stack'")
    k_count = stack.shape[2]
    # One uncropped stack: extract_slices pads nothing, so each slice's pose is its k-plane's
    # scanner pose (origin at the plane's centre voxel), as stack_slice_poses gives it.
    slices = extract_slices(
        [
            Stack(
                name="stack",
                image=Image(data / scale, affine),
                mask=Image(inside, affine),
                thickness_mm=float(thickness_mm or float(stack.spacing[2])),
                k_indices=torch.arange(k_count),
                full_shape=(stack.shape[0], stack.shape[1]),
            )
        ]
    ).to(device)
    ks = slices.slice_indices.cpu()
    planes = se3_compose(to_canonical[None], stack_slice_poses(stack).cpu())
    start = planes[ks].to(device)
    i_n, j_n, k_n = atlas.image.shape
    grid = VolumeGrid((i_n, j_n, k_n), atlas.image.affine.to(torch.float64))
    projector = SliceProjector(
        grid, slices.with_poses(start, "canonical"), psf_samples=config.psf_samples
    )
    volume = atlas.image.data.float()
    registered = register_rigid(
        projector,
        volume,
        slices.images,
        start,
        torch.arange(len(ks), device=device),
        RegistrationConfig(levels=config.levels, iterations=config.iterations),
    )
    simulated = projector.forward(volume, projector.grid_points(registered))
    ncc = float(slice_ncc(projector, simulated, projector.gather(slices.images)).mean())
    kept = ncc >= config.min_ncc
    if kept:
        planes[ks] = registered.to(torch.float64).cpu()
        present = torch.zeros(k_count, dtype=torch.bool)
        present[ks] = True
        pose = stack_pose_from_slices(planes, stack, present)
        to_canonical = se3_compose(pose, se3_inverse(stack_frame(stack)))
    else:
        pose = se3_compose(to_canonical, stack_frame(stack))
    return AtlasSliceFit(
        to_canonical=to_canonical, pose=pose, plane_poses=planes, ncc=ncc, kept=kept
    )
