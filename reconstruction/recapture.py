"""A wider search for the slices that fit badly: :func:`recapture`.

After the early rounds a slice can sit far from its pose, out of reach of a local registration
step (its packet turned with the head, or its start was a wrong twin). :func:`recapture` registers
each such slice alone from several starts (its temporal neighbours' motion, its packet's motion
trajectory, the coarse turns of the head that fit it best) against a reference the searched slices
did not shape (:func:`svr.reconstruction.rounds.volume_without`), and keeps a result only where it
fits clearly better. The schedule calls it (:mod:`svr.reconstruction.schedule`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from svr.geometry import so3_exp
from svr.reconstruction.acquisition import Acquisition, packet_neighbours
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.operators import SliceProjector
from svr.reconstruction.registration import (
    SVR_PSF_SAMPLES,
    RegistrationConfig,
    register_rigid,
    slice_ncc,
)

__all__ = ["COARSE_KEPT", "COARSE_TURNS_DEG", "RECAPTURE_MARGIN", "coarse_turns", "recapture"]

# recapture(): the NCC a wider search must gain over the current pose.
RECAPTURE_MARGIN = 0.01

# recapture(): the coarse search's turns of the head (degrees), each about 13 axes both ways, and
# how many of its best-fitting turns per slice go on to registration.
COARSE_TURNS_DEG = (30.0, 60.0)
COARSE_KEPT = 2


def _axes() -> Tensor:
    """(26, 3) unit axes: the 13 axes of a cube (faces, edges, corners), both ways."""
    ones = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1)]
    ones += [(0, 1, 1), (0, 1, -1), (1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1)]
    axes = torch.tensor(ones, dtype=torch.float64)
    axes = axes / axes.norm(dim=1, keepdim=True)
    return torch.cat([axes, -axes])


def coarse_turns(poses: Tensor, centre: Tensor, turns_deg: tuple[float, ...]) -> Tensor:
    """(N, T, 4, 4) each pose with the head turned about ``centre`` by each coarse rotation.

    Args:
        poses: (N, 4, 4) slice poses (slice-plane mm -> frame mm).
        centre: (3,) the centre of the head's turns, frame mm (e.g. the brain's centre).
        turns_deg: Rotation angles (degrees), each about 26 directions (:func:`_axes`).

    Returns:
        (N, 26 x len(turns_deg), 4, 4) float64 ``G_t @ P_n`` with ``G_t`` the rotation about
        ``centre``.
    """
    angles = torch.deg2rad(torch.tensor(turns_deg, dtype=torch.float64))
    vectors = torch.cat([_axes() * angle for angle in angles])
    turn = torch.eye(4, dtype=torch.float64).repeat(len(vectors), 1, 1)
    rotation = so3_exp(vectors)
    c = centre.to(torch.float64).cpu()
    turn[:, :3, :3] = rotation
    turn[:, :3, 3] = c - rotation @ c
    return turn.to(poses.device)[None] @ poses.to(torch.float64)[:, None]


def recapture(
    acquisition: Acquisition,
    volume: Tensor,
    poses: Tensor,
    start_poses: Tensor,
    candidates: Tensor,
    config: ReconstructionConfig,
    trajectory: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """A wider search for slices that still fit badly: their packet neighbours' motion as starts.

    Each slice in ``candidates`` is registered alone from its current pose, from the poses its
    temporal neighbours' motion gives it (the corrections that moved the previous and next slice
    of its packet since ``start_poses``, applied to it), with ``trajectory`` from the pose
    its packet's motion trajectory gives it at its time (fitted to the other slices:
    :func:`svr.reconstruction.trajectory.fit_slice_trajectory`), and from the coarse turns of the
    head about that pose that fit it best (:func:`coarse_turns`: 30 and 60 degrees about 13 axes
    both ways, scored by NCC before any registration). It takes the result that matches
    its simulation from ``volume`` best (NCC over its brain pixels), if that beats its current
    pose by ``RECAPTURE_MARGIN``.

    Args:
        acquisition: The acquisition model.
        volume: (I, J, K) the reference to match on ``acquisition.grid``: best one the searched
            slices did not shape (:func:`volume_without`).
        poses: (N, 4, 4) current poses.
        start_poses: (N, 4, 4) the poses the rounds started from (for the neighbours' motion).
        candidates: (N,) bool, the slices to search for.
        config: Settings (``packets`` and the schedule's registration levels and steps).
        trajectory: (N, 4, 4) each slice's pose on its packet's trajectory, or ``None``.

    Returns:
        (N, 4, 4) float64 poses (changed only where a search found a better fit) and (N,) bool,
        the slices whose pose changed.
    """
    slices = acquisition.slices
    device = poses.device
    poses = poses.to(torch.float64).clone()
    changed = torch.zeros(len(slices), dtype=torch.bool, device=device)
    index = torch.nonzero(candidates.to(device)).flatten()
    if index.numel() == 0:
        return poses, changed
    starts, owners = [], []
    neighbour = packet_neighbours(slices, config.packets)
    motion = poses @ torch.linalg.inv(start_poses.to(poses))
    coarse = _coarse_starts(acquisition, volume, poses, index, trajectory)
    for n, i in enumerate(index.tolist()):
        own = [poses[i]]
        for j in neighbour[i]:
            own.append(motion[j] @ start_poses[i].to(poses))
        if trajectory is not None:
            own.append(trajectory[i].to(poses))
        own += list(coarse[n])
        starts += own
        owners += [i] * len(own)
    owner = torch.tensor(owners, device=device)
    subset = slices.subset(owner)
    projector = SliceProjector(acquisition.grid, subset, psf_samples=SVR_PSF_SAMPLES)
    settings = RegistrationConfig(
        levels=config.schedule.svr_levels, iterations=config.schedule.svr_iterations
    )
    found = register_rigid(
        projector,
        volume,
        subset.images,
        torch.stack(starts),
        torch.arange(len(owner), device=device),
        settings,
    )
    observed = projector.gather(subset.images)
    ncc = slice_ncc(projector, projector.forward(volume, projector.grid_points(found)), observed)
    current = slice_ncc(
        projector, projector.forward(volume, projector.grid_points(torch.stack(starts))), observed
    )
    for i in index.tolist():
        mine = torch.nonzero(owner == i).flatten()
        best = mine[int(ncc[mine].argmax())]
        # The current pose as it is (first start) is the bar to beat.
        if float(ncc[best]) > float(current[mine[0]]) + RECAPTURE_MARGIN:
            poses[i] = found[best]
            changed[i] = True
    return poses, changed


def _coarse_starts(
    acquisition: Acquisition,
    volume: Tensor,
    poses: Tensor,
    index: Tensor,
    trajectory: Tensor | None,
) -> Tensor:
    """(len(index), COARSE_KEPT, 4, 4) the best-fitting coarse turns of the head per slice.

    Each slice in ``index`` is simulated from ``volume`` with the head turned about the brain's
    centre (the mean of all slices' centres) by every :func:`coarse_turns` rotation of its
    trajectory pose (its current pose without one); the ``COARSE_KEPT`` turns whose simulation
    matches the slice best (NCC over its brain pixels) are returned, to be registered.
    """
    slices = acquisition.slices
    around = (trajectory if trajectory is not None else poses)[index].to(poses)
    centre = poses[:, :3, 3].mean(dim=0)
    turned = coarse_turns(around, centre, COARSE_TURNS_DEG)
    count = turned.shape[1]
    owner = index.repeat_interleave(count)
    subset = slices.subset(owner)
    projector = SliceProjector(acquisition.grid, subset, psf_samples=SVR_PSF_SAMPLES)
    flat = turned.reshape(-1, 4, 4)
    observed = projector.gather(subset.images)
    ncc = slice_ncc(projector, projector.forward(volume, projector.grid_points(flat)), observed)
    best = ncc.reshape(len(index), count).topk(min(COARSE_KEPT, count), dim=1).indices
    return torch.gather(turned, 1, best[..., None, None].expand(-1, -1, 4, 4))
