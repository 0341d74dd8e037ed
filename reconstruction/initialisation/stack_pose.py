"""A stack's canonical pose from its own data: mask-axis hypotheses, refined, one chosen.

The global part of a stack's orientation comes from structure, the local part is learned:

1. **Hypotheses** (:func:`mask_axis_hypotheses`): the principal axes of the stack's brain mask
   give the brain's axes (fetal brains are longest front to back, then left to right, then top to
   bottom), up to their signs and, where two lengths are close, their order: 8 candidates.
2. **Refinement** (:func:`refine_transforms`): the stack resampled in a candidate canonical frame
   goes through the stack-pose network (:class:`svr.models.stack_pose.StackPoseNet`), which
   predicts the residual rigid transform to the true canonical frame and scores the candidate;
   the residual is applied and the step iterated.
3. **Choice**: the hypothesis whose refined transform scores highest; without a network, the one
   that agrees best with an atlas (:func:`svr.reconstruction.atlas_fit.atlas_agreement`).

Transforms follow :mod:`svr.sampling.blocks`: ``to_canonical`` ``E`` maps the stack's scanner mm
to canonical mm, and the stack pose ``P = E o F`` maps the stack frame ``F`` to canonical mm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from svr.geometry import half_turns, rotation_angle, se3_compose, se3_inverse, so3_exp
from svr.geometry.averaging import robust_mean_pose
from svr.image import Image, voxel_to_world
from svr.models.stack_pose import StackPoseNet
from svr.reconstruction.atlas_fit import (
    AtlasFitConfig,
    atlas_agreement,
    fit_to_atlas,
)
from svr.sampling.blocks import block_channels, coarsen_stack, sample_blocks, stack_frame
from svr.sampling.volume import CanonicalVolume
from svr.validation import check_number

__all__ = [
    "JointFrame",
    "PacketPoseEstimate",
    "StackPoseEstimate",
    "estimate_packet_poses",
    "estimate_stack_pose",
    "joint_frame",
    "mask_axis_hypotheses",
    "refine_transforms",
    "restart_transforms",
]


def mask_axis_hypotheses(points: Tensor, weights: Tensor | None = None) -> Tensor:
    """Candidate scanner -> canonical transforms from the principal axes of a brain mask.

    The longest axis is taken as the brain's front-back (canonical y), the middle one as left-right
    (x) and the shortest as top-bottom (z), or with x and z swapped (their lengths are close in
    young brains); each with the 4 sign choices that keep the frame right-handed.

    Args:
        points: (N, 3) world positions (mm) of the mask's voxels, N >= 4.
        weights: (N,) non-negative weights (mask fractions), default 1.

    Returns:
        (8, 4, 4) float64 transforms (world mm -> canonical mm), each mapping the mask's centroid
        to the canonical origin.

    Raises:
        ValueError: If ``points`` is not (N >= 4, 3).
    """
    if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] < 4:
        raise ValueError(
            "mask_axis_hypotheses(): 'points' must have shape (N >= 4, 3), got "
            f"{tuple(points.shape)}"
        )
    p = points.to(torch.float64)
    w = torch.ones(p.shape[0], dtype=torch.float64) if weights is None else weights.double()
    w = w / w.sum()
    centre = (w[:, None] * p).sum(0)
    d = p - centre
    _, vectors = torch.linalg.eigh((w[:, None] * d).T @ d)  # ascending: shortest first
    short, middle, longest = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    transforms = []
    for x_axis in (middle, short):
        for sx, sy in ((1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)):
            x, y = sx * x_axis, sy * longest
            rows = torch.stack([x, y, torch.linalg.cross(x, y)])
            transform = torch.eye(4, dtype=torch.float64)
            transform[:3, :3] = rows
            transform[:3, 3] = -rows @ centre
            transforms.append(transform)
    return torch.stack(transforms)


class StackPoseEstimate(NamedTuple):
    """A stack's estimated canonical pose.

    Attributes:
        pose: (4, 4) float64 stack pose (stack frame mm -> canonical mm).
        to_canonical: (4, 4) float64 transform (the stack's scanner mm -> canonical mm).
        score: What chose it: the model's logit, or the atlas NCC where an atlas chose.
        hypotheses: (H, 4, 4) transforms of every hypothesis (refined by the model if given).
        scores: (H,) their scores (model logits, or atlas NCCs where an atlas chose).
        method: How it was made: ``"learned"``, ``"learned+atlas"`` (the model's choice, fitted
            to the atlas), ``"axes+atlas"`` (no model), or ``"learned (atlas fit rejected: ...)"``.
    """

    pose: Tensor
    to_canonical: Tensor
    score: float
    hypotheses: Tensor
    scores: Tensor
    method: str


def restart_transforms(to_canonical: Tensor, turn_deg: float) -> Tensor:
    """A transform and six copies turned by ``turn_deg`` either way about each canonical axis.

    The turns are about the canonical origin (the brain's centre): every copy maps the same
    scanner point to it.

    Args:
        to_canonical: (4, 4) transform (scanner mm -> canonical mm).
        turn_deg: The turn (degrees, >= 0).

    Returns:
        (7, 4, 4) float64 transforms, ``to_canonical`` first, then +x, -x, +y, -y, +z, -z.

    Raises:
        ValueError: If ``to_canonical`` is not (4, 4) or ``turn_deg`` is negative or not finite.
    """
    if tuple(to_canonical.shape) != (4, 4):
        raise ValueError(
            f"restart_transforms(): 'to_canonical' must be (4, 4), got {tuple(to_canonical.shape)}"
        )
    check_number("restart_transforms", "turn_deg", turn_deg, ge=0.0)
    eye = torch.eye(3, dtype=torch.float64)
    axes = torch.stack([eye, -eye], dim=1).reshape(6, 3)  # +x, -x, +y, -y, +z, -z
    turns = torch.eye(4, dtype=torch.float64).repeat(7, 1, 1)
    turns[1:, :3, :3] = so3_exp(axes * math.radians(turn_deg))
    return se3_compose(turns, to_canonical.to(torch.float64))


@torch.no_grad()
def refine_transforms(
    model: StackPoseNet,
    stack: Image,
    mask: Tensor,
    transforms: Tensor,
    iterations: int = 3,
    present: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Apply the network's residual to candidate transforms, ``iterations`` times, and score them.

    Args:
        model: The network (eval mode).
        stack: (I, J, K) stack, already coarsened (:func:`svr.sampling.blocks.coarsen_stack`).
        mask: (I, J, K) float mask on its grid.
        transforms: (H, 4, 4) starting transforms (scanner -> canonical).
        iterations: Refinement steps, >= 0.
        present: (K,) bool slices to use (default all).

    Returns:
        The (H, 4, 4) float64 refined transforms and (H,) float logits scored at them.
    """
    device = next(model.parameters()).device
    grid = model.config.grid
    transforms = transforms.to(torch.float64)
    score = torch.zeros(transforms.shape[0])
    channels = block_channels(stack, mask, present)
    for step in range(iterations + 1):
        blocks = sample_blocks(channels, stack, transforms, grid).to(device)
        residual, logits, _, _ = model(blocks)
        score = logits.float().cpu()
        if step < iterations:
            transforms = se3_compose(residual.double().cpu(), transforms)
    return transforms, score


def estimate_stack_pose(
    model: StackPoseNet | None,
    stack: Image,
    mask: Tensor,
    iterations: int = 3,
    atlas: CanonicalVolume | None = None,
    fit: AtlasFitConfig | None = None,
    in_plane_mm: float = 2.0,
    max_fit_turn_deg: float = 15.0,
    levels: list[Image] | None = None,
    restart_deg: float = 0.0,
) -> StackPoseEstimate:
    """A stack's canonical pose from its own data: mask-axis hypotheses, refined, one chosen.

    With a model, every hypothesis is refined by it and its score chooses one; with
    ``restart_deg`` > 0 the chosen transform is then refined again from itself and six starts
    turned by ``restart_deg`` about the canonical axes (:func:`restart_transforms`), and the
    robust mean of the seven is kept. With an atlas as well, the chosen transform is then
    rigidly fitted to the atlas (:func:`svr.reconstruction.atlas_fit.fit_to_atlas`) unless the
    fit turns it by more than ``max_fit_turn_deg`` (a fit gone to another optimum: the model's
    transform is kept). Without a model, the hypothesis that agrees best with the atlas (NCC,
    :func:`svr.reconstruction.atlas_fit.atlas_agreement`) is chosen and fitted.

    Args:
        model: The trained network, or ``None`` (then ``atlas`` is required).
        stack: (I, J, K) stack in its scanner frame (any in-plane spacing).
        mask: (I, J, K) brain mask on its grid (bool or fractions).
        iterations: Refinement steps per hypothesis.
        atlas: A brain of about the stack's age in canonical space, or ``None``.
        fit: The atlas fit's settings (default
            :class:`~svr.reconstruction.atlas_fit.AtlasFitConfig`).
        in_plane_mm: In-plane spacing the stack is averaged to without a model (with one, the
            model's).
        max_fit_turn_deg: With a model and an atlas, the largest turn the atlas fit may make.
        levels: The atlas's blurred copies for ``fit``
            (:func:`svr.reconstruction.atlas_fit.atlas_levels`), computed once for the stacks of
            one fetus; ``None`` makes them here.
        restart_deg: With a model, the turn (degrees, >= 0) of the restarts about the chosen
            transform; 0 keeps the chosen hypothesis as refined.

    Returns:
        The estimate.

    Raises:
        ValueError: If the mask has fewer than 4 voxels, or neither a model nor an atlas is given.
    """
    if model is None and atlas is None:
        raise ValueError("estimate_stack_pose(): give a 'model', an 'atlas' or both")
    if model is not None:
        model.eval()
        in_plane_mm = model.config.in_plane_mm
    image, fractions = coarsen_stack(stack, mask, in_plane_mm)
    inside = fractions > 0.5
    if int(inside.sum()) < 4:
        raise ValueError("estimate_stack_pose(): the brain mask has fewer than 4 voxels")
    idx = torch.nonzero(inside).to(torch.float64)
    transforms = mask_axis_hypotheses(voxel_to_world(image.affine, idx))
    method = "axes"
    if model is not None:
        transforms, scores = refine_transforms(model, image, fractions, transforms, iterations)
        method = "learned"
    else:
        assert atlas is not None
        with torch.no_grad():
            scores = atlas_agreement(image, fractions, transforms, atlas).float()
    best = int(torch.argmax(scores))
    to_canonical, score = transforms[best], float(scores[best])
    if model is not None and restart_deg > 0:
        restarted, _ = refine_transforms(
            model, image, fractions, restart_transforms(to_canonical, restart_deg), iterations
        )
        to_canonical = robust_mean_pose(restarted)
    if atlas is not None:
        fitted, ncc = fit_to_atlas(image, fractions, to_canonical, atlas, fit, levels)
        turn = math.degrees(rotation_angle(fitted, to_canonical))
        if model is None or turn <= max_fit_turn_deg:
            to_canonical, method = fitted, method + "+atlas"
            score = ncc if model is None else score
        else:
            method += f" (atlas fit rejected: {turn:.0f} deg away)"
    return StackPoseEstimate(
        pose=se3_compose(to_canonical, stack_frame(stack)),
        to_canonical=to_canonical,
        score=score,
        hypotheses=transforms,
        scores=scores,
        method=method,
    )


class PacketPoseEstimate(NamedTuple):
    """The canonical transforms of a stack's interleaved packets, each estimated on its own.

    Attributes:
        to_canonical: (P, 4, 4) float64 transform of each packet (scanner mm -> canonical mm).
        scores: (P,) the model's logit for each chosen transform.
        own: (P,) bool, True where a packet's own mask-axis hypothesis scored higher than its
            stack's transform (the packet turned away from its stack, or the stack's was wrong).
    """

    to_canonical: Tensor
    scores: Tensor
    own: Tensor


def estimate_packet_poses(
    model: StackPoseNet,
    stack: Image,
    mask: Tensor,
    to_canonical: Tensor,
    packet_of: Tensor,
    iterations: int = 3,
    max_apart_deg: float = 100.0,
) -> PacketPoseEstimate:
    """Each interleaved packet's canonical transform from its own slices, its stack's a candidate.

    A packet's slices were acquired in one sweep, so they move together far less than a stack's.
    For each packet, the stack's transform and the 8 mask-axis hypotheses of the packet's own mask
    (:func:`mask_axis_hypotheses`) are refined by the network on the packet's slices only
    (:func:`refine_transforms` with ``present``) and the best-scored is kept. Where the fetus
    turned within the stack, or the stack's transform is a wrong twin, a packet's own hypothesis
    wins. Packets of one stack that end more than ``max_apart_deg`` apart mean that one took a
    wrong twin; then every packet keeps the stack's transform refined on its slices.

    Args:
        model: The trained network.
        stack: (I, J, K) stack in its scanner frame (any in-plane spacing).
        mask: (I, J, K) brain mask on its grid (bool or fractions).
        to_canonical: (4, 4) the stack's estimated transform (scanner mm -> canonical mm).
        packet_of: (K,) int packet index 0..P-1 of each k-plane.
        iterations: Refinement steps per candidate.
        max_apart_deg: The largest angle between two packets' own transforms (degrees).

    Returns:
        The transforms and scores of packets 0 to ``packet_of.max()``; a packet with fewer than 4
        mask voxels keeps the stack's transform refined on its slices, one without a plane the
        stack's transform (score NaN).

    Raises:
        ValueError: If ``packet_of`` does not have one entry per k-plane or has negative values.
    """
    k = stack.data.shape[-1]
    if packet_of.shape != (k,) or bool((packet_of < 0).any()):
        raise ValueError(
            f"estimate_packet_poses(): 'packet_of' must be ({k},) non-negative packet indices, "
            f"got shape {tuple(packet_of.shape)}"
        )
    model.eval()
    image, fractions = coarsen_stack(stack, mask, model.config.in_plane_mm)
    stack_transform = to_canonical.to(torch.float64).cpu()
    packet_of = packet_of.cpu()
    count = int(packet_of.max()) + 1
    # Per packet: the best-scored candidate, and the stack's transform refined on the packet
    # (the fallback); a packet without a plane in the (cropped) stack keeps the stack's.
    best_transforms = stack_transform.repeat(count, 1, 1)
    stack_transforms = stack_transform.repeat(count, 1, 1)
    best_scores = torch.full((count,), float("nan"))
    stack_scores = best_scores.clone()
    own = torch.zeros(count, dtype=torch.bool)
    placed = [p for p in range(count) if bool((packet_of == p).any())]
    for packet in placed:
        present = packet_of == packet
        candidates = stack_transform[None]
        idx = torch.nonzero((fractions > 0.5) & present[None, None, :]).to(torch.float64)
        if idx.shape[0] >= 4:
            hypotheses = mask_axis_hypotheses(voxel_to_world(image.affine, idx))
            candidates = torch.cat([candidates, hypotheses])
        refined, logits = refine_transforms(
            model, image, fractions, candidates, iterations, present
        )
        best = int(torch.argmax(logits))
        best_transforms[packet], best_scores[packet] = refined[best], logits[best]
        stack_transforms[packet], stack_scores[packet] = refined[0], logits[0]
        own[packet] = best > 0
    apart = max(
        (
            math.degrees(rotation_angle(best_transforms[a], best_transforms[b]))
            for i, a in enumerate(placed)
            for b in placed[i + 1 :]
        ),
        default=0.0,
    )
    if apart > max_apart_deg:
        return PacketPoseEstimate(stack_transforms, stack_scores, torch.zeros_like(own))
    return PacketPoseEstimate(best_transforms, best_scores, own)


class JointFrame(NamedTuple):
    """The canonical frame of several registered stacks of one fetus, by their pooled scores.

    Attributes:
        to_canonical: (4, 4) float64 transform from the registration's (template) frame to
            canonical mm: stack ``s`` placed by ``to_canonical o M_s``.
        score: The network's logits at the chosen hypothesis, summed over the stacks.
        margin: That sum minus the best sum of a hypothesis more than ``distinct_deg`` away (a
            twin or another frame); small or negative: the stacks do not tell the frames apart.
    """

    to_canonical: Tensor
    score: float
    margin: float


@torch.no_grad()
def joint_frame(
    model: StackPoseNet,
    stacks: Sequence[tuple[Image, Tensor]],
    to_canonical: Tensor,
    moves: Tensor,
    iterations: int = 3,
    distinct_deg: float = 45.0,
) -> JointFrame:
    """One canonical frame for stacks that registration put together, from all of them at once.

    A stack alone can score its front-back twin above the right frame (a brain unlike the
    training atlas's, real contrast); stacks registered to one another share one frame, so each
    hypothesis is scored on every stack and the scores are summed. The hypotheses are each stack's
    own transform ``E_s o M_s^-1`` and its three half turns about the canonical axes; the winner
    is refined on every stack (``iterations`` steps of the network from ``G o M_s``) and the robust
    mean of the frames they imply is returned.

    Args:
        model: The stack-pose network.
        stacks: Per stack, its image and brain mask (bool or fractions) in its scanner frame.
        to_canonical: (S, 4, 4) each stack's own estimate ``E_s`` (scanner mm -> canonical mm).
        moves: (S, 4, 4) each stack's registration ``M_s`` (scanner mm -> the template frame).
        iterations: Refinement steps of the winner on each stack.
        distinct_deg: Hypotheses farther apart than this (degrees) are other frames (margin).

    Returns:
        The frame, its pooled score and its margin.
    """
    model.eval()
    coarse = [coarsen_stack(image, mask, model.config.in_plane_mm) for image, mask in stacks]
    moves = moves.to(torch.float64).cpu()
    own = se3_compose(to_canonical.to(torch.float64).cpu(), se3_inverse(moves))  # (S, 4, 4)
    turns = torch.cat([torch.eye(4, dtype=torch.float64)[None], half_turns()])
    hypotheses = se3_compose(turns[None], own[:, None]).reshape(-1, 4, 4)
    scores = torch.zeros(len(hypotheses), dtype=torch.float64)
    for (image, fractions), move in zip(coarse, moves, strict=True):
        placed = se3_compose(hypotheses, move.expand_as(hypotheses))
        scores += refine_transforms(model, image, fractions, placed, iterations=0)[1].double()
    best = int(torch.argmax(scores))
    frame = hypotheses[best]
    far = rotation_angle(hypotheses, frame.expand_as(hypotheses)) > math.radians(distinct_deg)
    runner_up = float(scores[far].max()) if bool(far.any()) else -math.inf
    implied = []
    for (image, fractions), move in zip(coarse, moves, strict=True):
        start = se3_compose(frame, move)[None]
        refined, _ = refine_transforms(model, image, fractions, start, iterations)
        implied.append(se3_compose(refined[0], se3_inverse(move)))
    return JointFrame(
        robust_mean_pose(torch.stack(implied)),
        float(scores[best]),
        float(scores[best]) - runner_up,
    )
