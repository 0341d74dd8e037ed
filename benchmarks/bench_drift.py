"""Why more rounds hurt moderate motion: slices drift from their true poses, and what stops it.

Starts every slice of a bench case at its **true** pose and alternates slice-to-volume
registration (one by one) and super-resolution for ``--rounds`` rounds with the public round
steps of :mod:`svr.reconstruction.pipeline`, once with only the brain pixels as data (as the fixed
schedule of fetal-svr 0.1.0 does) and once with the background band of the adaptive schedule
(pixels 2-5 mm outside each slice's mask observed as 0, EM-weighted). After each round it prints
the per-slice pose errors against the truth (after the best rigid alignment of all slices,
:func:`svr.geometry.averaging.robust_mean_pose`) and, per stack, the **stretch**: the slope of the
slices' error along the stack normal against their true position along it (in %; +1 % means the
stack's slices spread 1 % farther apart than they are). A volume that spreads beyond the brain
pulls the edge slices outward, the next volume spreads farther, and the stacks stretch round
after round.

Run from the repository root::

    python benchmarks/bench_drift.py [--case sb28-moderate] [--rounds 8] [--threads 2]
        [--results benchmarks/results/convergence-drift.md]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from bench_common import SHARED, load_case_stacks, true_slice_poses

from svr.geometry import se3_compose, se3_inverse, se3_to_vector
from svr.geometry.averaging import robust_mean_pose
from svr.metrics import rotation_error_rad, translation_error_mm
from svr.reconstruction.acquisition import acquisition_model
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.rounds import initial_volume, reject_outliers, super_resolve, svr_pass
from svr.reconstruction.slices import SliceSet, array_poses, extract_slices, plane_poses
from svr.reconstruction.superres import output_grid


def slice_truth(case: Path, slices: SliceSet) -> torch.Tensor:
    """(N, 4, 4) true scanner poses of the slice set's k-planes."""
    truth = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))["stacks"]
    by_file = {str((case / s["file"]).resolve()): s["slices"] for s in truth}
    per_stack = [
        true_slice_poses(by_file[str(Path(name).resolve())], "scanner")
        for name in slices.stack_names
    ]
    return torch.stack(
        [
            per_stack[int(s)][int(k)]
            for s, k in zip(slices.stack_ids.tolist(), slices.slice_indices.tolist(), strict=True)
        ]
    )


def errors(slices: SliceSet, poses: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """Median rotation and translation error after alignment, and each stack's stretch (%)."""
    estimate = plane_poses(slices, poses).double().cpu()
    shift = robust_mean_pose(se3_compose(truth, se3_inverse(estimate)))
    aligned = se3_compose(shift.expand_as(estimate), estimate)
    p, t = se3_to_vector(aligned), se3_to_vector(truth)
    out = {
        "rotation_deg": float(rotation_error_rad(p, t).rad2deg().median()),
        "translation_mm": float(translation_error_mm(p, t).median()),
    }
    for sid in range(len(slices.stack_names)):
        members = (slices.stack_ids == sid).cpu()
        normal = truth[members][0, :3, 2]
        z = truth[members][:, :3, 3] @ normal
        z = z - z.mean()
        e = (aligned[members][:, :3, 3] - truth[members][:, :3, 3]) @ normal
        out[f"stretch_{sid}"] = 100 * float((z * (e - e.mean())).sum() / (z * z).sum())
    return out


def run(
    slices: SliceSet, truth: torch.Tensor, rounds: int, band: tuple[float, float]
) -> list[dict[str, float]]:
    """Rounds of (one-by-one SVR, outlier weights, super-resolution) from the true poses."""
    config = ReconstructionConfig.preset("stack", "fixed")
    poses = array_poses(slices, truth).to(slices.poses)
    model = acquisition_model(slices, output_grid(slices, config.grid.resolution_mm), band)
    points, b_points = model.points(poses), model.background_points(poses)
    volume = initial_volume(model, points)
    outliers = reject_outliers(model, volume, points, config, background_points=b_points)
    volume = super_resolve(model, volume, points, outliers, config, 0, b_points)
    rows = []
    for index in range(1, rounds + 1):
        poses = svr_pass(
            model, volume, poses, config, 1, outliers.slice_weights * ~outliers.excluded
        )
        points, b_points = model.points(poses), model.background_points(poses)
        outliers = reject_outliers(
            model,
            volume,
            points,
            config,
            outliers.pixel_weights,
            outliers.slice_weights,
            b_points,
        )
        volume = super_resolve(model, volume, points, outliers, config, index, b_points)
        rows.append({"round": index, **errors(slices, poses, truth)})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="sb28-moderate")
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--results", type=Path)
    args = parser.parse_args()
    case = args.data / args.case
    if not (case / "truth_slices.json").exists():
        print(f"{case}: bench case with truth_slices.json not found", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    slices = extract_slices(load_case_stacks(case))
    truth = slice_truth(case, slices)
    stacks = len(slices.stack_names)
    lines = [
        "# Slice drift from the true poses (`benchmarks/bench_drift.py`)",
        "",
        "Command: `python benchmarks/" + " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]) + "`",
        "",
        f"Case {args.case}, {len(slices)} slices started at their true poses, {args.rounds} "
        "rounds of one-by-one SVR + super-resolution (the fixed schedule's round settings).",
        "",
        "| data | round | rotation error (deg, median) | translation error (mm, median) | "
        + " | ".join(f"stretch stack {s} (%)" for s in range(stacks))
        + " | time (s) |",
        "|---|---:|---:|---:|" + "---:|" * stacks + "---:|",
    ]
    print("\n".join(lines), flush=True)
    summary = {}
    for name, band in (("brain pixels only", (0.0, 0.0)), ("with background band", (2.0, 5.0))):
        start = time.perf_counter()
        rows = run(slices, truth, args.rounds, band)
        seconds = time.perf_counter() - start
        summary[name] = rows
        for row in rows:
            stretch = " | ".join(f"{row[f'stretch_{s}']:+.2f}" for s in range(stacks))
            line = (
                f"| {name} | {row['round']} | {row['rotation_deg']:.2f} | "
                f"{row['translation_mm']:.2f} | {stretch} | "
                + (f"{seconds:.1f} |" if row is rows[-1] else "|")
            )
            lines.append(line)
            print(line, flush=True)
    last = {name: rows[-1] for name, rows in summary.items()}
    a, b = last["brain pixels only"], last["with background band"]
    verdict = (
        f"After {args.rounds} rounds: translation error {a['translation_mm']:.2f} -> "
        f"{b['translation_mm']:.2f} mm (x{b['translation_mm'] / a['translation_mm']:.2f}), "
        f"rotation {a['rotation_deg']:.2f} -> {b['rotation_deg']:.2f} deg "
        f"(x{b['rotation_deg'] / a['rotation_deg']:.2f}), largest stretch "
        f"{max(abs(a[f'stretch_{s}']) for s in range(stacks)):.2f} -> "
        f"{max(abs(b[f'stretch_{s}']) for s in range(stacks)):.2f} %"
    )
    lines += ["", verdict]
    print("\n" + verdict)
    if args.results is not None:
        args.results.write_text("\n".join(lines) + "\n", encoding="utf-8")
        args.results.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
