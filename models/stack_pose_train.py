"""Training the stack-pose network on stacks simulated on the fly, on one CPU core.

Each step simulates ``stacks_per_step`` stacks from the training volumes
(:func:`svr.sampling.blocks.simulate_training_stack`: uniform orientation, real motion, thickness
2-5 mm, gaps and overlaps, bias, noise, voids, imperfect masks) and cuts ``samples_per_stack``
blocks from each, in frames drawn around the truth:

* within reach (probability ``positive_fraction``): the true frame turned by up to
  ``max_start_deg`` about a random axis and shifted by a Gaussian of ``start_shift_mm`` per axis;
  the network learns the residual back to the truth, with the SE(3) geodesic loss on the final
  stack pose, and that the frame is right (score 1);
* out of reach: a turn of at least 60 degrees (half of them the 180/90 degree turns that wrong
  mask-axis hypotheses make), score 0.

Blocks use every slice of the stack (probability ``1 - subset_fraction``) or a subset: one
interleaved packet, or k neighbouring slices (k from 1 to ``max_subset``). The run has two
phases: the last ``fine_tune_steps`` steps restart the learning rate lower and add the fine-tune
brains (procedural phantoms: anatomy unlike the atlas's) to the training ones. Each stack's brain
is drawn alike from the phase's brains, or by a weight per brain (``volume_weights``,
``fine_tune_weights``: for example the anatomy variants of an atlas brain sharing that brain's
weight, so that adding them leaves the phantoms their share of the stacks). With
``fine_tune_seed`` the second phase starts as a separate fine-tuning run from the first phase's
weights would (a fresh Adam, the random stream reseeded), so two commands become one. Checkpoints
(:mod:`svr.models.checkpoint`) are written every ``checkpoint_every`` steps and the newest is
resumed, with the RNG state, so a run that is stopped and started again continues where it was.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import Tensor
from torch.nn import functional
from torch.utils.data import DataLoader, Dataset

from svr.errors import ConfigFieldError
from svr.geometry import se3_compose, so3_exp, vector_to_se3
from svr.models.resume import (
    cosine_schedule,
    restart_as_new_run,
    resume_training,
    save_training_checkpoint,
)
from svr.models.stack_pose import StackPoseConfig, StackPoseNet
from svr.models.stack_pose_loss import stack_pose_loss
from svr.sampling.blocks import (
    TrainingStack,
    TrainingStackConfig,
    block_inputs,
    coarsen_stack,
    packet_index,
    simulate_training_stack,
    stack_frame,
)
from svr.sampling.motion import Trajectory
from svr.sampling.volume import CanonicalVolume
from svr.validation import check_fraction, check_instance, check_int, check_number, is_integer

__all__ = [
    "StackPoseTrainingConfig",
    "draw_samples",
    "simulate_batch",
    "step_seed",
    "train_stack_pose",
]

log = logging.getLogger(__name__)

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


@dataclass(frozen=True)
class StackPoseTrainingConfig:
    """How the stack-pose network is trained.

    Attributes:
        steps: Optimiser steps, >= 1.
        stacks_per_step: Stacks simulated per step, >= 1.
        samples_per_stack: Blocks cut from each stack, >= 1.
        learning_rate: Adam's initial rate (cosine decay to 5 % of it).
        fine_tune_steps: The last steps of ``steps``, a second phase: the rate restarts at
            ``fine_tune_learning_rate`` (cosine decay to 5 % of it again) and the fine-tune
            volumes (``train_stack_pose``'s ``fine_tune_volumes``: the procedural phantoms)
            join the training brains. 0 for one phase; < ``steps``.
        fine_tune_learning_rate: Adam's rate at the start of the second phase.
        fine_tune_seed: An int: the second phase is the run that fine-tuning the first
            phase's weights with this seed would be (Adam's moments reset, the random stream
            reseeded with it, its rate ``fine_tune_learning_rate`` times the cosine as that
            run's own), to the last bit: the shipped model's recipe. ``None``: the second phase
            continues the first's random stream and Adam's moments (one schedule with a warm
            restart). Unused without a second phase.
        max_start_deg: Largest start error within reach (degrees).
        start_shift_mm: Per-axis standard deviation of the start's shift (mm).
        positive_fraction: Share of blocks within reach.
        subset_fraction: Share of blocks made of a packet or k neighbouring slices.
        max_subset: Largest k of the neighbouring-slice blocks.
        score_weight: Weight of the score's cross-entropy beside the pose loss.
        coords_weight: Weight of the coordinate loss (``"coords"`` head).
        checkpoint_every: Steps between checkpoints.
        seed: Seed of every random draw.
        stacks: The ranges the training stacks are drawn from.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    steps: int = 23000
    stacks_per_step: int = 2
    samples_per_stack: int = 4
    learning_rate: float = 1e-3
    fine_tune_steps: int = 9000
    fine_tune_learning_rate: float = 3e-4
    fine_tune_seed: int | None = 2
    max_start_deg: float = 40.0
    start_shift_mm: float = 5.0
    positive_fraction: float = 0.65
    subset_fraction: float = 0.25
    max_subset: int = 12
    score_weight: float = 0.2
    coords_weight: float = 0.1
    checkpoint_every: int = 250
    seed: int = 0
    stacks: TrainingStackConfig = field(default_factory=TrainingStackConfig)

    def __post_init__(self) -> None:
        owner = "StackPoseTrainingConfig"
        for name in (
            "steps",
            "stacks_per_step",
            "samples_per_stack",
            "checkpoint_every",
            "max_subset",
        ):
            check_int(owner, name, getattr(self, name), minimum=1)
        for name in ("positive_fraction", "subset_fraction"):
            check_fraction(owner, name, getattr(self, name))
        for name in ("learning_rate", "fine_tune_learning_rate", "max_start_deg"):
            check_number(owner, name, getattr(self, name), gt=0)
        check_int(owner, "fine_tune_steps", self.fine_tune_steps, minimum=0)
        if self.fine_tune_steps >= self.steps:
            raise ConfigFieldError(
                owner,
                "fine_tune_steps",
                f"< steps ({self.steps}; 0 for one phase)",
                self.fine_tune_steps,
            )
        for name in ("start_shift_mm", "score_weight", "coords_weight"):
            check_number(owner, name, getattr(self, name), ge=0)
        check_int(owner, "seed", self.seed)
        check_int(owner, "fine_tune_seed", self.fine_tune_seed, allow_none=True)
        check_instance(owner, "stacks", self.stacks, TrainingStackConfig)

    @property
    def turn(self) -> int:
        """The first step of the second phase (``steps`` without one)."""
        return self.steps - self.fine_tune_steps

    @property
    def second_phase_is_new_run(self) -> bool:
        """Whether the second phase runs as a separate fine-tuning run (``fine_tune_seed``)."""
        return self.fine_tune_seed is not None and self.fine_tune_steps > 0


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
        volume = volumes[index]
        stack = simulate_training_stack(volume, config.stacks, generator, trajectories)
        blocks, starts, target, labels = draw_samples(stack, model_config, config, generator)
        batch.append((blocks, starts, target.expand_as(starts), labels))
    blocks, starts, targets, labels = (torch.cat(parts) for parts in zip(*batch, strict=True))
    return blocks, starts, targets, labels


def step_seed(seed: int, step: int) -> int:
    """The seed of step ``step``'s simulation when stacks are simulated by worker processes."""
    return (seed * 1_000_003 + step) % (2**63)


_Brains = tuple[list[CanonicalVolume], Tensor | None]
"""A phase's training brains and their draw weights (``None``: alike)."""


def _draw_weights(weights: Sequence[float] | None, count: int, name: str) -> Tensor:
    """``weights`` as a (count,) float64 tensor (ones for ``None``), checked."""
    if weights is None:
        return torch.ones(count, dtype=torch.float64)
    values = torch.as_tensor(list(weights), dtype=torch.float64)
    if values.shape != (count,) or not bool(torch.all(values > 0)):  # NaN fails too
        raise ValueError(
            f"train_stack_pose(): {name!r} must be {count} numbers > 0 (one per brain), got "
            f"{list(weights)!r}"
        )
    return values


class _StepBatches(Dataset):
    """Step ``i``'s batch, simulated from a generator seeded by :func:`step_seed`.

    ``phases`` are the training brains (with their draw weights, :func:`simulate_batch`) before
    and from step ``turn`` on; with the config's ``fine_tune_seed`` the steps from ``turn`` on
    are seeded as a separate run's steps 0, 1, ...
    """

    def __init__(
        self,
        phases: tuple[_Brains, _Brains],
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


def _one_thread(_worker: int) -> None:
    torch.set_num_threads(1)  # the workers share the cores; one thread each simulates fastest


def _check_arguments(
    volumes: list[CanonicalVolume],
    workers: int,
    model_config: StackPoseConfig,
    config: StackPoseTrainingConfig,
) -> None:
    """Refuse arguments :func:`train_stack_pose` cannot train with (ValueError naming them)."""
    if not volumes:
        raise ValueError("train_stack_pose(): 'volumes' is empty")
    if not (is_integer(workers) and workers >= 0):
        raise ValueError(f"train_stack_pose(): 'workers' must be an int >= 0, got {workers!r}")
    if model_config.hidden_norm and config.stacks_per_step * config.samples_per_stack < 2:
        raise ValueError(
            "train_stack_pose(): 'config' must give >= 2 blocks per step (stacks_per_step x "
            "samples_per_stack) for the hidden layer's batch normalisation, got "
            f"{config.stacks_per_step} x {config.samples_per_stack}"
        )


def _phases(
    volumes: list[CanonicalVolume],
    extra: list[CanonicalVolume],
    volume_weights: Sequence[float] | None,
    fine_tune_weights: Sequence[float] | None,
    config: StackPoseTrainingConfig,
) -> tuple[_Brains, _Brains]:
    """The brains (and draw weights) before the turn to the second phase and from it on.

    Without a second phase both are every brain. The weights are ``None`` (every brain alike,
    the draws made before weights existed) unless either list is given.

    Raises:
        ValueError: If a weights list does not match its brains or has a weight not > 0.
    """
    first_weights = _draw_weights(volume_weights, len(volumes), "volume_weights")
    extra_weights = _draw_weights(fine_tune_weights, len(extra), "fine_tune_weights")
    weighted = volume_weights is not None or fine_tune_weights is not None
    every: _Brains = (
        [*volumes, *extra],
        torch.cat([first_weights, extra_weights]) if weighted else None,
    )
    first: _Brains = (volumes, first_weights if weighted else None)
    return (first if config.fine_tune_steps else every, every)


def _batches(
    phases: tuple[_Brains, _Brains],
    trajectories: list[Trajectory] | None,
    model_config: StackPoseConfig,
    config: StackPoseTrainingConfig,
    generator: torch.Generator,
    start: int,
    workers: int,
    device: str | torch.device,
) -> Iterable[tuple[Tensor, ...]]:
    """The batches of steps ``start, ..., steps - 1``.

    With no workers they are simulated lazily in this process from ``generator`` (reseeded at
    the turn when the second phase is a new run, as the step's batch is drawn: after the last
    checkpoint of the first phase), else by worker processes from each step's own seed.
    """
    turn = config.turn
    if workers == 0:

        def stream() -> Iterator[tuple[Tensor, ...]]:
            for step in range(start, config.steps):
                if config.second_phase_is_new_run and step == turn:
                    assert config.fine_tune_seed is not None
                    generator.manual_seed(config.fine_tune_seed)
                brains, weights = phases[step >= turn]
                yield simulate_batch(brains, trajectories, model_config, config, generator, weights)

        return stream()
    return DataLoader(
        _StepBatches(phases, turn, trajectories, model_config, config),
        batch_size=None,
        sampler=range(start, config.steps),
        num_workers=workers,
        worker_init_fn=_one_thread,
        prefetch_factor=4,
        pin_memory=torch.device(device).type == "cuda",
    )


def _optimisation(
    model_config: StackPoseConfig,
    config: StackPoseTrainingConfig,
    init: dict[str, Tensor] | None,
    device: str | torch.device,
) -> tuple[StackPoseNet, torch.optim.Adam, torch.optim.lr_scheduler.LambdaLR]:
    """The network (initialised from the global RNG, or from ``init``), Adam and its schedule.

    With a second phase the schedule restarts at the turn: at ``fine_tune_learning_rate`` for a
    warm restart, or at the full rate when the second phase is a new run, whose own base rate
    :func:`~svr.models.resume.restart_as_new_run` sets at the turn.
    """
    net = StackPoseNet(model_config)
    if init is not None:
        net.load_state_dict(init)
    net = net.to(device)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.learning_rate)
    schedule = cosine_schedule(
        optimiser,
        config.steps,
        restart_at=config.turn if config.fine_tune_steps else None,
        restart_scale=1.0
        if config.second_phase_is_new_run
        else config.fine_tune_learning_rate / config.learning_rate,
    )
    return net, optimiser, schedule


def _train_step(
    net: StackPoseNet,
    optimiser: torch.optim.Optimizer,
    schedule: torch.optim.lr_scheduler.LRScheduler,
    batch: tuple[Tensor, ...],
    config: StackPoseTrainingConfig,
    device: str | torch.device,
) -> dict[str, float]:
    """One optimisation step on ``(blocks, starts, targets, labels)``; the loss's parts."""
    blocks, starts, targets, labels = (part.to(device) for part in batch)
    loss, parts = stack_pose_loss(
        net(blocks),
        starts,
        targets,
        labels,
        config,
        getattr(net, "cells", None),
        net.config.representation,
    )
    optimiser.zero_grad()
    loss.backward()
    optimiser.step()
    schedule.step()
    return parts


def _log_progress(done: int, steps: int, sums: dict[str, float], count: int, rate: float) -> None:
    """Log the mean losses since the last checkpoint and the steps per second."""
    means = " ".join(f"{k} {v / max(count, 1):.4f}" for k, v in sums.items())
    log.info("step %d/%d %s (%.2f steps/s)", done, steps, means, rate)


def train_stack_pose(
    volumes: list[CanonicalVolume],
    trajectories: list[Trajectory] | None,
    model_config: StackPoseConfig,
    config: StackPoseTrainingConfig,
    folder: str | Path | None = None,
    progress: bool = False,
    time_limit_s: float | None = None,
    extra_config: dict | None = None,
    device: str | torch.device = "cpu",
    init: dict[str, Tensor] | None = None,
    workers: int = 0,
    fine_tune_volumes: list[CanonicalVolume] | None = None,
    volume_weights: Sequence[float] | None = None,
    fine_tune_weights: Sequence[float] | None = None,
) -> StackPoseNet:
    """Train (or resume training) the stack-pose network.

    Args:
        volumes: Training brains in canonical space.
        trajectories: Real motion recordings (``None``: random walks).
        model_config: The network.
        config: The training.
        folder: Where ``step_NNNNNNNNN`` checkpoints go (the newest is resumed); ``None`` for none.
        progress: Log the losses at every checkpoint.
        time_limit_s: Stop (after a checkpoint) once this much wall time has passed.
        extra_config: More JSON fields for the checkpoint's config (e.g. the training data).
        device: Where the network trains (stacks are simulated on the CPU).
        init: Weights to start from (fine-tuning a trained network with a new schedule), used
            when ``folder`` holds no checkpoint yet; ``None`` starts from random weights.
        workers: Processes that simulate the stacks. 0 (the shipped recipe) simulates them in
            this process from one random stream, saved in the checkpoints; N >= 1 simulates each
            step's stacks in one of N worker processes from a generator seeded by the seed and
            the step (:func:`step_seed`), so the run is the same for every N >= 1 and resumes
            exactly, but differs from a run with 0. Use them where simulation is the bottleneck
            (a GPU, or a machine with spare cores).
        fine_tune_volumes: Brains that join ``volumes`` for the last ``config.fine_tune_steps``
            steps (the procedural phantoms), or for every step if that is 0; ``None`` for none.
        volume_weights: Relative chance of each of ``volumes`` being drawn for a stack (> 0 each);
            ``None``: 1 each.
        fine_tune_weights: The same for ``fine_tune_volumes``, on the scale of
            ``volume_weights``; ``None``: 1 each. With neither, every brain is drawn alike, as
            before these existed (the same stream of draws).

    Returns:
        The network (eval mode).

    Raises:
        ValueError: If ``volumes`` is empty, ``workers`` is negative, a weights list does not
            match its brains or has a weight that is not > 0, or a step has a single block for
            a network with ``hidden_norm``.
    """
    _check_arguments(volumes, workers, model_config, config)
    phases = _phases(volumes, fine_tune_volumes or [], volume_weights, fine_tune_weights, config)
    torch.manual_seed(config.seed)  # the weights' initialisation
    generator = torch.Generator().manual_seed(config.seed)
    net, optimiser, schedule = _optimisation(model_config, config, init, device)
    start = resume_training(folder, net, optimiser, schedule, generator, device)
    batches = _batches(
        phases, trajectories, model_config, config, generator, start, workers, device
    )
    saved_config = {
        "architecture": "stack_pose",
        "model": model_config.to_dict(),
        "train": asdict(config),
        **(extra_config or {}),
    }
    net.train()
    sums: dict[str, float] = {}
    count = 0
    began = time.time()
    for step, batch in zip(range(start, config.steps), batches, strict=True):
        if config.second_phase_is_new_run and step == config.turn:
            restart_as_new_run(optimiser, schedule, config.fine_tune_learning_rate)
        parts = _train_step(net, optimiser, schedule, batch, config, device)
        for key, value in parts.items():
            sums[key] = sums.get(key, 0.0) + value
        count += 1
        done = step + 1
        out_of_time = time_limit_s is not None and time.time() - began > time_limit_s
        if done % config.checkpoint_every == 0 or done == config.steps or out_of_time:
            if progress:
                rate = (done - start) / (time.time() - began)
                _log_progress(done, config.steps, sums, count, rate)
            sums, count = {}, 0
            if folder is not None:
                save_training_checkpoint(
                    folder, done, net, optimiser, schedule, generator, saved_config
                )
            if out_of_time:
                break
    return net.eval()
