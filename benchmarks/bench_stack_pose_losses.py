"""The stack-pose network trained with the SE(3) loss and with the baselines' losses, same budget.

The paper's Table 3 for stacks: one network (:class:`svr.models.stack_pose.StackPoseNet`, the
regress head), one training recipe (:class:`svr.models.stack_pose_train.StackPoseTrainingConfig`
with ``--steps`` steps, the same seed, so every run sees the same simulated blocks in the same
order), and four ways of outputting and scoring the residual pose:

* ``se3``: rotation vector + translation, the SE(3) geodesic loss on the final stack pose (the
  shipped recipe);
* ``posenet``: quaternion + translation, PoseNet's loss (beta 500);
* ``anchor``: three anchor points (half-size 60 mm), the Anchor Points loss;
* ``rot6d``: the continuous 6D rotation + translation, its squared loss.

Each baseline's loss compares its raw outputs with the true residual's labels. The runs are
trained here one after another on one core (``--runs-dir``; a rerun resumes or reuses them), then
each is measured on the same stacks as ``bench_learned_stack_poses.py``: held-out ages (never
trained on) and the bench cases, two ways:

* ``estimate``: the whole estimator (mask-axis hypotheses, three refinements, the score's choice);
* ``local``: three refinements from the true frame turned by 20 degrees about a random axis and
  shifted 5 mm (the part that the pose loss trains).

Beside them, the single-slice route (``--slice-model``, default the shipped slice-pose model):
every slice's canonical pose predicted on its own, then the stack's robust consensus with the
mirror-twin disambiguation
(:func:`svr.reconstruction.initialisation.slice_model.slice_predictions`), as ``estimate`` only.

Paired comparison per stack against ``se3``: the Wilcoxon signed-rank test on the rotation errors
(two-sided p) and the share of stacks where the baseline is worse.

Run from the repository root::

    python benchmarks/bench_stack_pose_losses.py --steps 1500 --threads 1
        --results benchmarks/results/stack-pose-losses.md
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import ATLAS, MOTION, SHARED
from bench_learned_stack_poses import bench_stacks, held_out_stacks, rotation_deg
from scipy.stats import wilcoxon

from svr.geometry import se3_compose, se3_inverse, so3_exp
from svr.image import Image
from svr.models.predict import load_pose_model
from svr.models.stack_pose import StackPoseConfig, load_stack_pose_model
from svr.models.stack_pose_train import StackPoseTrainingConfig, train_stack_pose
from svr.reconstruction.initialisation.slice_model import slice_predictions
from svr.reconstruction.initialisation.stack_pose import estimate_stack_pose, refine_transforms
from svr.reconstruction.slices import extract_slices
from svr.reconstruction.stacks import prepare_stacks
from svr.representation_registry import representations_by_cli_name
from svr.sampling.blocks import coarsen_stack, stack_frame
from svr.sampling.motion import load_trajectories
from svr.sampling.volume import atlas_volume_paths, downsample_volume, load_canonical_volume


def train_runs(args, trajectories) -> dict[str, float]:
    """Train (or resume) one run per loss; returns the wall seconds each took here."""
    by_cli = representations_by_cli_name()
    pairs = atlas_volume_paths(args.atlas, hold_out=tuple(args.hold_out))
    volumes = [downsample_volume(load_canonical_volume(v, m), 2) for v, m in pairs]
    seconds = {}
    for loss in args.losses:
        folder = args.runs_dir / loss
        began = time.perf_counter()
        train_stack_pose(
            volumes,
            trajectories,
            StackPoseConfig(representation=by_cli[loss].name),
            StackPoseTrainingConfig(
                steps=args.steps,
                learning_rate=args.learning_rate,
                fine_tune_steps=0,
                seed=args.seed,
            ),
            folder=folder,
            progress=True,
        )
        seconds[loss] = time.perf_counter() - began
        print(f"{loss}: trained to {args.steps} steps ({seconds[loss]:.0f} s this run)", flush=True)
    return seconds


def local_start(truth_frame: torch.Tensor, gen: torch.Generator, turn_deg: float) -> torch.Tensor:
    """The true frame turned by ``turn_deg`` about a random axis and shifted 5 mm."""
    axis = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=torch.float64), dim=0)
    shift = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=torch.float64), dim=0)
    start = torch.eye(4, dtype=torch.float64)
    start[:3, :3] = so3_exp(axis * math.radians(turn_deg))
    start[:3, 3] = shift * 5.0
    return se3_compose(start, truth_frame)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--losses", nargs="+", default=["se3", "posenet", "anchor", "rot6d"])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--learning-rate", type=float, default=1e-3)
    parser.add_argument("--runs-dir", type=Path, default=Path("runs/stack-pose-losses"))
    parser.add_argument("--atlas", type=Path, default=ATLAS)
    parser.add_argument("--motion", type=Path, default=MOTION)
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument("--hold-out", type=float, nargs="*", default=[24.0, 28.0, 32.0])
    parser.add_argument("--bench", nargs="*", default=["sb24-large", "sb28-moderate"])
    parser.add_argument("--cases-per-age", type=int, default=3)
    parser.add_argument("--stacks-per-case", type=int, default=3)
    parser.add_argument("--turn-deg", type=float, default=20.0)
    parser.add_argument("--slice-model", default="default", help="'' to leave it out")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--results", type=Path, default=None)
    args = parser.parse_args()
    if "se3" not in args.losses:
        parser.error("--losses must include se3 (the paired reference)")
    torch.set_num_threads(args.threads)
    trajectories = load_trajectories(args.motion)
    seconds = train_runs(args, trajectories)
    args.ages, args.phantom_ages = args.hold_out, []
    stacks = held_out_stacks(args, trajectories) + bench_stacks(args)
    models = {loss: load_stack_pose_model(args.runs_dir / loss) for loss in args.losses}
    errors: dict[str, dict[str, list[float]]] = {
        loss: {"estimate": [], "local": [], "estimate_mm": [], "local_mm": []}
        for loss in args.losses
    }
    slice_model = load_pose_model(args.slice_model) if args.slice_model else None
    if slice_model is not None:
        errors["slice model"] = {"estimate": [], "estimate_mm": []}
    gen = torch.Generator().manual_seed(args.seed)
    for item in stacks:
        frame_of = stack_frame(item["image"])
        truth_frame = se3_compose(item["pose"], se3_inverse(frame_of))
        start = local_start(truth_frame, gen, args.turn_deg)
        line = f"{item['name']:28s}"
        for loss, model in models.items():
            estimate = estimate_stack_pose(model, item["image"], item["mask"], restart_deg=10.0)
            image, fractions = coarsen_stack(item["image"], item["mask"], model.config.in_plane_mm)
            local, _ = refine_transforms(model, image, fractions, start[None])
            for kind, frame in (("estimate", estimate.to_canonical), ("local", local[0])):
                pose = se3_compose(frame, frame_of)
                errors[loss][kind].append(rotation_deg(pose, item["pose"]))
                errors[loss][f"{kind}_mm"].append(float((pose[:3, 3] - item["pose"][:3, 3]).norm()))
            line += f"  {loss} {errors[loss]['estimate'][-1]:6.1f}/{errors[loss]['local'][-1]:5.1f}"
        if slice_model is not None:
            prepared = prepare_stacks(
                [item["image"]], [Image(item["mask"].float(), item["image"].affine)]
            )
            learned = slice_predictions(slice_model, prepared, extract_slices(prepared))
            pose = se3_compose(learned.stack_transforms[0].double().cpu(), frame_of)
            errors["slice model"]["estimate"].append(rotation_deg(pose, item["pose"]))
            errors["slice model"]["estimate_mm"].append(
                float((pose[:3, 3] - item["pose"][:3, 3]).norm())
            )
            line += f"  slice model {errors['slice model']['estimate'][-1]:6.1f}"
        print(line, flush=True)

    lines = [
        f"Same network, recipe and blocks; {args.steps} steps each at learning rate "
        f"{args.learning_rate:g} (seed {args.seed}); "
        f"{len(stacks)} stacks (held-out GA {', '.join(f'{a:g}' for a in args.hold_out)}: "
        f"{args.cases_per_age} cases x {args.stacks_per_case} stacks per age; "
        f"{', '.join(args.bench)}). Paired against se3 on the same stacks.",
        "",
        "| loss | kind | median (deg) | p90 (deg) | within 10 deg | centre median (mm) "
        "| vs se3: median ratio | worse than se3 | Wilcoxon p |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    summary = {}
    for kind in ("estimate", "local"):
        ref = np.array(errors["se3"][kind])
        for loss in [name for name in errors if kind in errors[name]]:
            rot = np.array(errors[loss][kind])
            mm = np.array(errors[loss][f"{kind}_mm"])
            if loss == "se3":
                ratio, worse, p = "1.00", "-", "-"
            else:
                ratio = f"{np.median(rot) / np.median(ref):.2f}"
                worse = f"{100 * (rot > ref).mean():.0f} %"
                p = f"{wilcoxon(rot, ref).pvalue:.2g}"
            summary[f"{loss}/{kind}"] = {
                "median_deg": float(np.median(rot)),
                "p90_deg": float(np.percentile(rot, 90)),
                "within10": float((rot <= 10).mean()),
                "median_centre_mm": float(np.median(mm)),
            }
            lines.append(
                f"| {loss} | {kind} | {np.median(rot):.1f} | {np.percentile(rot, 90):.1f} | "
                f"{100 * (rot <= 10).mean():.0f} % | {np.median(mm):.1f} | {ratio} | {worse} | "
                f"{p} |"
            )
    if seconds:
        lines += [
            "",
            "Training wall time this run (s): "
            + ", ".join(f"{k} {v:.0f}" for k, v in seconds.items()),
        ]
    text = "\n".join(lines)
    print(text)
    if args.results is not None:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        command = "python benchmarks/bench_stack_pose_losses.py " + " ".join(sys.argv[1:])
        args.results.write_text(
            f"# Stack-pose losses: SE(3) vs the baselines\n\nCommand: `{command}`\n\n{text}\n",
            encoding="utf-8",
        )
        args.results.with_suffix(".json").write_text(
            json.dumps({"summary": summary, "errors": errors, "seconds": seconds}, indent=1),
            encoding="utf-8",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
