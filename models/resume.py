"""What every resumable training loop of the project shares: the schedule, resuming, checkpoints.

The slice-pose loop (:func:`svr.models.train.train`), the stack-pose loop
(:func:`svr.models.stack_pose_train.train_stack_pose`) and the brain-mask loop
(:func:`svr.masking.train.train_network`) all checkpoint and resume through this module. A run
folder holds ``step_NNNNNNNNN`` checkpoints (:mod:`svr.models.checkpoint`) with the weights, the
config and a training state: the optimiser's and schedule's state dicts, the step and, where the
loop has them, the data generator's RNG state (``"generator"``; a loop whose batches are addressed
by the step, as the slice-pose loop's are, has none: the step is its data stream's state) and the
mixed-precision loss scaler's state (``"scaler"``). :func:`resume_training` restores all of it
from the newest complete checkpoint, so a run stopped at any point and started again continues as
if it had not stopped; :func:`save_training_checkpoint` writes one atomically and keeps the
newest few.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch
from torch import nn

from svr.errors import CheckpointError
from svr.models.checkpoint import (
    checkpoint_name,
    latest_checkpoint,
    load_checkpoint,
    prune_checkpoints,
    save_checkpoint,
)

__all__ = [
    "cosine_schedule",
    "restart_as_new_run",
    "resume_training",
    "save_training_checkpoint",
]

log = logging.getLogger(__name__)


def cosine_schedule(
    optimiser: torch.optim.Optimizer,
    steps: int,
    floor: float = 0.05,
    restart_at: int | None = None,
    restart_scale: float = 1.0,
) -> torch.optim.lr_scheduler.LambdaLR:
    """Cosine decay of the learning rate from its initial value to ``floor`` of it in ``steps``.

    With ``restart_at`` the decay is a warm restart (Loshchilov & Hutter, SGDR): the first
    ``restart_at`` steps decay from the initial rate to ``floor`` of it, then the rate jumps to
    ``restart_scale`` times the initial rate and decays again to ``floor`` of that at ``steps``.

    Args:
        optimiser: The optimiser whose initial rate is scaled.
        steps: Length of the whole schedule, >= 1.
        floor: Final share of each phase's starting rate.
        restart_at: Step of the warm restart, 0 < restart_at < steps; ``None`` for none.
        restart_scale: The restart's rate as a share of the initial rate, > 0.

    Raises:
        ValueError: If ``restart_at`` is not inside the schedule or ``restart_scale`` <= 0.
    """

    def cosine(s: float, length: int) -> float:
        return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(s / length, 1.0)))

    if restart_at is None:
        return torch.optim.lr_scheduler.LambdaLR(optimiser, lambda s: cosine(s, steps))
    if not (isinstance(restart_at, int) and 0 < restart_at < steps):
        raise ValueError(
            f"cosine_schedule(): 'restart_at' must be an int in (0, {steps}), got {restart_at!r}"
        )
    if not restart_scale > 0:
        raise ValueError(f"cosine_schedule(): 'restart_scale' must be > 0, got {restart_scale!r}")
    return torch.optim.lr_scheduler.LambdaLR(
        optimiser,
        lambda s: (
            cosine(s, restart_at)
            if s < restart_at
            else restart_scale * cosine(s - restart_at, steps - restart_at)
        ),
    )


def restart_as_new_run(
    optimiser: torch.optim.Optimizer, schedule: torch.optim.lr_scheduler.LambdaLR, rate: float
) -> None:
    """Make the optimiser and its schedule those of a new run from here, in place.

    The optimiser's state (Adam's moments and step counts) is cleared and ``rate`` becomes the
    base rate that the schedule's factor multiplies (a :func:`cosine_schedule` with a warm
    restart here and ``restart_scale`` 1 continues as the new run's own cosine).

    Args:
        optimiser: The optimiser (its state cleared, its rates set).
        schedule: Its schedule (base rates replaced).
        rate: The new run's initial learning rate, > 0.
    """
    optimiser.state.clear()
    schedule.base_lrs = [rate] * len(optimiser.param_groups)
    for group, function in zip(optimiser.param_groups, schedule.lr_lambdas, strict=True):
        group["initial_lr"] = rate
        group["lr"] = rate * function(schedule.last_epoch)


def resume_training(
    folder: str | Path | None,
    net: nn.Module,
    optimiser: torch.optim.Optimizer,
    schedule: torch.optim.lr_scheduler.LRScheduler,
    generator: torch.Generator | None,
    device: str | torch.device = "cpu",
    *,
    scaler: torch.amp.GradScaler | None = None,
) -> int:
    """Restore a run from the newest checkpoint in ``folder`` (created if missing).

    Args:
        folder: The run folder, or ``None`` for a run without checkpoints (or one that starts
            afresh).
        net: The network (its weights are replaced).
        optimiser: Its optimiser (state replaced).
        schedule: Its learning-rate schedule (state replaced).
        generator: The data generator (state replaced), or ``None`` for a loop whose batches
            are addressed by the step.
        device: Where the weights and optimiser state go.
        scaler: The mixed-precision loss scaler (state replaced), or ``None`` for none.

    Returns:
        The step to continue from (0 for a new run).

    Raises:
        CheckpointError: If ``folder`` is a file, or the newest checkpoint lacks a state that the
            run has (a generator or scaler state) or cannot be read.
    """
    if folder is None:
        return 0
    newest = latest_checkpoint(folder)  # (first: a file in the folder's place is named)
    Path(folder).mkdir(parents=True, exist_ok=True)
    if newest is None:
        return 0
    checkpoint = load_checkpoint(newest, device, with_training_state=True)
    state = checkpoint.training_state
    assert state is not None  # loaded with_training_state
    for name, holder in (("generator", generator), ("scaler", scaler)):
        if holder is not None and name not in state:
            raise CheckpointError(newest, f"its training state has no {name!r} state to resume")
    net.load_state_dict(checkpoint.state_dict)
    optimiser.load_state_dict(state["optimizer"])
    schedule.load_state_dict(state["scheduler"])
    if generator is not None:
        generator.set_state(state["generator"])
    if scaler is not None:
        scaler.load_state_dict(state["scaler"])
    start = int(state["step"])
    log.info("resuming from %s (step %d)", newest, start)
    return start


def save_training_checkpoint(
    folder: str | Path,
    step: int,
    net: nn.Module,
    optimiser: torch.optim.Optimizer,
    schedule: torch.optim.lr_scheduler.LRScheduler,
    generator: torch.Generator | None,
    config: dict[str, Any],
    *,
    scaler: torch.amp.GradScaler | None = None,
    keep: int = 2,
) -> Path:
    """Write the checkpoint after ``step`` steps into ``folder`` and keep the newest ``keep``.

    A checkpoint of the same step already there (one of an earlier run that this one replaces,
    or an incomplete one) is replaced atomically.

    Args:
        folder: The run folder (it must exist: :func:`resume_training` creates it).
        step: Steps done.
        net: The network (weights saved as CPU copies).
        optimiser: Its optimiser.
        schedule: Its schedule.
        generator: The data generator, or ``None`` (batches addressed by the step).
        config: The checkpoint's JSON config (architecture, model, training).
        scaler: The mixed-precision loss scaler, or ``None``.
        keep: How many of the newest complete checkpoints to keep, >= 1.

    Returns:
        The checkpoint folder.
    """
    state: dict[str, Any] = {
        "optimizer": optimiser.state_dict(),
        "scheduler": schedule.state_dict(),
    }
    if generator is not None:
        state["generator"] = generator.get_state()
    if scaler is not None:
        state["scaler"] = scaler.state_dict()
    state["step"] = step
    path = save_checkpoint(
        Path(folder) / checkpoint_name(step),
        net.state_dict(),
        config,
        training_state=state,
        overwrite=True,
    )
    prune_checkpoints(folder, keep=keep)
    return path
