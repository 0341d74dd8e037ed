"""What every resumable training loop of the project shares: the schedule, resuming, checkpoints.

A run folder holds ``step_NNNNNNNNN`` checkpoints (:mod:`svr.models.checkpoint`) with the weights,
the config and a training state: the optimiser's and schedule's state dicts, the data generator's
RNG state and the step. :func:`resume_training` restores all of it from the newest complete
checkpoint, so a run stopped at any point and started again continues as if it had not stopped;
:func:`save_training_checkpoint` writes one atomically and keeps the newest two.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch
from torch import nn

from svr.models.checkpoint import (
    checkpoint_name,
    latest_checkpoint,
    load_checkpoint,
    prune_checkpoints,
    save_checkpoint,
)

__all__ = ["cosine_schedule", "resume_training", "save_training_checkpoint"]

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


def resume_training(
    folder: str | Path | None,
    net: nn.Module,
    optimiser: torch.optim.Optimizer,
    schedule: torch.optim.lr_scheduler.LRScheduler,
    generator: torch.Generator,
    device: str | torch.device = "cpu",
) -> int:
    """Restore a run from the newest checkpoint in ``folder`` (created if missing).

    Args:
        folder: The run folder, or ``None`` for a run without checkpoints.
        net: The network (its weights are replaced).
        optimiser: Its optimiser (state replaced).
        schedule: Its learning-rate schedule (state replaced).
        generator: The data generator (state replaced).
        device: Where the weights and optimiser state go.

    Returns:
        The step to continue from (0 for a new run).
    """
    if folder is None:
        return 0
    Path(folder).mkdir(parents=True, exist_ok=True)
    newest = latest_checkpoint(folder)
    if newest is None:
        return 0
    checkpoint = load_checkpoint(newest, device, with_training_state=True)
    assert checkpoint.training_state is not None
    net.load_state_dict(checkpoint.state_dict)
    optimiser.load_state_dict(checkpoint.training_state["optimizer"])
    schedule.load_state_dict(checkpoint.training_state["scheduler"])
    generator.set_state(checkpoint.training_state["generator"])
    start = int(checkpoint.training_state["step"])
    log.info("resuming from %s (step %d)", newest, start)
    return start


def save_training_checkpoint(
    folder: str | Path,
    step: int,
    net: nn.Module,
    optimiser: torch.optim.Optimizer,
    schedule: torch.optim.lr_scheduler.LRScheduler,
    generator: torch.Generator,
    config: dict[str, Any],
) -> Path:
    """Write the checkpoint after ``step`` steps into ``folder`` and keep the newest two.

    Args:
        folder: The run folder.
        step: Steps done.
        net: The network (weights saved as CPU copies).
        optimiser: Its optimiser.
        schedule: Its schedule.
        generator: The data generator.
        config: The checkpoint's JSON config (architecture, model, training).

    Returns:
        The checkpoint folder.
    """
    state = {
        "optimizer": optimiser.state_dict(),
        "scheduler": schedule.state_dict(),
        "generator": generator.get_state(),
        "step": step,
    }
    path = save_checkpoint(
        Path(folder) / checkpoint_name(step),
        {k: v.cpu() for k, v in net.state_dict().items()},
        config,
        training_state=state,
    )
    prune_checkpoints(folder, keep=2)
    return path
