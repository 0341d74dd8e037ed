"""Every slice placed by the slice refiner against the atlas, kept where the other stacks agree.

After the learned start (:mod:`~svr.reconstruction.initialisation.learned`) every slice sits
where its stack's or packet's transform put it, not where the fetus was when it was acquired.
Here each slice is moved by the slice refiner (:class:`svr.models.slice_refiner.SliceRefinerNet`):
it sees the slice beside a reference volume resampled on the slice's current plane and on
parallel planes and predicts the residual rigid pose, applied and iterated, one stage after
another (the shipped ``wide`` stage, trained on residual rotations up to 30 degrees, then
``fine``, up to 10: :func:`svr.models.slice_refiner.shipped_slice_refiners`).

The reference is the atlas of the fetus's age in canonical space (brain-masked, at the
refiner's training scale): a sharp brain, unlike a volume of the subject's own roughly placed
slices. The atlas is not the fetus, so a slice keeps its refined pose only where it agrees better
with the *other* stacks' slices than it did at its start (NCC with a scattered-data volume of
them): the subject's own data decides, never the atlas (:func:`place_slices`). Which poses of the
other stacks it is judged against depends on how well the start already agrees:

- where the start's slices agree with the other stacks (median leave-one-stack-out NCC above
  :data:`TRUSTED_START_NCC`), the other stacks *at their start*: the refined slices all carry the
  same pull towards the atlas's anatomy, so against each other they agree better even where each
  moved away from the fetus's, and only a move that fits the other stacks as they are is kept;
- otherwise (motion within the stacks has scattered the start), the other stacks *at their
  refined poses*: their start is itself too wrong to judge a move by.

The refiner's estimates scatter by several degrees about the truth, and a packet's slices were
acquired one after another. With ``packets`` (``--slice-trajectory``), where the head was calm,
the kept poses are put on their packets' motion trajectories: when the stiffest trajectory of
:data:`~svr.reconstruction.trajectory.SMOOTHNESS_GRID` predicts a left-out slice best
(:func:`svr.reconstruction.trajectory.cross_validated_trajectory`), the estimates' scatter is
what varies from slice to slice, and averaging it away helps. Where a more flexible trajectory
predicts better, the head moved between slices, smoothing would pull the slices away from
where they were, and the poses stay as estimated.

Frames: every pose is a slice array's pose (slice-plane mm about the array centre -> canonical
mm), as :class:`~svr.reconstruction.slices.SliceSet` holds it; the atlas is in canonical mm.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor
from torch.nn import functional

from svr.geometry import se3_compose, vector_to_se3
from svr.image import Image
from svr.models.slice_refiner import SliceRefinerNet
from svr.reconstruction.registration import SliceAgreement, slice_agreement
from svr.reconstruction.slices import SliceSet
from svr.reconstruction.trajectory import SMOOTHNESS_GRID, cross_validated_trajectory
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import CanonicalVolume, downsample_volume

__all__ = [
    "KEEP_MARGIN",
    "TRUSTED_START_NCC",
    "SlicePlacement",
    "atlas_reference",
    "place_slices",
    "refine_poses",
    "refiner_inputs",
    "slices_on_grid",
]

log = logging.getLogger(__name__)

KEEP_MARGIN = 0.01
"""NCC by which a slice's agreement with the other stacks must rise for its refined pose to be
kept."""

TRUSTED_START_NCC = 0.35
"""Median leave-one-stack-out slice NCC of the start above which the keep rule judges a refined
slice against the other stacks at their start rather than at their refined poses (module
docstring)."""

REFERENCE_VOXEL_MM = 1.6
"""Voxel size (mm) of the references the shipped refiner was trained on (atlases at 0.8 mm,
downsampled twice)."""

BATCH = 64
"""Slices per forward pass of the refiner."""


def _normalised(values: Tensor, inside: Tensor) -> Tensor:
    """``values`` divided by the 99th percentile of their ``inside`` part (unchanged if none)."""
    part = values[inside]
    scale = float(part.quantile(0.99)) if part.numel() else 1.0
    return values / (scale if scale > 0 else 1.0)


def atlas_reference(atlas: CanonicalVolume) -> Image:
    """The atlas as the refiner's reference: brain-masked, at about its training voxel size.

    Args:
        atlas: A brain of about the fetus's age in canonical space (downsampled by the integer
            factor that brings its voxels nearest to :data:`REFERENCE_VOXEL_MM`).

    Returns:
        The reference in canonical mm, intensities scaled to 1 at the brain's 99th percentile.
    """
    spacing = float(atlas.image.spacing.min())
    factor = max(1, round(REFERENCE_VOXEL_MM / spacing))
    small = downsample_volume(atlas, factor) if factor > 1 else atlas
    data = small.image.data.float() * small.mask.float()
    return Image(_normalised(data, small.mask > 0), small.image.affine)


def slices_on_grid(slices: SliceSet, refiner: SliceRefinerNet) -> Tensor:
    """(N, H, W) each brain-masked slice on the refiner's pixel grid about its array centre.

    The slice is box-averaged to about the grid's spacing and sampled bilinearly (zero outside);
    its intensities are scaled to 1 at its brain's 99th percentile.

    Args:
        slices: The slices.
        refiner: A stage of the refiner (its input size and pixel spacing).

    Returns:
        The slices, float32, on ``slices.device``.
    """
    config = refiner.config
    h, w = config.size
    out = torch.zeros(len(slices), h, w, dtype=torch.float32, device=slices.device)
    images = (slices.images * slices.masks).float()[:, None]
    rows, cols = images.shape[-2:]
    u = (torch.arange(h, dtype=torch.float64) - (h - 1) / 2) * config.spacing_mm
    v = (torch.arange(w, dtype=torch.float64) - (w - 1) / 2) * config.spacing_mm
    for i in range(len(slices)):
        su, sv = (float(x) for x in slices.spacing_mm[i])
        factor = max(1, round(config.spacing_mm / min(su, sv)))
        image = functional.avg_pool2d(images[i : i + 1], factor, stride=1, padding=factor // 2)
        image = image[..., :rows, :cols]
        gu = (u / su) / ((rows - 1) / 2)
        gv = (v / sv) / ((cols - 1) / 2)
        grid = torch.stack(torch.meshgrid(gu, gv, indexing="ij")[::-1], dim=-1)
        sampled = functional.grid_sample(image, grid[None].to(image), align_corners=True)[0, 0]
        out[i] = _normalised(sampled, sampled > 0)
    return out


def refiner_inputs(
    refiner: SliceRefinerNet, images: Tensor, reference: Image, poses: Tensor
) -> Tensor:
    """(N, C, H, W) the slices beside the reference on their planes and the parallel ones.

    Args:
        refiner: A stage of the refiner (input size, spacing and plane offsets along the normal).
        images: (N, H, W) the slices on the refiner's grid (:func:`slices_on_grid`).
        reference: The reference volume in the poses' frame (:func:`atlas_reference`).
        poses: (N, 4, 4) the slices' current poses (slice plane about the array centre -> mm).

    Returns:
        Channel 0 the slice, then the reference at each offset of ``plane_offsets_mm``; float32.
    """
    config = refiner.config
    offsets = torch.tensor(config.plane_offsets_mm, dtype=torch.float64)
    shifts = torch.eye(4, dtype=torch.float64).repeat(len(offsets), 1, 1)
    shifts[:, 2, 3] = offsets
    planes = se3_compose(poses.double()[:, None], shifts[None].to(poses.device)).reshape(-1, 4, 4)
    thin = SliceConfig(size=config.size, spacing_mm=config.spacing_mm)
    sampled = sample_slices(reference, planes.to(reference.data.device), thin)
    sampled = sampled.reshape(len(poses), len(offsets), *config.size).to(images)
    return torch.cat([images[:, None], sampled], dim=1).float()


@torch.no_grad()
def refine_poses(
    stages: Sequence[tuple[SliceRefinerNet, int]], slices: SliceSet, reference: Image
) -> Tensor:
    """Each slice's pose moved by the refiner's stages, each applied its number of steps.

    Every step moves every slice by its predicted residual, ``T <- T o D`` (``D`` in the
    slice's frame), and resamples the reference at the new pose for the next.

    Args:
        stages: ``(refiner, steps)`` in the order applied; refiners of one input size and
            spacing, in eval mode (``context="none"``).
        slices: The slices at their current poses, in the reference's frame.
        reference: The reference (:func:`atlas_reference`).

    Returns:
        (N, 4, 4) float64 the refined poses, on ``slices.device``.
    """
    poses = slices.poses.to(torch.float64).clone()
    if not stages or not len(slices):
        return poses
    images = slices_on_grid(slices, stages[0][0])
    for refiner, steps in stages:
        device = next(refiner.parameters()).device
        for _ in range(steps):
            for start in range(0, len(poses), BATCH):
                part = slice(start, start + BATCH)
                inputs = refiner_inputs(refiner, images[part], reference, poses[part])
                residual = refiner.to_pose(refiner(inputs.to(device))).double()
                poses[part] = se3_compose(poses[part], vector_to_se3(residual).to(poses))
    return poses


class SlicePlacement(NamedTuple):
    """What :func:`place_slices` did.

    Attributes:
        poses: (N, 4, 4) float64 the slices' poses: refined where kept, else as they were.
        kept: (N,) bool, the slices whose refined pose was kept.
        ncc_before: (N,) each slice's NCC with the other stacks' volume, at the start.
        ncc_after: (N,) each slice's NCC at its refined pose (every slice refined) with the other
            stacks' volume at their start (``start_trusted``) or at their refined poses.
        smoothness: The smoothness that predicted a left-out slice best, or ``None`` without
            ``packets`` (or nothing refined).
        on_trajectory: Whether the poses were put on their packets' trajectories (the head was
            calm: ``smoothness`` is the grid's stiffest).
        start_trusted: Whether the start agreed well enough (:data:`TRUSTED_START_NCC`) for the
            refined slices to be judged against the other stacks at their start.
    """

    poses: Tensor
    kept: Tensor
    ncc_before: Tensor
    ncc_after: Tensor
    smoothness: float | None = None
    on_trajectory: bool = False
    start_trusted: bool = False


def place_slices(
    slices: SliceSet,
    atlas: CanonicalVolume,
    stages: Sequence[tuple[SliceRefinerNet, int]],
    resolution_mm: float,
    packets: int | None = None,
) -> SlicePlacement:
    """Every slice refined against the atlas, kept where the other stacks agree better.

    A refined pose is kept where the slice's NCC with the other stacks' volume rises by more than
    :data:`KEEP_MARGIN`: the other stacks at their start where the start agrees well
    (:data:`TRUSTED_START_NCC`), else at their refined poses (module docstring). With
    ``packets``, the poses (kept or not) are then put on their packets' motion trajectories where
    the head was calm.

    Args:
        slices: All slices at their starting canonical poses (two stacks or more for any to be
            kept: one stack has no other to agree with).
        atlas: A brain of about the fetus's age in canonical space.
        stages: ``(refiner, steps)`` in the order applied (:func:`refine_poses`).
        resolution_mm: Voxel size of the other stacks' volumes (mm).
        packets: Interleaved packets per stack for the trajectories, or ``None`` for none.

    Returns:
        The poses, which slices kept their refined pose, and each slice's NCC before and after.
    """
    n = len(slices)
    start = slices.poses.to(torch.float64)
    zeros = torch.zeros(n, dtype=torch.float64, device=slices.device)
    if not stages or len(slices.stack_names) < 2:
        return SlicePlacement(
            start.clone(), torch.zeros_like(zeros, dtype=torch.bool), zeros, zeros
        )
    refined = refine_poses(stages, slices, atlas_reference(atlas))
    at_start = SliceAgreement(slices, resolution_mm, leave_out=True)
    before = at_start().to(zeros)
    trusted = float(before.median()) > TRUSTED_START_NCC
    if trusted:
        after = at_start(refined)
    else:
        moved = slices.with_poses(refined.to(slices.poses))
        after = slice_agreement(moved, resolution_mm, leave_out=True)
    after = after.to(zeros)
    kept = after > before + KEEP_MARGIN
    poses = torch.where(kept[:, None, None], refined.to(start), start)
    if packets is None:
        return SlicePlacement(poses, kept, before, after, start_trusted=trusted)
    fit, smoothness, _ = cross_validated_trajectory(slices.with_poses(poses), packets)
    calm = smoothness == max(SMOOTHNESS_GRID)
    if calm:
        poses = fit.poses.to(start)
    return SlicePlacement(poses, kept, before, after, smoothness, calm, trusted)
