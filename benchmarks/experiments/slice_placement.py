"""Every slice placed against the other stacks' volume, by a slice refiner, kept where it fits.

After the stacks and packets are placed (:mod:`svr.reconstruction.initialisation`), each slice is
still where its packet put it, not where the fetus was when it was acquired. For each stack, the
volume of the *other* stacks' slices (a scattered-data approximation at their current poses) is
the reference; the slice refiner (:class:`slice_refiner.SliceRefinerNet`) sees each
slice beside that reference on its current plane and parallel planes and predicts the residual,
applied and iterated (:func:`refine_slice_poses`). A slice keeps its refined pose only where it
matches its simulation from the reference better than before (NCC over its brain pixels); the
others keep theirs, so a wrong estimate is never kept (:func:`place_slices`).
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import torch
from slice_refiner import SliceRefinerNet
from torch import Tensor
from torch.nn import functional

from svr.geometry import se3_compose, vector_to_se3
from svr.image import Image
from svr.reconstruction.operators import SliceProjector
from svr.reconstruction.registration import slice_ncc
from svr.reconstruction.slices import SliceSet
from svr.reconstruction.superres import output_grid, scattered_data_approximation
from svr.sampling.slicer import SliceConfig, sample_slices

__all__ = ["SlicePlacement", "network_inputs", "place_slices", "refine_slice_poses"]

log = logging.getLogger(__name__)

PLACEMENT_MARGIN = 0.01
"""NCC by which a refined pose must beat the slice's current one to be kept."""


def _normalised(values: Tensor, inside: Tensor) -> Tensor:
    """``values`` divided by the 99th percentile of their brain part (1 where there is none)."""
    brain = values[inside]
    scale = float(brain.quantile(0.99)) if brain.numel() else 1.0
    return values / (scale if scale > 0 else 1.0)


def _resampled_slices(slices: SliceSet, net: SliceRefinerNet) -> Tensor:
    """(N, H, W) each slice on the network's grid about its centre (brain-masked, normalised)."""
    config = net.config
    h, w = config.size
    out = torch.zeros(len(slices), h, w, dtype=torch.float32, device=slices.device)
    images = (slices.images * slices.masks).float()[:, None]
    n, _, rows, cols = images.shape
    # pixel centres of the network's grid, in mm about the slice centre -> the slice's array
    u = (torch.arange(h, dtype=torch.float64) - (h - 1) / 2) * config.spacing_mm
    v = (torch.arange(w, dtype=torch.float64) - (w - 1) / 2) * config.spacing_mm
    for i in range(n):
        su, sv = (float(x) for x in slices.spacing_mm[i])
        factor = max(1, round(config.spacing_mm / min(su, sv)))
        image = functional.avg_pool2d(images[i : i + 1], factor, stride=1, padding=factor // 2)
        image = image[..., :rows, :cols]
        gu = (u / su) / ((rows - 1) / 2)
        gv = (v / sv) / ((cols - 1) / 2)
        grid = torch.stack(torch.meshgrid(gu, gv, indexing="ij")[::-1], dim=-1)
        sample = functional.grid_sample(image, grid[None].to(image), align_corners=True)
        out[i] = sample[0, 0]
    return out


def network_inputs(net: SliceRefinerNet, slices: Tensor, reference: Image, poses: Tensor) -> Tensor:
    """(N, C, H, W) the slices beside the reference on their planes and the parallel ones.

    Args:
        net: The slice refiner (its input size, spacing and plane offsets).
        slices: (N, H, W) the slices on the network's grid (:func:`_resampled_slices`).
        reference: The reference volume, in the poses' frame, normalised.
        poses: (N, 4, 4) the slices' current poses (slice plane about its centre -> frame mm).

    Returns:
        The inputs, float32.
    """
    config = net.config
    offsets = torch.tensor(config.plane_offsets_mm, dtype=torch.float64)
    shifts = torch.eye(4, dtype=torch.float64).repeat(len(offsets), 1, 1)
    shifts[:, 2, 3] = offsets
    planes = se3_compose(poses.double()[:, None], shifts[None].to(poses.device)).reshape(-1, 4, 4)
    thin = SliceConfig(size=config.size, spacing_mm=config.spacing_mm)
    sampled = sample_slices(reference, planes.to(reference.data.device), thin)
    sampled = sampled.reshape(len(poses), len(offsets), *config.size).to(slices)
    return torch.cat([slices[:, None], sampled], dim=1).float()


@torch.no_grad()
def refine_slice_poses(
    net: SliceRefinerNet,
    slices: SliceSet,
    reference: Image,
    iterations: int = 3,
    batch_size: int = 64,
) -> Tensor:
    """Each slice's pose refined against ``reference`` by the network, ``iterations`` times.

    Args:
        net: The slice refiner (``context="none"``), in eval mode.
        slices: The slices at their current poses, in ``reference``'s frame.
        reference: The reference volume (any intensity scale: it is normalised here).
        iterations: Refinement steps, >= 1.
        batch_size: Slices per forward pass.

    Returns:
        (N, 4, 4) float64 refined poses.
    """
    net.eval()
    device = next(net.parameters()).device
    data = reference.data.float()
    inside = data > 0
    reference = Image(_normalised(data, inside), reference.affine)
    images = _resampled_slices(slices, net)
    images = torch.stack([_normalised(im, im > 0) for im in images]) if len(images) else images
    poses = slices.poses.to(torch.float64).clone()
    for _ in range(iterations):
        for start in range(0, len(poses), batch_size):
            part = slice(start, start + batch_size)
            inputs = network_inputs(net, images[part], reference, poses[part])
            residual = vector_to_se3(net.to_pose(net(inputs.to(device))).double().cpu())
            poses[part] = se3_compose(poses[part], residual.to(poses))
    return poses


class SlicePlacement(NamedTuple):
    """What :func:`place_slices` did.

    Attributes:
        poses: (N, 4, 4) float64 the slices' poses: refined where kept, else as they were.
        kept: (N,) bool, the slices whose refined pose was kept.
        ncc_before: (N,) each slice's NCC with its simulation from its reference, before.
        ncc_after: (N,) the same at its refined pose.
    """

    poses: Tensor
    kept: Tensor
    ncc_before: Tensor
    ncc_after: Tensor


def _reference(slices: SliceSet, others: Tensor, resolution_mm: float) -> Image:
    """The scattered-data volume of the slices in ``others`` (bool, N), on their own grid."""
    subset = slices.subset(others)
    grid = output_grid(subset, resolution_mm)
    projector = SliceProjector(grid, subset)
    observed = projector.gather(subset.images)
    volume = scattered_data_approximation(
        projector, projector.grid_points(subset.poses), observed, torch.ones_like(observed)
    )
    return grid.image(volume)


def _ncc(slices: SliceSet, reference: Image, poses: Tensor) -> Tensor:
    """(N,) each slice's NCC with its simulation from ``reference`` at ``poses``."""
    from svr.reconstruction.operators import VolumeGrid

    grid = VolumeGrid(tuple(reference.shape), reference.affine.to(torch.float64))  # type: ignore[arg-type]
    projector = SliceProjector(grid, slices)
    observed = projector.gather(slices.images)
    simulated = projector.forward(reference.data.float(), projector.grid_points(poses))
    return slice_ncc(projector, simulated, observed)


def place_slices(
    net: SliceRefinerNet,
    slices: SliceSet,
    resolution_mm: float = 2.0,
    iterations: int = 3,
) -> SlicePlacement:
    """Every slice refined against the volume of the other stacks, kept where it fits better.

    Args:
        net: The slice refiner.
        slices: All slices at their starting poses (one frame).
        resolution_mm: Voxel size of the reference volumes (mm).
        iterations: Refinement steps per slice.

    Returns:
        The poses, which slices kept their refined pose, and each slice's NCC before and after.
    """
    poses = slices.poses.to(torch.float64).clone()
    kept = torch.zeros(len(slices), dtype=torch.bool, device=slices.device)
    before = torch.zeros(len(slices), dtype=torch.float64, device=slices.device)
    after = torch.zeros_like(before)
    ids = slices.stack_ids
    several = len(slices.stack_names) > 1
    for sid, name in enumerate(slices.stack_names):
        mine = ids == sid
        if not bool(mine.any()):
            continue
        reference = _reference(slices, ~mine if several else mine, resolution_mm)
        own = slices.subset(mine)
        refined = refine_slice_poses(net, own, reference, iterations)
        ncc_before = _ncc(own, reference, own.poses).double()
        ncc_after = _ncc(own, reference, refined.to(own.poses)).double()
        better = ncc_after > ncc_before + PLACEMENT_MARGIN
        index = torch.nonzero(mine).flatten()
        poses[index[better]] = refined[better.cpu()].to(poses)
        kept[index] = better
        before[index], after[index] = ncc_before, ncc_after
        log.info(
            "%s: %d of %d slices placed by the slice refiner (NCC with the other stacks %.3f -> "
            "%.3f for those)",
            name,
            int(better.sum()),
            int(mine.sum()),
            float(ncc_before[better].mean()) if bool(better.any()) else float("nan"),
            float(ncc_after[better].mean()) if bool(better.any()) else float("nan"),
        )
    return SlicePlacement(poses, kept, before, after)
