"""The paper's fetal experiment (Table 3): SE(3) vs PoseNet and Anchor Points on held-out ages.

SE(3) with the default and the data-adaptive Z, PoseNet and Anchor Points are trained with the same
backbone, data and budget, and evaluated on held-out gestational ages.

Run from the repository root::

    python benchmarks/run_table3.py --budget cpu [--atlas-dir ../shared/data/atlas/sb-fidon2021]
    python benchmarks/run_table3.py --budget smoke   # minutes; checks the pipeline end to end

Steps, all through the ``svr`` command line (so the run is what a user would do):
    1. ``svr train`` for each loss (se3, posenet, anchor) on the atlas volumes other than the
       held-out ages (24, 28 and 32 weeks by default), same backbone, slices, seed and steps.
    2. Data-adaptive Z (the paper's second stage): the se3 model predicts validation slices drawn
       from the *training* volumes (never the held-out ones); Z = diag(cov(errors)^-1)
       (:func:`svr.losses.estimate_metric_weights`); se3 is trained again from scratch with that Z
       on the same budget.
    3. ``svr evaluate`` of the four checkpoints on random validation poses (Euler angles in ±90°,
       offsets in ±40 mm) of the held-out volumes: Table 3 (CC, MSE, PSNR, SSIM, geodesic, Euler
       and translation errors) with paired tests, written under ``OUT/report``.

Budgets (per model): ``smoke`` a few steps of a tiny network (about 30 s in all); ``cpu`` 4,000
steps of 32 slices on random poses, two trainings at a time with one thread each (measured: 25
min in all on 2 cores, 8 min a wave on quiet cores; the budget is 2 h on 2 cores);
``gpu`` the paper-scale run: the Euler grid of every training volume (``--pose-sampling grid``),
60,000 steps of 64 slices at 128 x 128.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from svr.cli import main as svr
from svr.geometry import se3_error
from svr.image import Image
from svr.losses import estimate_metric_weights
from svr.metrics import nearest_orbit_member
from svr.models.checkpoint import load_checkpoint
from svr.models.network import ModelConfig, build_model
from svr.sampling.poses import random_slice_poses
from svr.sampling.slicer import SliceConfig, brain_fraction, sample_slices
from svr.sampling.volume import load_canonical_volume

ROOT = Path(__file__).resolve().parents[1]
LOSSES = ("se3", "posenet", "anchor")


@dataclass(frozen=True)
class Budget:
    """Training and evaluation sizes of one budget."""

    steps: int
    batch_size: int
    size: int
    spacing_mm: float
    width: int
    depth: int
    eval_slices: int
    z_slices: int
    pose_sampling: str = "random"


BUDGETS = {
    "smoke": Budget(
        steps=20,
        batch_size=8,
        size=64,
        spacing_mm=2.0,
        width=8,
        depth=3,
        eval_slices=32,
        z_slices=64,
    ),
    "cpu": Budget(
        steps=4000,
        batch_size=32,
        size=96,
        spacing_mm=1.4,
        width=16,
        depth=4,
        eval_slices=200,
        z_slices=600,
    ),
    "gpu": Budget(
        steps=60000,
        batch_size=64,
        size=128,
        spacing_mm=1.0,
        width=32,
        depth=4,
        eval_slices=1000,
        z_slices=4000,
        pose_sampling="grid",
    ),
}


def common_args(budget: Budget, device: str, seed: int) -> list[str]:
    return [
        "--size",
        str(budget.size),
        "--spacing",
        str(budget.spacing_mm),
        "--width",
        str(budget.width),
        "--depth",
        str(budget.depth),
        "--device",
        device,
        "--seed",
        str(seed),
        "--quiet",
    ]


def train_args(budget: Budget, atlas: Path, hold_out: list[str], out: Path) -> list[str]:
    return [
        "train",
        "--output-dir",
        str(out),
        "--atlas-dir",
        str(atlas),
        "--hold-out",
        *hold_out,
        "--steps",
        str(budget.steps),
        "--batch-size",
        str(budget.batch_size),
        "--pose-sampling",
        budget.pose_sampling,
        "--checkpoint-every",
        str(max(1, budget.steps // 5)),
        "--warmup-steps",
        str(min(100, budget.steps // 10)),
    ]


def run_parallel(commands: dict[str, list[str]], jobs: int, device: str) -> dict[str, float]:
    """Run commands ``jobs`` at a time; return each one's wall time. Exits if one fails."""
    threads = max(1, (os.cpu_count() or 1) // jobs) if device == "cpu" else None
    env = dict(os.environ)
    if threads is not None:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    pending = list(commands.items())
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    timings: dict[str, float] = {}
    while pending or running:
        while pending and len(running) < jobs:
            name, command = pending.pop(0)
            running[name] = (subprocess.Popen(command, env=env), time.perf_counter())
        for name, (process, started) in list(running.items()):
            if process.poll() is not None:
                del running[name]
                if process.returncode:
                    raise SystemExit(f"training {name} failed ({process.returncode})")
                timings[name] = time.perf_counter() - started
        time.sleep(1)
    return timings


def latest(run: Path) -> Path:
    return max((run / "checkpoints").glob("step_*"))


def adaptive_weights(
    checkpoint: Path, atlas: Path, hold_out: list[str], budget: Budget, device: str, seed: int
) -> list[float]:
    """diag(cov^-1) of the se3 model's errors on validation slices of the training volumes.

    For a model trained up to the mirror twin (``symmetry_planes``), the errors are taken to the
    nearer member of each true pose's orbit, as its loss measures them.
    """
    ckpt = load_checkpoint(checkpoint, map_location=device)
    config = ModelConfig.from_dict(ckpt.config["model"])
    model = build_model(config).to(device).eval()
    model.load_state_dict(ckpt.state_dict)
    slice_config = SliceConfig(size=config.input_size, spacing_mm=config.spacing_mm)
    generator = torch.Generator().manual_seed(seed + 1)  # not the training poses
    errors = []
    held = {float(h) for h in hold_out}
    folders = [d for d in sorted(atlas.glob("GA*")) if float(d.name[2:4]) not in held]
    per_volume = max(8, budget.z_slices // len(folders))
    for folder in folders:
        volume = load_canonical_volume(folder / "srr.nii.gz", folder / "mask.nii.gz").to(device)
        poses = random_slice_poses(4 * per_volume, generator).to(device)
        mask = Image(volume.mask.float(), volume.image.affine)
        poses = poses[brain_fraction(mask, poses, slice_config) >= 0.1][:per_volume]
        with torch.no_grad():
            slices = sample_slices(volume.image, poses, slice_config)[:, None]
            predicted = model.predict_poses(slices).double()
        member, _ = nearest_orbit_member(predicted, poses.double(), config.symmetry_planes)
        errors.append(se3_error(predicted, member).cpu())
    return estimate_metric_weights(torch.cat(errors)).tolist()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budget", choices=sorted(BUDGETS), default="cpu")
    parser.add_argument(
        "--atlas-dir", type=Path, default=ROOT.parent / "shared" / "data" / "atlas" / "sb-fidon2021"
    )
    parser.add_argument("--hold-out", nargs="+", default=["24", "28", "32"])
    parser.add_argument("--out", type=Path, default=None, help="default: runs/table3-BUDGET")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=None, help="override the budget's steps")
    parser.add_argument(
        "--jobs", type=int, default=2, help="trainings run at once (CPU: one thread each)"
    )
    args = parser.parse_args()
    budget = BUDGETS[args.budget]
    if args.steps is not None:
        budget = replace(budget, steps=args.steps)
    out = args.out or ROOT / "runs" / f"table3-{args.budget}"
    out.mkdir(parents=True, exist_ok=True)
    device = (
        "cuda"
        if args.device == "auto" and torch.cuda.is_available()
        else ("cpu" if args.device == "auto" else args.device)
    )
    common = common_args(budget, device, args.seed)
    timings: dict[str, float] = {}

    def train_command(name: str, loss: str, extra: list[str]) -> list[str]:
        run = train_args(budget, args.atlas_dir, args.hold_out, out / name)
        return [sys.executable, "-m", "svr", *run, "--loss", loss, *extra, *common]

    # Two waves of args.jobs parallel trainings (1 thread each on the CPU: no oversubscription):
    # se3 and PoseNet, then Anchor Points and se3 with the Z estimated from the first se3 model.
    first = {
        "se3": train_command("se3", "se3", []),
        "posenet": train_command("posenet", "posenet", []),
    }
    timings.update(run_parallel(first, args.jobs, device))
    start = time.perf_counter()
    weights = adaptive_weights(
        latest(out / "se3"), args.atlas_dir, args.hold_out, budget, device, args.seed
    )
    timings["adaptive_weights"] = time.perf_counter() - start
    (out / "adaptive_weights.json").write_text(json.dumps({"diag": weights}, indent=1) + "\n")
    second = {
        "anchor": train_command("anchor", "anchor", []),
        "se3_adaptive": train_command(
            "se3_adaptive", "se3", ["--metric-weights", *map(str, weights)]
        ),
    }
    timings.update(run_parallel(second, args.jobs, device))

    start = time.perf_counter()
    checkpoints = [f"{name}={latest(out / name)}" for name in (*LOSSES, "se3_adaptive")]
    code = svr(
        [
            "evaluate",
            "--checkpoints",
            *checkpoints,
            "--atlas-dir",
            str(args.atlas_dir),
            "--only-ga",
            *args.hold_out,
            "--num-slices",
            str(budget.eval_slices),
            "--output-dir",
            str(out / "report"),
            "--overwrite",
            "--device",
            device,
            "--seed",
            str(args.seed + 2),
            "--quiet",
        ]
    )
    if code:
        raise SystemExit("evaluation failed")
    timings["evaluate"] = time.perf_counter() - start
    (out / "timings.json").write_text(json.dumps(timings, indent=1) + "\n")
    print(f"adaptive Z diag: {[round(w, 4) for w in weights]}")
    print(f"timings (s): {json.dumps({k: round(v) for k, v in timings.items()})}")
    print(f"report: {out / 'report' / 'summary.md'}")


if __name__ == "__main__":
    main()
