"""Is the real scan's output frame the same however the reconstruction runs?

``svr reconstruct --registration cnn`` ends by bringing the volume into the atlas's frame
(:func:`svr.reconstruction.atlas_frame.atlas_transform`). On the real clinical scan (a fetus without
spina bifida, unlike the atlas's brains) a frame and its front-back twin fit the atlas almost
equally well, so a choice by NCC alone followed rounding: the output flipped with the number of
threads. This reconstructs the real scan once per thread count (``OMP_NUM_THREADS``, a fresh process
each) and reports, per run, the frame chosen (the start that won and the final NCCs of the frames
compared) and the angle between the output's frame and a reference: the frame of an earlier output
whose axial, coronal and sagittal views were looked at and found to be the atlas's standard planes
(``benchmarks/results/real-scan-frame-reference.json``, its affine). There is no ground truth on a
real scan; what this measures is whether every run lands on that frame (a few degrees) rather than
its twin (150-180 degrees).

Run from the repository root (about 2-4 minutes per run on one core)::

    python benchmarks/bench_real_frame.py [--threads 1 2] [--out runs/real-frame] \
        [--results benchmarks/results/real-scan-frame.md]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import nibabel as nib
import numpy as np
from bench_common import ATLAS, SHARED, write_results

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "benchmarks" / "results" / "real-scan-frame-reference.json"
SCAN = SHARED / "data" / "stacks" / "real-mialsrtk-sub01"
FRAME_LINE = re.compile(
    r"atlas frame: turned ([\d.]+) deg, shifted ([\d.]+) mm \(start (\w+); (.*)\)"
)


def rotation_part(affine: np.ndarray) -> np.ndarray:
    """The (3, 3) rotation of a voxel-to-world affine (4, 4): its columns divided by the spacing."""
    return affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0)


def frame_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) between the rotation parts of two voxel-to-world affines (4, 4)."""
    ra, rb = rotation_part(a), rotation_part(b)
    cosine = (np.trace(rb @ ra.T) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cosine, -1.0, 1.0))))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scan", type=Path, default=SCAN, help="the real scan's folder")
    parser.add_argument("--atlas", type=Path, default=ATLAS / "GA28_operated")
    parser.add_argument("--model", default="stack-pose")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--reference", type=Path, default=REFERENCE)
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "real-frame")
    parser.add_argument("--results", type=Path, help="also write the table here (markdown)")
    args = parser.parse_args()
    reference = np.asarray(json.loads(args.reference.read_text(encoding="utf-8"))["affine"])
    runs = range(1, 7)
    stacks = [str(args.scan / f"sub-01_run-{i}_T2w.nii.gz") for i in runs]
    masks = [str(args.scan / f"sub-01_run-{i}_T2w_desc-brain_mask.nii.gz") for i in runs]
    args.out.mkdir(parents=True, exist_ok=True)
    rows, affines = [], []
    for threads in args.threads:
        output = args.out / f"real-cnn-{threads}t.nii.gz"
        command = [
            sys.executable, "-m", "svr", "reconstruct", "--input-stacks", *stacks,
            "--stack-masks", *masks, "--registration", "cnn", "--model", args.model,
            "--atlas-volume", str(args.atlas / "srr.nii.gz"),
            "--atlas-mask", str(args.atlas / "mask.nii.gz"),
            "--output-volume", str(output), "--overwrite", "-v",
        ]  # fmt: skip
        env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
        began = time.perf_counter()
        done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
        seconds = time.perf_counter() - began
        if done.returncode != 0:
            print(done.stderr[-2000:], file=sys.stderr)
            return 1
        match = FRAME_LINE.search(done.stderr)
        start, detail = (match.group(3), match.group(4)) if match else ("?", "")
        affine = nib.load(output).affine
        affines.append(affine)
        angle = frame_angle_deg(reference, affine)
        final = detail.split("; coarse")[0].removeprefix("final NCC ")
        rows.append(f"| {threads} | {angle:.1f} | {start} | {final} | {seconds:.0f} |")
        print(rows[-1], flush=True)
    spread = max(
        (frame_angle_deg(a, b) for i, a in enumerate(affines) for b in affines[i + 1 :]),
        default=0.0,
    )
    lines = [
        "| threads | frame vs reference (deg) | start kept | final NCC of the frames compared "
        "| wall (s) |",
        "|---:|---:|---|---|---:|",
        *rows,
        "",
        f"Largest angle between two runs' frames: {spread:.1f} deg.",
    ]
    text = "\n".join(lines)
    print(text.splitlines()[-1])
    if args.results is not None:
        write_results(
            args.results,
            "The real scan's output frame, run by run",
            text,
            f" ({datetime.date.today().isoformat()}, the 2-core VM)",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
