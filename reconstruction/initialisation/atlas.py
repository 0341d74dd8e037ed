"""The ``"atlas"`` start: every stack placed by agreement with an atlas, no network.

Each stack's mask-axis hypotheses
(:func:`~svr.reconstruction.initialisation.stack_pose.mask_axis_hypotheses`) are scored by how
well they put the stack on the atlas (NCC), and the best is rigidly fitted to it
(:func:`~svr.reconstruction.initialisation.stack_pose.estimate_stack_pose` without a model). With
several atlases, a stack follows the first unless another fits it clearly better
(:func:`~svr.reconstruction.atlas_fit.preferred_atlas`). The placements are then refined by
stack registration and chosen per stack against it
(:func:`~svr.reconstruction.initialisation.choice.place_stacks`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch

from svr.reconstruction.atlas_fit import atlas_levels, preferred_atlas
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation.choice import Start, place_stacks
from svr.reconstruction.initialisation.stack_pose import estimate_stack_pose
from svr.reconstruction.slices import SliceSet, Stack
from svr.sampling.volume import CanonicalVolume

__all__ = ["atlas_start"]

log = logging.getLogger(__name__)


def atlas_start(
    slices: SliceSet,
    stacks: Sequence[Stack],
    atlases: Sequence[CanonicalVolume],
    config: ReconstructionConfig,
) -> Start:
    """Every stack placed by agreement with the atlases, or stack registration, per stack.

    Args:
        slices: All slices, at their scanner poses.
        stacks: The stacks they were cut from (same order as ``slices.stack_names``).
        atlases: Brains of about the fetus's age in canonical space, the preferred first.
        config: Settings (the template and grid).

    Returns:
        The slices at their starting canonical poses, the choice and notes per stack.

    Raises:
        ValueError: If ``atlases`` is empty.
    """
    if not atlases:
        raise ValueError("atlas_start(): 'atlases' must hold at least one atlas")
    levels = [atlas_levels(atlas) for atlas in atlases]
    to_canonical = torch.empty(len(stacks), 4, 4, dtype=torch.float64)
    heads = []
    for sid, stack in enumerate(stacks):
        mask = stack.mask.data > 0.5
        per_atlas = [
            estimate_stack_pose(None, stack.image, mask, atlas=atlas, levels=level)
            for atlas, level in zip(atlases, levels, strict=True)
        ]
        estimate = per_atlas[preferred_atlas([e.score for e in per_atlas])]
        to_canonical[sid] = estimate.to_canonical
        heads.append(f"{estimate.method}, score {estimate.score:.2f}")
        log.info("%s: stack pose by %s (score %.3f)", stack.name, estimate.method, estimate.score)
    # One vote each: the scores are atlas NCCs, not confidences.
    votes = torch.ones(len(stacks), dtype=torch.float64)
    return place_stacks(slices, to_canonical, None, votes, heads, config)
