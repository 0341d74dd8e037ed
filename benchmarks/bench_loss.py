"""Forward + backward wall time of the pose losses, against ``torch.nn.functional.mse_loss``.

Run from the repository root::

    python benchmarks/bench_loss.py [--repeats 200] [--threads 2] [--device cpu|cuda|all]

For N = 64 and 4096 float32 poses (rotation vectors with angles uniform in [0, pi), translations
~ N(0, 20 mm); predictions are the targets perturbed by ~0.1 rad and ~3.5 mm), it times one
``loss(pred, target).backward()`` per repeat, after a warm-up, for: MSE on the (N, 6) pose
vectors; the SE(3) geodesic loss with the default weights and ``gradient="exact"``,
``"riemannian"`` and ``"autograd"``, and with an anisotropic (data-adaptive-like) Z; and the
baselines on their representations: PoseNet on quaternion + translation (N, 7), Anchor Points
(N, 9) and 6D rotation + translation (N, 9). On CUDA each repeat is bracketed by
``torch.cuda.synchronize``. The table gives the median time, its ratio to MSE and, for the
baselines, the ratio of the exact SE(3) loss to them. By default it runs on the CPU, and on CUDA
too when available.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable
from functools import partial

import torch
from bench_common import add_device_options, resolve_devices
from torch import Tensor

from svr.geometry import (
    pose_to_anchor_points,
    pose_to_quat_translation,
    pose_to_rotation_6d_translation,
)
from svr.losses import anchor_point_loss, posenet_loss, rotation_6d_loss, se3_geodesic_loss

Loss = Callable[[Tensor, Tensor], Tensor]

# An anisotropic diagonal Z like the data-adaptive weights of the paper's second stage; it takes
# the fused loss's general path (the default Z, block-isotropic, takes the faster one).
ADAPTIVE_Z = torch.tensor([1.0, 1.3, 0.8, 1 / 900, 1.2 / 900, 0.9 / 900])


def _identity(pose: Tensor) -> Tensor:
    return pose


# (name, loss, representation of the (N, 6) poses it takes)
CASES: list[tuple[str, Loss, Callable[[Tensor], Tensor]]] = [
    ("mse", torch.nn.functional.mse_loss, _identity),
    ("se3 exact", partial(se3_geodesic_loss, gradient="exact"), _identity),
    ("se3 riemannian", partial(se3_geodesic_loss, gradient="riemannian"), _identity),
    ("se3 autograd", partial(se3_geodesic_loss, gradient="autograd"), _identity),
    ("se3 adaptive Z", partial(se3_geodesic_loss, weights=ADAPTIVE_Z), _identity),
    ("posenet", posenet_loss, pose_to_quat_translation),
    ("anchor points", anchor_point_loss, pose_to_anchor_points),
    ("rotation6d", rotation_6d_loss, pose_to_rotation_6d_translation),
]
BASELINES = ("posenet", "anchor points", "rotation6d")


def random_poses(n: int, generator: torch.Generator) -> Tensor:
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator), dim=1)
    angle = torch.rand(n, 1, generator=generator) * math.pi
    return torch.cat([axis * angle, 20.0 * torch.randn(n, 3, generator=generator)], dim=1)


def median_us(loss: Loss, pred: Tensor, target: Tensor, repeats: int) -> float:
    sync = torch.cuda.synchronize if pred.is_cuda else lambda: None

    def step() -> float:
        pred.grad = None
        sync()
        start = time.perf_counter()
        loss(pred, target).backward()
        sync()
        return time.perf_counter() - start

    for _ in range(max(10, repeats // 10)):
        step()
    return statistics.median(step() for _ in range(repeats)) * 1e6


def run(device: torch.device, n: int, repeats: int) -> dict[str, float]:
    generator = torch.Generator().manual_seed(n)
    target = random_poses(n, generator)
    noise_scale = torch.tensor([0.06] * 3 + [2.0] * 3)  # ~0.1 rad and ~3.5 mm
    pred = target + noise_scale * torch.randn(n, 6, generator=generator)
    return {
        name: median_us(
            loss,
            represent(pred).detach().to(device).requires_grad_(True),
            represent(target).to(device),
            repeats,
        )
        for name, loss, represent in CASES
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per case")
    add_device_options(parser)
    args = parser.parse_args()
    devices = resolve_devices(parser, args)

    print(f"torch {torch.__version__}, {args.threads} CPU threads, median of {args.repeats}")
    print(f"{'loss':<16}{'N':>6}  {'device':<7}{'time us':>10}{'x mse':>8}{'exact / this':>14}")
    for device in map(torch.device, devices):
        run(device, 64, 10)  # first calls in a process and on a device are slower: not timed
        for n in (64, 4096):
            times = run(device, n, args.repeats)
            for name, us in times.items():
                vs_exact = f"{times['se3 exact'] / us:14.2f}" if name in BASELINES else ""
                ratio = us / times["mse"]
                print(f"{name:<16}{n:>6}  {device.type:<7}{us:>10.1f}{ratio:>8.1f}{vs_exact}")


if __name__ == "__main__":
    main()
