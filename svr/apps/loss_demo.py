"""Pose recovery by gradient descent with each pose loss: a self-contained demonstration.

The ``svr demo`` command draws the target poses like the paper's validation slices (extrinsic
x-y-z Euler angles uniform in [-90, 90] degrees, offsets ``Tz`` uniform in [-40, 40] mm). Every
method starts from the same initial poses (the identity rotation at the origin, i.e. a slice
through the centre, as a zero-initialised network head would predict), optimises its own output
representation with Adam, and is scored the same way: its parameters are converted back to pose
vectors and compared with the targets by :func:`svr.metrics.pose_errors`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor
from tqdm import tqdm

from svr.geometry import ANCHOR_HALF_SIZE_MM
from svr.losses import DEFAULT_LENGTH_SCALE_MM
from svr.metrics import pose_errors
from svr.representation_registry import REPRESENTATIONS, PoseRepresentation
from svr.validation import check_bool, check_int, check_number, check_str

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LossDemoConfig:
    """Settings of :func:`run_loss_demo`.

    Attributes:
        num_poses: Number of target poses, > 0 (drawn by the caller).
        steps: Adam steps per method, > 0.
        learning_rate: Adam learning rate, > 0.
        seed: Seed of the target poses.
        device: Torch device to run on.
        progress: Show a progress bar.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    num_poses: int = 512
    steps: int = 200
    learning_rate: float = 0.05
    seed: int = 0
    device: str = "cpu"
    progress: bool = True

    def __post_init__(self) -> None:
        owner = "LossDemoConfig"
        check_int(owner, "num_poses", self.num_poses, minimum=1)
        check_int(owner, "steps", self.steps, minimum=1)
        check_number(owner, "learning_rate", self.learning_rate, gt=0)
        check_int(owner, "seed", self.seed)
        check_str(owner, "device", self.device)
        check_bool(owner, "progress", self.progress)


@dataclass(frozen=True)
class LossDemoResult:
    """Outcome of one method: medians over the poses, and the share recovered within 1° and 1 mm."""

    method: str
    median_rotation_deg: float
    median_translation_mm: float
    median_geodesic: float
    recovered_fraction: float
    seconds: float


@dataclass(frozen=True)
class _Method:
    """One loss of the demo: a registered representation with its demo output scale."""

    name: str
    to_params: Callable[[Tensor], Tensor]
    to_pose: Callable[[Tensor], Tensor]
    loss: Callable[[Tensor, Tensor], Tensor]
    scale: Tensor  # (D,) label units per optimised parameter

    def output_scale(self, like: Tensor) -> Tensor:
        return self.scale.to(dtype=like.dtype, device=like.device)


def _method(entry: PoseRepresentation) -> _Method:
    """The demo's method for a registry entry (named by its ``svr train --loss`` name).

    Every output in mm (translations, and all anchor-point coordinates) is optimised in units of
    :data:`~svr.losses.DEFAULT_LENGTH_SCALE_MM`.
    """
    a = ANCHOR_HALF_SIZE_MM
    return _Method(
        entry.cli_name,
        lambda poses: entry.encode(poses, a),
        lambda labels: entry.decode(labels, a),
        entry.loss(None, a),
        entry.output_scale(DEFAULT_LENGTH_SCALE_MM, DEFAULT_LENGTH_SCALE_MM),
    )


METHODS = tuple(_method(entry) for entry in REPRESENTATIONS.values())
"""One method per registered representation (:data:`svr.representation_registry.REPRESENTATIONS`).
"""


def run_loss_demo(config: LossDemoConfig, targets: Tensor) -> list[LossDemoResult]:
    """Recover target poses with each loss and report how close each method gets.

    Args:
        config: The settings.
        targets: (N, 6) float32 target poses, e.g. ``svr.sampling.poses.random_slice_poses``.

    Returns:
        One result per method (:data:`METHODS`), in registry order: se3, posenet, anchor, rot6d.
    """
    targets = targets.to(device=config.device, dtype=torch.float32)
    start = torch.zeros_like(targets)
    results = []
    for method in METHODS:
        labels = method.to_params(targets)
        scale = method.output_scale(labels)
        raw = (method.to_params(start) / scale).requires_grad_(True)
        optimiser = torch.optim.Adam([raw], lr=config.learning_rate)
        t0 = time.perf_counter()
        for _ in tqdm(
            range(config.steps), desc=method.name, disable=not config.progress, leave=False
        ):
            optimiser.zero_grad()
            method.loss(raw * scale, labels).backward()
            optimiser.step()
        seconds = time.perf_counter() - t0
        with torch.no_grad():
            errors = pose_errors(method.to_pose(raw * scale), targets)
        recovered = (errors["rotation_deg"] < 1.0) & (errors["translation_mm"] < 1.0)
        results.append(
            LossDemoResult(
                method=method.name,
                median_rotation_deg=errors["rotation_deg"].median().item(),
                median_translation_mm=errors["translation_mm"].median().item(),
                median_geodesic=errors["geodesic"].median().item(),
                recovered_fraction=recovered.float().mean().item(),
                seconds=seconds,
            )
        )
        log.info("%s: %d steps in %.2f s", method.name, config.steps, seconds)
    return results
