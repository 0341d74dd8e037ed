"""Training slice-pose networks: the loop behind ``svr train``.

Data: :class:`svr.sampling.dataset.SliceStream` batches (random poses) or
:class:`svr.sampling.dataset.EulerGridStream` batches (the shuffled Euler grid,
``TrainConfig.pose_sampling="grid"``) are addressed by index, so step ``s`` always trains on the
same batch whatever the interruptions: a run resumed from its latest checkpoint
continues exactly as if it had not stopped (up to floating-point nondeterminism of the device).

Outputs in ``output_dir``: ``checkpoints/step_NNNNNNNNN/`` (:mod:`svr.models.checkpoint`; the newest
``keep_checkpoints`` are kept), ``log.csv`` and TensorBoard event files
(:mod:`svr.models.training_log`), and ``train_config.json``.

Distributed data-parallel training: launched with ``torchrun --nproc_per_node N``, each process
takes every N-th batch (``gloo`` on the CPU, ``nccl`` on CUDA); rank 0 writes the outputs.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, cast, get_args

import torch
import torch.distributed as dist
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from svr.errors import ConfigFieldError
from svr.files import OutputExistsError
from svr.models.checkpoint import checkpoint_name, latest_checkpoint
from svr.models.network import ModelConfig, build_model, checkpoint_model_config, loss_function
from svr.models.resume import resume_training, save_training_checkpoint
from svr.models.training_log import TrainingLog
from svr.sampling.dataset import EulerGridStream, SliceDatasetConfig, SliceStream
from svr.sampling.poses import DEFAULT_EULER_GRID, EulerGridConfig
from svr.sampling.volume import CanonicalVolume
from svr.validation import (
    check_bool,
    check_choice,
    check_instance,
    check_instance_tuple,
    check_int,
    check_number,
    check_number_tuple,
    check_str,
)

log = logging.getLogger(__name__)

OptimizerName = Literal["adamw", "sgd"]
"""The optimisers of :class:`OptimConfig`."""
Schedule = Literal["cosine", "constant"]
"""The learning-rate schedules of :class:`OptimConfig`."""
PoseSampling = Literal["random", "grid"]
"""How :class:`TrainConfig` draws the poses of its slices."""


@dataclass(frozen=True)
class OptimConfig:
    """Optimiser and learning-rate schedule.

    Attributes:
        name: ``"adamw"`` or ``"sgd"`` (with Nesterov momentum 0.9).
        lr: Peak learning rate, > 0.
        weight_decay: Decoupled weight decay, >= 0.
        schedule: ``"cosine"`` (to 0 at the last step) or ``"constant"``, after a linear warm-up.
        warmup_steps: Linear warm-up steps, >= 0.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    name: OptimizerName = "adamw"
    lr: float = 1e-3
    weight_decay: float = 1e-4
    schedule: Schedule = "cosine"
    warmup_steps: int = 100

    def __post_init__(self) -> None:
        owner = "OptimConfig"
        check_choice(owner, "name", self.name, get_args(OptimizerName))
        check_number(owner, "lr", self.lr, gt=0)
        check_number(owner, "weight_decay", self.weight_decay, ge=0)
        check_choice(owner, "schedule", self.schedule, get_args(Schedule))
        check_int(owner, "warmup_steps", self.warmup_steps, minimum=0)


@dataclass(frozen=True)
class TrainConfig:
    """A training run.

    Attributes:
        output_dir: Folder of checkpoints and logs.
        model: Architecture and output representation.
        data: Slices and augmentation; its ``representation`` must be the model's.
        optim: Optimiser and schedule.
        steps: Optimisation steps, >= 1.
        metric_weights: For the SE(3) loss, Z as 6 (diagonal) or 36 (row-major 6x6) numbers;
            ``None``: the default Z.
        checkpoint_every: Steps between checkpoints, >= 1 (a last one is always written).
        keep_checkpoints: How many checkpoints to keep, >= 1.
        log_every: Steps between log lines, >= 1.
        workers: ``DataLoader`` worker processes (0: batches made in the main process).
        device: Torch device.
        amp: Mixed precision (float16 autocast with loss scaling); CUDA only.
        seed: Seed of the weight initialisation.
        data_sources: Names of the training volumes, recorded in checkpoints.
        pose_sampling: ``"random"``: random poses drawn per batch
            (:class:`~svr.sampling.dataset.SliceStream`);
            ``"grid"``: the Euler-grid poses of every volume, shuffled
            (:class:`~svr.sampling.dataset.EulerGridStream`; needs ``data.rotation == "euler"``, and
            ``data.angle_range_deg`` and ``data.tz_range_mm`` are replaced by ``grid``'s).
        grid: The Euler grid of ``pose_sampling="grid"`` (default: the paper's).
        symmetry_report: How ``model.symmetry_planes`` were chosen
            (:func:`svr.sampling.mirror_planes.resolve_symmetry`), recorded in checkpoints.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range, or for settings that disagree (named by their path, e.g.
            ``data.representation``).
    """

    output_dir: str
    model: ModelConfig = field(default_factory=ModelConfig)
    data: SliceDatasetConfig = field(default_factory=SliceDatasetConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    steps: int = 1000
    metric_weights: tuple[float, ...] | None = None
    checkpoint_every: int = 500
    keep_checkpoints: int = 3
    log_every: int = 10
    workers: int = 0
    device: str = "cpu"
    amp: bool = False
    seed: int = 0
    data_sources: tuple[str, ...] = ()
    pose_sampling: PoseSampling = "random"
    grid: EulerGridConfig = DEFAULT_EULER_GRID
    symmetry_report: dict | None = None

    def __post_init__(self) -> None:
        owner = "TrainConfig"
        check_str(owner, "output_dir", self.output_dir)
        check_instance(owner, "model", self.model, ModelConfig)
        check_instance(owner, "data", self.data, SliceDatasetConfig)
        check_instance(owner, "optim", self.optim, OptimConfig)
        for name in ("steps", "checkpoint_every", "keep_checkpoints", "log_every"):
            check_int(owner, name, getattr(self, name), minimum=1)
        weights = check_number_tuple(
            owner,
            "metric_weights",
            self.metric_weights,
            length=(6, 36),
            allow_list=True,
            allow_none=True,
        )
        check_int(owner, "workers", self.workers, minimum=0)
        check_str(owner, "device", self.device)
        check_bool(owner, "amp", self.amp)
        check_int(owner, "seed", self.seed)
        sources = check_instance_tuple(
            owner, "data_sources", self.data_sources, str, allow_list=True
        )
        check_choice(owner, "pose_sampling", self.pose_sampling, get_args(PoseSampling))
        check_instance(owner, "grid", self.grid, EulerGridConfig)
        check_instance(owner, "symmetry_report", self.symmetry_report, dict, allow_none=True)
        if self.pose_sampling == "grid" and self.data.rotation != "euler":
            raise ConfigFieldError(
                owner, "data.rotation", "'euler' for grid pose sampling", self.data.rotation
            )
        if self.data.representation != self.model.representation:
            raise ConfigFieldError(
                owner,
                "data.representation",
                f"equal to 'model.representation' ({self.model.representation!r})",
                self.data.representation,
            )
        if weights is not None and self.model.representation != "se3":
            raise ConfigFieldError(
                owner, "metric_weights", "None unless the representation is 'se3'", weights
            )
        object.__setattr__(self, "metric_weights", weights)
        object.__setattr__(self, "data_sources", sources)

    def weights_tensor(self) -> Tensor | None:
        """Z as a (6,) or (6, 6) float32 tensor, or ``None``."""
        if self.metric_weights is None:
            return None
        z = torch.tensor(self.metric_weights, dtype=torch.float32)
        return z if z.numel() == 6 else z.reshape(6, 6)

    def to_dict(self) -> dict:
        """A JSON-serialisable description of the run."""
        d = asdict(self)
        d["model"] = self.model.to_dict()
        return d


@dataclass(frozen=True)
class TrainResult:
    """The outcome of :func:`train`: the final checkpoint and the last logged loss."""

    checkpoint: Path
    last_loss: float
    steps_done: int


class _StepBatches(Dataset):
    """Map-style view of a stream's batches ``start, start + stride, ...`` (one per step)."""

    def __init__(self, stream: SliceStream, steps: Sequence[int]) -> None:
        self.stream = stream
        self.steps = list(steps)

    def __len__(self) -> int:
        return len(self.steps)

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return self.stream.batch(self.steps[i])


def _schedule(config: OptimConfig, steps: int) -> Callable[[int], float]:
    def factor(step: int) -> float:
        if step < config.warmup_steps:
            return (step + 1) / config.warmup_steps
        if config.schedule == "constant":
            return 1.0
        progress = (step - config.warmup_steps) / max(1, steps - config.warmup_steps)
        return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))

    return factor


def _optimizer(model: nn.Module, config: OptimConfig) -> torch.optim.Optimizer:
    if config.name == "sgd":
        return torch.optim.SGD(
            model.parameters(),
            lr=config.lr,
            momentum=0.9,
            nesterov=True,
            weight_decay=config.weight_decay,
        )
    return torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)


def _distributed() -> tuple[int, int]:
    """(rank, world size), initialising the process group when launched by torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    return (dist.get_rank(), world) if world > 1 else (0, 1)


def train_step(
    net: nn.Module,
    criterion: Callable[[Tensor, Tensor], Tensor],
    optimizer: torch.optim.Optimizer,
    scaler: torch.amp.GradScaler,
    slices: Tensor,
    labels: Tensor,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
) -> Tensor:
    """One optimisation step, as :func:`train` takes it.

    The forward pass runs under float16 autocast on ``slices``' device type when ``scaler`` is
    enabled (mixed precision); the loss is computed in float32 on the outputs, the gradients are
    cleared, and the scaled loss is back-propagated; then ``scaler`` steps ``optimizer`` (skipping
    the step if the gradients overflowed) and updates its scale, and ``scheduler``, if given,
    advances the learning rate by one step.

    Args:
        net: The model in training mode (or its ``DistributedDataParallel`` wrapper).
        criterion: The loss: (B, D) float32 outputs and labels -> scalar.
        optimizer: The optimiser of ``net``'s parameters.
        scaler: The loss scaler; a disabled one (``enabled=False``) makes this a plain float32
            step.
        slices: (B, 1, H, W) input slices, on ``net``'s device.
        labels: The batch's labels in the model's representation, on the same device.
        scheduler: The learning-rate schedule, stepped once per step, or ``None``.

    Returns:
        The loss (scalar, detached; on the device, not synchronised).
    """
    with torch.autocast(slices.device.type, dtype=torch.float16, enabled=scaler.is_enabled()):
        outputs = net(slices)
    loss = criterion(outputs.float(), labels)
    optimizer.zero_grad(set_to_none=True)
    scaler.scale(loss).backward()
    scaler.step(optimizer)
    scaler.update()
    if scheduler is not None:
        scheduler.step()
    return loss.detach()


def checkpoint_config(config: TrainConfig, step: int) -> dict:
    """The JSON config stored with a checkpoint (what a predictor needs, and provenance)."""
    return {
        **checkpoint_model_config(config.model),
        "metric_weights": None if config.metric_weights is None else list(config.metric_weights),
        **({"symmetry": config.symmetry_report} if config.symmetry_report else {}),
        "training": {
            "step": step,
            "steps": config.steps,
            "data_sources": list(config.data_sources),
            "run": config.to_dict(),
        },
    }


def _refuse_restart(out: Path, checkpoints: Path, resume: bool, overwrite: bool) -> None:
    """Refuse to start a run afresh over an earlier one unless ``overwrite`` allows it.

    Raises:
        OutputExistsError: If ``checkpoints`` holds a checkpoint and neither ``resume`` nor
            ``overwrite`` is set.
    """
    if not resume and not overwrite and latest_checkpoint(checkpoints) is not None:
        raise OutputExistsError(
            out, "holds checkpoints of an earlier run (resume it, or allow overwriting)"
        )


def _step_batches(
    config: TrainConfig,
    volumes: Sequence[CanonicalVolume],
    device: torch.device,
    start: int,
    rank: int,
    world: int,
) -> _StepBatches:
    """The batches this process trains on from step ``start``: every ``world``-th, from ``rank``.

    With no worker processes the volumes move to ``device`` (batches are made there); worker
    processes make them on the CPU.
    """
    sources = [v.to(device) for v in volumes] if config.workers == 0 else volumes
    if config.pose_sampling == "grid":
        stream: SliceStream = EulerGridStream(sources, config.data, config.grid)
    else:
        stream = SliceStream(sources, config.data)
    return _StepBatches(stream, range(start * world + rank, config.steps * world, world))


def _log_line(
    log_file: TrainingLog,
    step: int,
    loss: float,
    scheduler: torch.optim.lr_scheduler.LRScheduler,
    images: int,
    seconds: float,
) -> None:
    """Write step ``step``'s loss, learning rate and throughput (``images`` in ``seconds``)."""
    log_file.write(
        step,
        loss=loss,
        lr=cast("float", scheduler.get_last_lr()[0]),  # the optimiser's lr is a float
        images_per_s=images / seconds,
    )


def train(
    config: TrainConfig,
    volumes: Sequence[CanonicalVolume],
    *,
    resume: bool = True,
    overwrite: bool = False,
    progress: bool = True,
) -> TrainResult:
    """Train a slice-pose network, resuming from the newest checkpoint in ``output_dir``.

    Checkpoints are written and resumed by :mod:`svr.models.resume` (the training state holds
    the optimiser, schedule and loss-scaler states and the step, which addresses the batches).

    Args:
        config: The run.
        volumes: Canonical training volumes (moved to ``config.device``).
        resume: Continue from the newest complete checkpoint if there is one.
        overwrite: Start afresh even if ``output_dir`` holds checkpoints (they are kept until
            pruned by the new run).
        progress: Show a progress bar.

    Returns:
        The final checkpoint, the last loss and the number of steps done.

    Raises:
        OutputExistsError: If ``output_dir`` holds checkpoints and neither ``resume`` nor
            ``overwrite`` is set.
    """
    rank, world = _distributed()
    device = torch.device(config.device)
    out = Path(config.output_dir)
    ckpt_dir = out / "checkpoints"
    _refuse_restart(out, ckpt_dir, resume, overwrite)
    torch.manual_seed(config.seed)
    model = build_model(config.model).to(device)
    optimizer = _optimizer(model, config.optim)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, _schedule(config.optim, config.steps))
    scaler = torch.amp.GradScaler("cuda", enabled=config.amp and device.type == "cuda")
    start = resume_training(
        ckpt_dir if resume else None, model, optimizer, scheduler, None, device, scaler=scaler
    )
    net: nn.Module = model
    if world > 1:
        net = nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None
        )
    criterion = loss_function(
        config.model.representation,
        config.weights_tensor(),
        config.model.symmetry_planes,
        config.model.anchor_half_size_mm,
    )
    batches = _step_batches(config, volumes, device, start, rank, world)
    loader = DataLoader(
        batches, batch_size=None, num_workers=config.workers, persistent_workers=False
    )
    log_file = TrainingLog(out, ["loss", "lr", "images_per_s"]) if rank == 0 else None
    if rank == 0:
        ckpt_dir.mkdir(parents=True, exist_ok=True)
        (out / "train_config.json").write_text(json.dumps(config.to_dict(), indent=1) + "\n")

    model.train()
    last_loss, step, seen, tick = float("nan"), start, 0, time.perf_counter()
    bar = tqdm(
        loader, total=len(batches), initial=0, desc="train", disable=not progress or rank != 0
    )
    for step, batch in enumerate(bar, start=start + 1):
        slices = batch["slices"].to(device, non_blocking=True)
        labels = batch["labels"].to(device, non_blocking=True)
        loss = train_step(net, criterion, optimizer, scaler, slices, labels, scheduler)
        seen += slices.shape[0] * world
        if step % config.log_every == 0 or step == config.steps:
            last_loss = float(loss)
            now = time.perf_counter()
            if log_file is not None:
                _log_line(log_file, step, last_loss, scheduler, seen, now - tick)
                bar.set_postfix(loss=f"{last_loss:.4g}")
            seen, tick = 0, now
        if rank == 0 and (step % config.checkpoint_every == 0 or step == config.steps):
            save_training_checkpoint(
                ckpt_dir,
                step,
                model,
                optimizer,
                scheduler,
                None,
                checkpoint_config(config, step),
                scaler=scaler,
                keep=config.keep_checkpoints,
            )
        if world > 1 and step % config.checkpoint_every == 0:
            dist.barrier()
    if log_file is not None:
        log_file.close()
    # Rank 0 wrote it (or resumed from it, when the run had no step left).
    return TrainResult(ckpt_dir / checkpoint_name(step), last_loss, step)
