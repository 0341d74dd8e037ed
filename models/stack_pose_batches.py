"""The stack-pose network's training batches (:func:`svr.models.stack_pose_train.train_stack_pose`).

A step's batch (:func:`simulate_batch`) is ``stacks_per_step`` stacks, each simulated from a
brain drawn from the phase's brains (alike, or by a weight per brain), optionally a synthetic copy
of it (:func:`training_brain`: the labels' geometry with a random contrast,
:mod:`svr.sampling.synthesis`), with ``samples_per_stack`` blocks cut from each in frames drawn
around the truth (:func:`draw_samples`): within reach (the residual to learn, score 1) or out of
reach (score 0). With worker processes each step's batch comes from a generator seeded by the
step (:func:`step_seed`, :class:`StepBatches`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor
from torch.nn import functional
from torch.utils.data import Dataset

from svr.geometry import se3_compose, so3_exp, vector_to_se3
from svr.models.stack_pose import StackPoseConfig
from svr.sampling.blocks import (
    TrainingStack,
    block_inputs,
    coarsen_stack,
    packet_index,
    simulate_training_stack,
    stack_frame,
)
from svr.sampling.motion import Trajectory
from svr.sampling.synthesis import synthesize_volume
from svr.sampling.volume import CanonicalVolume

if TYPE_CHECKING:
    from svr.models.stack_pose_train_config import StackPoseTrainingConfig

__all__ = [
    "Brains",
    "StepBatches",
    "draw_samples",
    "simulate_batch",
    "step_seed",
    "training_brain",
]

_WRONG_TURNS = torch.tensor(
    [
        [math.pi, 0.0, 0.0],
        [0.0, math.pi, 0.0],
        [0.0, 0.0, math.pi],
        [0.0, math.pi / 2, 0.0],
        [0.0, -math.pi / 2, 0.0],
    ],
    dtype=torch.float64,
)
"""Rotation vectors of the turns that wrong mask-axis hypotheses make (sign flips, x/z swaps)."""


def _random_axis(n: int, generator: torch.Generator) -> Tensor:
    return functional.normalize(torch.randn(n, 3, generator=generator, dtype=torch.float64), dim=-1)


def _subset(
    stack: TrainingStack, config: StackPoseTrainingConfig, generator: torch.Generator
) -> Tensor:
    k = stack.image.shape[2]
    present = torch.ones(k, dtype=torch.bool)
    if float(torch.rand(1, generator=generator)) >= config.subset_fraction:
        return present
    present[:] = False
    if float(torch.rand(1, generator=generator)) < 0.5:
        packet = packet_index(stack.acquisition_index)
        j = int(torch.randint(int(packet.max()) + 1, (1,), generator=generator))
        return packet == j
    size = int(torch.randint(1, min(config.max_subset, k) + 1, (1,), generator=generator))
    first = int(torch.randint(0, k - size + 1, (1,), generator=generator))
    present[first : first + size] = True
    return present


def draw_samples(
    stack: TrainingStack,
    model_config: StackPoseConfig,
    config: StackPoseTrainingConfig,
    generator: torch.Generator,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Blocks of one stack in frames drawn around its true frame.

    Args:
        stack: The simulated stack.
        model_config: The network's block grid.
        config: The draw's ranges.
        generator: Source of the draws.

    Returns:
        ``(blocks, starts, target, labels)``: (n, 3, S, S, S) float32 blocks, (n, 4, 4) float64
        start stack poses, the (4, 4) true stack pose and (n,) float labels (1 = within reach).
        A subset's block is taught the whole stack's pose: teaching it its own slices' pose
        (:func:`svr.sampling.blocks.stack_pose_from_slices` of the present slices) measured no
        better.
    """
    n = config.samples_per_stack
    frame_true = se3_compose(stack.pose, torch.linalg.inv(stack_frame(stack.image)))
    positive = torch.rand(n, generator=generator) < config.positive_fraction
    angle = torch.rand(n, generator=generator, dtype=torch.float64) * math.radians(
        config.max_start_deg
    )
    rotvec = _random_axis(n, generator) * angle[:, None]
    shift = torch.randn(n, 3, generator=generator, dtype=torch.float64) * config.start_shift_mm
    local = vector_to_se3(torch.cat([rotvec, shift], dim=-1))
    wrong = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    for i in torch.nonzero(~positive).flatten().tolist():
        if float(torch.rand(1, generator=generator)) < 0.5:
            turn = _WRONG_TURNS[int(torch.randint(len(_WRONG_TURNS), (1,), generator=generator))]
        else:
            far = math.radians(60.0) + float(torch.rand(1, generator=generator)) * math.radians(
                120.0
            )
            turn = _random_axis(1, generator)[0] * far
        wrong[i, :3, :3] = so3_exp(turn)
    frames = se3_compose(local, se3_compose(wrong, frame_true.expand(n, 4, 4)))
    image, mask = coarsen_stack(stack.image, stack.mask, model_config.in_plane_mm)
    present = _subset(stack, config, generator)
    blocks = block_inputs(image, mask, frames, model_config.grid, present)
    starts = se3_compose(frames, stack_frame(stack.image).expand(n, 4, 4))
    return blocks, starts, stack.pose, positive.float()


def training_brain(
    volume: CanonicalVolume, config: StackPoseTrainingConfig, generator: torch.Generator
) -> CanonicalVolume:
    """The brain a training stack is simulated from: ``volume``, or a synthetic copy of it.

    With ``config.synthesis``, each stack draws whether its brain is synthetic (probability
    ``config.synthesis_fraction``); a brain with tissue labels then becomes a synthetic copy
    (:func:`svr.sampling.synthesis.synthesize_volume`, same geometry, random contrast), one
    without labels (a phantom) stays as it is. Without ``config.synthesis`` nothing is drawn, so
    the stream of draws is the one before synthesis existed.
    """
    if config.synthesis is None:
        return volume
    synthetic = float(torch.rand(1, generator=generator)) < config.synthesis_fraction
    if not synthetic or volume.labels is None:
        return volume
    return synthesize_volume(volume, config.synthesis, generator)


def simulate_batch(
    volumes: list[CanonicalVolume],
    trajectories: list[Trajectory] | None,
    model_config: StackPoseConfig,
    config: StackPoseTrainingConfig,
    generator: torch.Generator,
    weights: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One training step's blocks: ``stacks_per_step`` simulated stacks, their samples stacked.

    Args:
        volumes: Training brains in canonical space.
        trajectories: Real motion recordings (``None``: random walks).
        model_config: The network's block grid.
        config: The draw's ranges.
        generator: Source of every draw (advanced).
        weights: (len(volumes),) float64 relative chance of each brain being drawn for a stack;
            ``None`` draws every brain alike.

    Each stack's brain may be a synthetic copy of the drawn one (:func:`training_brain`).

    Returns:
        ``(blocks, starts, targets, labels)`` over B = stacks_per_step * samples_per_stack
        blocks: (B, 3, S, S, S) float32, (B, 4, 4) float64 start and true stack poses, (B,)
        labels.
    """
    batch = []
    for _ in range(config.stacks_per_step):
        if weights is None:
            index = int(torch.randint(len(volumes), (1,), generator=generator))
        else:
            index = int(torch.multinomial(weights, 1, generator=generator))
        volume = training_brain(volumes[index], config, generator)
        stack = simulate_training_stack(volume, config.stacks, generator, trajectories)
        blocks, starts, target, labels = draw_samples(stack, model_config, config, generator)
        batch.append((blocks, starts, target.expand_as(starts), labels))
    blocks, starts, targets, labels = (torch.cat(parts) for parts in zip(*batch, strict=True))
    return blocks, starts, targets, labels


def step_seed(seed: int, step: int) -> int:
    """The seed of step ``step``'s simulation when stacks are simulated by worker processes."""
    return (seed * 1_000_003 + step) % (2**63)


Brains = tuple[list[CanonicalVolume], Tensor | None]
"""A phase's training brains and their draw weights (``None``: alike)."""


class StepBatches(Dataset):
    """Step ``i``'s batch, simulated from a generator seeded by :func:`step_seed`.

    ``phases`` are the training brains (with their draw weights, :func:`simulate_batch`) before
    and from step ``turn`` on; with the config's ``fine_tune_seed`` the steps from ``turn`` on
    are seeded as a separate run's steps 0, 1, ...
    """

    def __init__(
        self,
        phases: tuple[Brains, Brains],
        turn: int,
        trajectories: list[Trajectory] | None,
        model_config: StackPoseConfig,
        config: StackPoseTrainingConfig,
    ) -> None:
        self.phases = phases
        self.turn = turn
        self.trajectories = trajectories
        self.model_config = model_config
        self.config = config

    def __len__(self) -> int:
        return self.config.steps

    def __getitem__(self, step: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        seed, index = self.config.seed, step
        if self.config.fine_tune_seed is not None and step >= self.turn:
            seed, index = self.config.fine_tune_seed, step - self.turn
        generator = torch.Generator().manual_seed(step_seed(seed, index))
        brains, weights = self.phases[step >= self.turn]
        return simulate_batch(
            brains, self.trajectories, self.model_config, self.config, generator, weights
        )
