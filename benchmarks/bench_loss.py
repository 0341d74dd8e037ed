"""Forward + backward wall time of the pose losses, against ``torch.nn.functional.mse_loss``.

Run from the repository root::

    python benchmarks/bench_loss.py [--repeats 200] [--rounds 1] [--threads 2]
        [--device cpu|cuda|all] [--results benchmarks/results/loss-run.md]

For N = 64 and 4096 float32 poses (rotation vectors with angles uniform in [0, pi), translations
~ N(0, 20 mm); predictions are the targets perturbed by ~0.1 rad and ~3.5 mm), it times one
``loss(pred, target).backward()`` per repeat, after a warm-up, for: MSE on the (N, 6) pose
vectors; the SE(3) geodesic loss with the default (block-isotropic) weights and
``gradient="exact"``, ``"riemannian"`` and ``"autograd"``, with an anisotropic diagonal
(data-adaptive-like) Z, and with that Z given as a 6x6 matrix (the general path); and the
baselines on their representations: PoseNet on quaternion + translation (N, 7), Anchor Points
(N, 9) and 6D rotation + translation (N, 9). On CUDA each repeat is bracketed by
``torch.cuda.synchronize``. The table gives the median time, its ratio to MSE and, for the
baselines, the ratio of the exact SE(3) loss to them. With ``--rounds R`` all the cases are timed
R times in turn and each time is the median of their R medians, so that a change of the machine's
load during the run weighs on all the cases alike. By default it runs on the CPU, and on CUDA
too when available. With ``--results PATH`` the table is also written to PATH as Markdown, with
the command and the torch version, and as JSON beside it.

On a machine whose cores are busy, ``--threads`` above 1 can make the medians meaningless: the
transcendental functions of the SE(3) loss (``sqrt``, ``sin``, ``cos``) are split across threads
from 2048 elements on, and each such call then waits for a thread that is not scheduled.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import statistics
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

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
# the fused loss's anisotropic diagonal path (the default Z, block-isotropic, takes the
# isotropic one, and a 6x6 matrix Z the general one).
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
    ("se3 6x6 Z", partial(se3_geodesic_loss, weights=torch.diag(ADAPTIVE_Z)), _identity),
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
    parser.add_argument(
        "--rounds", type=int, default=1, help="times all cases are timed in turn (median)"
    )
    parser.add_argument(
        "--results", type=Path, default=None, help="also write the table here (and JSON beside)"
    )
    add_device_options(parser)
    args = parser.parse_args()
    devices = resolve_devices(parser, args)

    header = f"torch {torch.__version__}, {args.threads} CPU threads, median of {args.repeats}"
    if args.rounds > 1:
        header += f", median over {args.rounds} rounds"
    print(header)
    print(f"{'loss':<16}{'N':>6}  {'device':<7}{'time us':>10}{'x mse':>8}{'exact / this':>14}")
    rows = []
    for device in map(torch.device, devices):
        run(device, 64, 10)  # first calls in a process and on a device are slower: not timed
        for n in (64, 4096):
            rounds = [run(device, n, args.repeats) for _ in range(max(1, args.rounds))]
            times = {name: statistics.median(r[name] for r in rounds) for name in rounds[0]}
            for name, us in times.items():
                vs_exact = times["se3 exact"] / us if name in BASELINES else None
                ratio = us / times["mse"]
                rows.append(
                    {"loss": name, "n": n, "device": device.type, "time_us": us, "x_mse": ratio}
                    | ({"exact_over_this": vs_exact} if vs_exact is not None else {})
                )
                extra = f"{vs_exact:14.2f}" if vs_exact is not None else ""
                print(f"{name:<16}{n:>6}  {device.type:<7}{us:>10.1f}{ratio:>8.1f}{extra}")
    if args.results is not None:
        write_results(args.results, header, rows)


def write_results(path: Path, header: str, rows: list[dict]) -> None:
    """Write the timings as a Markdown table (with the command) to ``path``, JSON beside it."""
    command = shlex.join(["python", *sys.argv])
    table = [
        "| loss | N | device | time (us) | x mse | exact / this |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        vs_exact = f"{row['exact_over_this']:.2f}" if "exact_over_this" in row else ""
        table.append(
            f"| {row['loss']} | {row['n']} | {row['device']} | {row['time_us']:.1f} "
            f"| {row['x_mse']:.1f} | {vs_exact} |"
        )
    text = "\n".join([f"Command: `{command}`", "", header, "", *table]) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    payload = {"command": command, "torch": torch.__version__, "header": header, "rows": rows}
    path.with_suffix(".json").write_text(json.dumps(payload, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
