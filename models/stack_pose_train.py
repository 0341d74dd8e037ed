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
weights would (a fresh Adam, the random stream reseeded), so two commands become one. With
``synthesis`` a share of the stacks (``synthesis_fraction``) is simulated from a synthetic copy
of its brain (:mod:`svr.sampling.synthesis`: the brain's tissue labels with a random contrast,
texture, bias, blur and noise), so that the network learns the brain's shape rather than one atlas
family's contrast. The batches are made in :mod:`svr.models.stack_pose_batches`. Checkpoints
(:mod:`svr.models.checkpoint`) are written every ``checkpoint_every`` steps and the newest is
resumed, with the RNG state, so a run that is stopped and started again continues where it was.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import DataLoader

from svr.models.resume import (
    cosine_schedule,
    restart_as_new_run,
    resume_training,
    save_training_checkpoint,
)
from svr.models.stack_pose import StackPoseConfig, StackPoseNet
from svr.models.stack_pose_batches import Brains, StepBatches, simulate_batch
from svr.models.stack_pose_loss import stack_pose_loss
from svr.models.stack_pose_train_config import StackPoseTrainingConfig
from svr.sampling.motion import Trajectory
from svr.sampling.volume import CanonicalVolume
from svr.validation import is_integer

__all__ = ["StackPoseTrainingConfig", "train_stack_pose"]

log = logging.getLogger(__name__)


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
) -> tuple[Brains, Brains]:
    """The brains (and draw weights) before the turn to the second phase and from it on.

    Without a second phase both are every brain. The weights are ``None`` (every brain alike,
    the draws made before weights existed) unless either list is given.

    Raises:
        ValueError: If a weights list does not match its brains or has a weight not > 0.
    """
    first_weights = _draw_weights(volume_weights, len(volumes), "volume_weights")
    extra_weights = _draw_weights(fine_tune_weights, len(extra), "fine_tune_weights")
    weighted = volume_weights is not None or fine_tune_weights is not None
    every: Brains = (
        [*volumes, *extra],
        torch.cat([first_weights, extra_weights]) if weighted else None,
    )
    first: Brains = (volumes, first_weights if weighted else None)
    return (first if config.fine_tune_steps else every, every)


def _batches(
    phases: tuple[Brains, Brains],
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
        StepBatches(phases, turn, trajectories, model_config, config),
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
