"""The ``"learned"`` start: every stack and packet placed in canonical space by the network.

1. **Per-stack transforms.** Each stack's scanner -> canonical transform ``E_s`` comes from its
   own slices and mask (:func:`~svr.reconstruction.initialisation.stack_pose.estimate_stack_pose`:
   mask-axis hypotheses refined by the stack-pose network, chosen by its score). No template
   stack: a fetus that turned between stacks is placed stack by stack.
2. **Per-packet transforms** (``config.packets`` > 1). Each interleaved packet's transform from its
   own slices (:func:`~svr.reconstruction.initialisation.stack_pose.estimate_packet_poses`), for a
   fetus that moved within a stack, or a stack whose own transform is a wrong twin that its
   packets are not.
3. **One frame for the registered stacks** (:func:`joint_frame`): stack registration from the
   scanner poses puts the stacks together; each stack's transform and its front-back twins are
   scored by the network on every stack at once, and the best, refined, is the frame of the
   registered stacks. A stack whose own transform is a twin of that frame takes the frame's
   (a brain unlike the training atlas's can make the network prefer a stack's twin, and one
   stack's evidence is weaker than all of them together).
4. **Candidates and the safe choice**
   (:func:`~svr.reconstruction.initialisation.choice.place_stacks`): each placement refined by
   stack registration and brought into canonical space, and per stack the candidate that agrees
   best with the other stacks, stack registration included.
5. **Every slice** (with an atlas, ``config.initialisation.slice_refinement``): each slice moved
   by the shipped slice refiner against the atlas, kept where the other stacks agree better,
   then put on its packet's motion trajectory where the head was calm
   (``config.initialisation.slice_trajectory``)
   (:func:`~svr.reconstruction.initialisation.slice_refinement.place_slices`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from svr.geometry import half_turns, rotation_angle, se3_compose
from svr.models.slice_refiner import shipped_slice_refiners
from svr.models.stack_pose import StackPoseNet
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation.choice import (
    AGREE_DEG,
    Start,
    place_stacks,
    register_stacks,
    stack_moves,
)
from svr.reconstruction.initialisation.slice_refinement import place_slices
from svr.reconstruction.initialisation.stack_pose import (
    estimate_packet_poses,
    estimate_stack_pose,
    joint_frame,
)
from svr.reconstruction.slices import SliceSet, Stack
from svr.sampling.volume import CanonicalVolume

__all__ = ["NetworkPlacement", "learned_start", "network_placement", "refined_slices"]

log = logging.getLogger(__name__)


class NetworkPlacement(NamedTuple):
    """Every stack (and packet) placed in canonical space by the stack-pose network alone.

    Attributes:
        to_canonical: (S, 4, 4) float64 CPU each stack's scanner -> canonical transform.
        packet_to_canonical: (S, P, 4, 4) float64 CPU each packet's (packet of slice ``k``:
            ``k % P``), or ``None`` with one packet per stack.
        scores: (S,) float64 the network's score of each stack's transform (logits).
        notes: Per stack, what its estimate says of itself (method, score, packets' turns).
    """

    to_canonical: Tensor
    packet_to_canonical: Tensor | None
    scores: Tensor
    notes: list[str]


def network_placement(
    stacks: Sequence[Stack], model: StackPoseNet, packets: int, restart_deg: float
) -> NetworkPlacement:
    """Steps 1 and 2 of the module docstring: each stack's and packet's own transform.

    Args:
        stacks: The stacks, in their scanner frames.
        model: The stack-pose network.
        packets: Interleaved packets per stack (``ReconstructionConfig.packets``); 1 for none.
        restart_deg: The turn of the network's restarts about each stack's choice (degrees).

    Returns:
        The placements, before any registration.
    """
    to_canonical = torch.empty(len(stacks), 4, 4, dtype=torch.float64)
    packet_to_canonical = torch.empty(len(stacks), packets, 4, 4, dtype=torch.float64)
    notes, scores = [], []
    for sid, stack in enumerate(stacks):
        mask = stack.mask.data > 0.5
        estimate = estimate_stack_pose(model, stack.image, mask, restart_deg=restart_deg)
        to_canonical[sid] = estimate.to_canonical
        scores.append(float(estimate.score))
        note = f"{estimate.method}, score {estimate.score:.2f}"
        log.info("%s: stack pose by %s (score %.3f)", stack.name, estimate.method, estimate.score)
        if packets > 1:
            per_packet = estimate_packet_poses(
                model, stack.image, mask, estimate.to_canonical, stack.k_indices.cpu() % packets
            )
            packet_to_canonical[sid] = estimate.to_canonical  # packets without a plane here
            packet_to_canonical[sid, : len(per_packet.to_canonical)] = per_packet.to_canonical
            turns = [
                math.degrees(rotation_angle(t, estimate.to_canonical))
                for t in per_packet.to_canonical
            ]
            note += "; packets " + ", ".join(f"{t:.0f} deg" for t in turns)
            log.info(
                "%s: packets %s from the stack's frame (own hypothesis: %s)",
                stack.name,
                ", ".join(f"{t:.1f}" for t in turns),
                per_packet.own.tolist(),
            )
        notes.append(note)
    return NetworkPlacement(
        to_canonical,
        packet_to_canonical if packets > 1 else None,
        torch.tensor(scores, dtype=torch.float64),
        notes,
    )


def learned_start(
    slices: SliceSet,
    stacks: Sequence[Stack],
    model: StackPoseNet,
    config: ReconstructionConfig,
    atlas: CanonicalVolume | None = None,
) -> Start:
    """Every stack and packet placed by the stack-pose network, or stack registration, per stack.

    Args:
        slices: All slices, at their scanner poses.
        stacks: The stacks they were cut from (same order as ``slices.stack_names``).
        model: The stack-pose network.
        config: Settings (``packets``, ``initialisation.restart_deg``, the template and grid).
        atlas: A brain of about the fetus's age in canonical space: with it (and
            ``config.initialisation.slice_refinement``), every slice is then refined against it
            (step 5 of the module docstring).

    Returns:
        The slices at their starting canonical poses, the choice and notes per stack.
    """
    placement = network_placement(stacks, model, config.packets, config.initialisation.restart_deg)
    to_canonical, packet_to_canonical = placement.to_canonical, placement.packet_to_canonical
    heads = placement.notes
    scanner = slices.poses.to(torch.float64).cpu()
    registered = register_stacks(slices, scanner, config)
    moves = stack_moves(slices, scanner, registered)
    images = [(stack.image, stack.mask.data > 0.5) for stack in stacks]
    joint = joint_frame(model, images, to_canonical, moves)
    log.info(
        "the registered stacks' frame: pooled score %.1f, margin %.1f over any other frame",
        joint.score,
        joint.margin,
    )
    expected = se3_compose(joint.to_canonical.expand_as(moves), moves)
    for sid, stack in enumerate(stacks):
        turned = _twin_towards(to_canonical[sid], expected[sid])
        if turned is not None:
            log.info("%s: its own transform is a twin of the stacks' frame: turned", stack.name)
            heads[sid] += "; turned to the stacks' frame"
            to_canonical[sid] = se3_compose(turned, to_canonical[sid])
            if packet_to_canonical is not None:
                packet_to_canonical[sid] = se3_compose(turned, packet_to_canonical[sid])
    # Each stack's vote for the output frame: the model's confidence in its transform.
    votes = torch.sigmoid(placement.scores)
    start = place_stacks(
        slices,
        to_canonical,
        packet_to_canonical,
        votes,
        heads,
        config,
        registered=registered,
        frame=joint.to_canonical,
    )
    start = start._replace(frame_margin=joint.margin)
    if atlas is None or not config.initialisation.slice_refinement:
        return start
    return refined_slices(start, atlas, config)


def refined_slices(start: Start, atlas: CanonicalVolume, config: ReconstructionConfig) -> Start:
    """The start with every slice refined against ``atlas`` where the other stacks agree.

    Args:
        start: The learned start (canonical frame).
        atlas: A brain of about the fetus's age in canonical space.
        config: Settings (``initialisation.slice_refiner_steps``, the initialisation grid).

    Returns:
        The start with the kept slices moved; each stack's note says how many and how far.
    """
    slices = start.slices
    refiners = shipped_slice_refiners(str(slices.device))
    stages = list(zip(refiners, config.initialisation.slice_refiner_steps, strict=True))
    packets = config.packets if config.initialisation.slice_trajectory else None
    placed = place_slices(slices, atlas, stages, config.initialisation_grid_mm, packets)
    if len(slices.stack_names) > 1 and len(slices):
        log.info(
            "slice refiner: the start's median slice NCC with the other stacks is %.3f, so each "
            "move is judged against the other stacks %s",
            float(placed.ncc_before.median()),
            "at their start" if placed.start_trusted else "at their refined poses",
        )
    if placed.smoothness is not None:
        log.info(
            "slice trajectories: the %s trajectory predicts a left-out slice best (smoothness "
            "%g): %s",
            "stiffest" if placed.on_trajectory else "a more flexible",
            placed.smoothness,
            "a calm head, the slices put on their packets' trajectories"
            if placed.on_trajectory
            else "the head moved between slices, the slices left as estimated",
        )
    moved = torch.rad2deg(rotation_angle(placed.poses, slices.poses.to(placed.poses)))
    notes = list(start.notes) or [""] * len(slices.stack_names)
    for sid, name in enumerate(slices.stack_names):
        mine = slices.stack_ids == sid
        kept = placed.kept & mine
        text = f"slice refiner: {int(kept.sum())} of {int(mine.sum())} slices moved"
        if placed.on_trajectory:
            text += (
                ", then all put on their packets' motion trajectories (median "
                f"{float(moved[mine].median()):.1f} deg from the packets' start)"
            )
        elif bool(kept.any()):
            text += f" (median {float(moved[kept].median()):.1f} deg)"
        log.info("%s: %s", name, text)
        notes[sid] = f"{notes[sid]}; {text}" if notes[sid] else text
    return start._replace(
        slices=slices.with_poses(placed.poses.to(slices.poses)), notes=tuple(notes)
    )


def _twin_towards(own: Tensor, expected: Tensor) -> Tensor | None:
    """The half turn (4, 4) that brings ``own`` within :data:`AGREE_DEG` of ``expected``.

    ``None`` where ``own`` is already within it, or no half turn brings it there (a stack that
    registration could not put with the others, for one).
    """
    if math.degrees(rotation_angle(own, expected)) <= AGREE_DEG:
        return None
    for turn in half_turns():
        if math.degrees(rotation_angle(se3_compose(turn, own), expected)) <= AGREE_DEG:
            return turn
    return None
