"""Per stack on real-like scans: does a stack-pose model place each stack, or its front-back twin?

``bench_real_frame.py`` checks the real scan's output frame, one number per run, which rests on
which stacks' poses the reconstruction's frame follows. This checks every stack: each of the six
stacks' canonical frame by the model (:func:`svr.models.stack_pose.estimate_stack_pose`, as the
reconstruction calls it: no restarts, no atlas) against the stack's reference frame, and the
model's score (logit) at the reference frame against its score at the reference turned by 180
degrees about each canonical axis (its twins), both refined by the model as it refines its own
hypotheses. A stack is *placed* when the model's frame is within 45 degrees of the reference (the
wrong twins are 150-180 degrees away); the *margin* is the reference's score minus the best
twin's (positive: the model prefers the right frame).

Two scans, each with its own references (``--scans``, default both):

- ``real``: the real clinical scan (6 stacks of a fetus without spina bifida, maternal tissue
  around the brain, manual masks).
- ``fabian``: the 4 FaBiAN stacks (3 subjects; a physics-based MR simulator's stacks of normal
  fetal brains from another atlas family, brain-extracted, thick slices at 3.2 mm): anatomy and
  contrast unlike the training atlas's, with a reference from the files themselves. Their world
  frame is the simulated brain's anatomical frame (RAS: the axial stacks' slices are the brain's
  axial planes, front to the front; looked at), so each stack's reference maps scanner mm to
  canonical mm by the identity turn and the shift that puts the brain mask's centre at the
  origin (``--make-header-truth`` writes them). It is the frame of that atlas family, a few
  degrees from the training atlas's: ample for telling a stack from its twin.

The real scan's reference frames (``benchmarks/results/real-scan-stack-frames.json``) come from a
reconstruction of the six stacks whose stacks all kept stack registration (so their relative
poses are classical registration's) and whose output frame was corrected to the reference frame
of ``bench_real_frame.py`` (an output whose axial, coronal and sagittal views were looked at):
``--make-truth TRANSFORMS.csv OUTPUT.nii.gz`` writes them. Their absolute accuracy is that of
a frame judged by eye (the stacks every model places are 12-24 degrees from them, so the models
or the references carry a tilt of that order on this scan), ample for telling a stack from its
twin; the angles of placed stacks are not a precision measure.

Run from the repository root (a few seconds per model and scan on one core)::

    python benchmarks/bench_real_stacks.py --model stack-pose runs/stack-pose [--threads 1] \
        [--scans real fabian] [--results benchmarks/results/real-scan-stacks.md]
    python benchmarks/bench_real_stacks.py --make-truth runs/real.csv runs/real.nii.gz
    python benchmarks/bench_real_stacks.py --make-header-truth
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import statistics
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from bench_common import FABIAN, FABIAN_STACKS, SHARED, scanner_from_canonical, write_results
from bench_real_frame import REFERENCE, rotation_part

ROOT = Path(__file__).resolve().parents[1]
TRUTH = ROOT / "benchmarks" / "results" / "real-scan-stack-frames.json"
SCAN = SHARED / "data" / "stacks" / "real-mialsrtk-sub01"
FABIAN_TRUTH = ROOT / "benchmarks" / "results" / "fabian-stack-frames.json"
SCANS = {"real": (SCAN, TRUTH), "fabian": (FABIAN, FABIAN_TRUTH)}
PLACED_DEG = 45.0
RUNS = range(1, 7)


def _paths(scan: Path, truth: dict | None = None) -> tuple[list[Path], list[Path]]:
    """The scan's stacks and masks: the truth file's ``masks`` where it names them."""
    if truth is not None and "masks" in truth:
        names = list(truth["masks"])
        return [scan / n for n in names], [scan / truth["masks"][n] for n in names]
    stacks = [scan / f"sub-01_run-{i}_T2w.nii.gz" for i in RUNS]
    masks = [scan / f"sub-01_run-{i}_T2w_desc-brain_mask.nii.gz" for i in RUNS]
    return stacks, masks


def make_header_truth(scan: Path, out: Path) -> None:
    """Write FaBiAN's reference frames: the identity turn, the brain mask's centre to the origin."""
    frames = {}
    for name, mask_name in FABIAN_STACKS.items():
        mask = nib.load(scan / mask_name)
        voxels = np.argwhere(np.asarray(mask.dataobj) > 0.5)
        centre = nib.affines.apply_affine(mask.affine, voxels).mean(axis=0)
        frame = np.eye(4)
        frame[:3, 3] = -centre
        frames[name] = frame.tolist()
    record = {
        "what": "each FaBiAN stack's scanner mm -> canonical mm frame (4x4): the identity turn "
        "(the simulated brain's world frame is its anatomical RAS frame) and the shift that puts "
        "its brain mask's centre at the origin",
        "frames": frames,
        "masks": FABIAN_STACKS,
    }
    out.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {out}")


def make_truth(transforms: Path, output: Path, scan: Path, out: Path) -> None:
    """Write each stack's reference frame (scanner mm -> canonical mm) from a reconstruction."""
    from svr.geometry import se3_compose, se3_inverse, vector_to_se3
    from svr.geometry.averaging import robust_mean_pose
    from svr.image import load_nifti, stack_slice_poses
    from svr.pose_io import read_pose_table

    reference = np.asarray(
        json.loads(REFERENCE.read_text(encoding="utf-8"))["scanner_from_canonical"]
    )
    # the run's canonical frame -> the reference's: G_ref^-1 o G_run (rotation only)
    turn = torch.eye(4, dtype=torch.float64)
    turn[:3, :3] = torch.from_numpy(
        rotation_part(np.linalg.inv(reference) @ scanner_from_canonical(transforms))
    )
    table = read_pose_table(transforms)
    canonical = vector_to_se3(table.poses)
    frames = {}
    for path in _paths(scan)[0]:
        rows = [i for i, f in enumerate(table.files) if Path(f).name == path.name]
        if not rows:
            raise SystemExit(f"{transforms}: no slices of {path.name}")
        image = load_nifti(path)
        planes = stack_slice_poses(image)[table.slice_indices[rows].long()]
        # Each slice's canonical pose times its scanner pose's inverse: the stack's frame.
        frame = robust_mean_pose(se3_compose(canonical[rows], se3_inverse(planes)))
        frames[path.name] = se3_compose(turn, frame).tolist()
    record = {
        "what": "each real-scan stack's scanner mm -> canonical mm frame (4x4): the final slice "
        f"poses of {output.name} (svr reconstruct --registration cnn, every stack kept stack "
        "registration), turned by the rotation from its output frame to the reference frame of "
        "bench_real_frame.py",
        "frames": frames,
    }
    out.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {out}")


def measure(
    model_path: str, scan_name: str, scan: Path, record: dict
) -> tuple[list[str], dict[str, float]]:
    """The table rows of one model on one scan and its summary."""
    from svr.geometry import half_turns, rotation_angle, se3_compose
    from svr.models.stack_pose import load_stack_pose_model
    from svr.reconstruction.initialisation.stack_pose import estimate_stack_pose, refine_transforms
    from svr.reconstruction.stacks import load_stacks
    from svr.sampling.blocks import coarsen_stack

    net = load_stack_pose_model(model_path)
    truth = record["frames"]
    stack_paths, mask_paths = _paths(scan, record)
    stacks = load_stacks(stack_paths, mask_paths)
    twins = half_turns()
    rows, angles, margins = [], [], []
    for path, stack in zip(stack_paths, stacks, strict=True):
        true = torch.tensor(truth[path.name], dtype=torch.float64)
        mask = stack.mask.data > 0.5
        estimate = estimate_stack_pose(net, stack.image, mask, restart_deg=0.0)
        angle = math.degrees(rotation_angle(estimate.to_canonical, true))
        image, fractions = coarsen_stack(stack.image, mask, net.config.in_plane_mm)
        starts = torch.cat([true[None], se3_compose(twins, true.expand(3, 4, 4))])
        _, scores = refine_transforms(net, image, fractions, starts)
        margin = float(scores[0] - scores[1:].max())
        angles.append(angle)
        margins.append(margin)
        twin = " / ".join(f"{float(s):.1f}" for s in scores[1:])
        rows.append(
            f"| {model_path} | {scan_name} | {_short(path.name)} | {angle:.1f} | "
            f"{'yes' if angle <= PLACED_DEG else 'no'} | {float(scores[0]):.1f} | {twin} | "
            f"{margin:+.1f} |"
        )
    placed = [a for a in angles if a <= PLACED_DEG]
    summary = {
        "stacks": len(angles),
        "placed": len(placed),
        "median_placed_deg": statistics.median(placed) if placed else float("nan"),
        "mean_margin": statistics.fmean(margins),
        "right_preferred": sum(m > 0 for m in margins),
    }
    return rows, summary


def _short(name: str) -> str:
    """A stack's short name: ``run-4`` on the real scan, ``simu005-run-2`` on FaBiAN."""
    parts = [p for p in name.split("_") if p.startswith(("sub-simu", "run-"))]
    return "-".join(p.removeprefix("sub-") for p in parts)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", nargs="+", default=["stack-pose"], help="stack-pose models")
    parser.add_argument(
        "--scans", nargs="+", choices=list(SCANS), default=list(SCANS), help="scans to measure"
    )
    parser.add_argument("--scan", type=Path, default=SCAN, help="the real scan's folder")
    parser.add_argument("--truth", type=Path, default=TRUTH, help="the real stacks' references")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--results", type=Path, help="also write the tables here (markdown)")
    parser.add_argument(
        "--make-truth",
        nargs=2,
        type=Path,
        metavar=("TRANSFORMS", "OUTPUT"),
        help="write --truth from a reconstruction's transforms table and output volume",
    )
    parser.add_argument(
        "--make-header-truth",
        action="store_true",
        help=f"write the FaBiAN stacks' references ({FABIAN_TRUTH.name}) from their files",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.make_truth is not None:
        make_truth(*args.make_truth, args.scan, args.truth)
        return 0
    if args.make_header_truth:
        make_header_truth(FABIAN, FABIAN_TRUTH)
        return 0
    scans = {name: SCANS[name] for name in args.scans}
    if "real" in scans:
        scans["real"] = (args.scan, args.truth)
    for name, (folder, _) in scans.items():
        if not folder.is_dir():
            print(f"{folder}: no such folder (the {name} scan)", file=sys.stderr)
            return 1
    header = [
        "| model | scan | stack | model's frame vs reference (deg) | placed | score at reference "
        "| scores at its twins (x / y / z) | margin |",
        "|---|---|---|---:|---|---:|---|---:|",
    ]
    rows, summaries = [], {}
    for model in args.model:
        for name, (folder, truth_path) in scans.items():
            record = json.loads(truth_path.read_text(encoding="utf-8"))
            model_rows, summaries[model, name] = measure(model, name, folder, record)
            rows += model_rows
            print("\n".join(model_rows), flush=True)
    lines = [
        "| model | scan | stacks placed | median angle of those (deg) | right frame preferred "
        "| mean margin | placed vs first model |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for (model, name), s in summaries.items():
        first = summaries[args.model[0], name]["placed"]
        ratio = s["placed"] / first if first else float("inf")
        n = s["stacks"]
        lines.append(
            f"| {model} | {name} | {s['placed']} of {n} | {s['median_placed_deg']:.1f} | "
            f"{s['right_preferred']} of {n} | {s['mean_margin']:+.2f} | x{ratio:.2f} |"
        )
    text = "\n".join([*lines, "", *header, *rows])
    print("\n".join(lines))
    if args.results is not None:
        write_results(
            args.results,
            "Real-like scans' stacks, one by one",
            text,
            f" ({datetime.date.today().isoformat()}, {args.threads} thread(s), the 2-core VM)",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
