"""Where the automatic masks of the real scan differ from the manual ones, in the brain's frame.

The real scan's automatic masks move the learned output frame's pitch by several degrees against
the manual masks (``benchmarks/results/real-scan-pitch.md``). This locates their errors: each
stack's automatic mask (``svr segment-stack``, written to ``--out`` unless already there) is
compared voxel by voxel with the manual one, and the voxels only one of them has are mapped into
the looked-at reference frame (``real-scan-frame-reference.json``: canonical x left to right, y
back to front, z foot to head, mm from the brain's centre), so that "a rim at the front of the
skull base" reads as coordinates. Run from the repository root (about 15 s on one core)::

    python benchmarks/bench_real_mask_errors.py [--out runs/real-masks] [--results FILE]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
from bench_common import write_results
from bench_real_frame import REFERENCE, ROOT, SCAN


def canonical_points(mask: np.ndarray, affine: np.ndarray, to_canonical: np.ndarray) -> np.ndarray:
    """(N, 3) canonical mm of a boolean mask's voxels (voxel -> world -> reference canonical)."""
    ijk = np.argwhere(mask).astype(np.float64)
    world = ijk @ affine[:3, :3].T + affine[:3, 3]
    return world @ to_canonical[:3, :3].T + to_canonical[:3, 3]


def _centroid(points: np.ndarray) -> str:
    if len(points) == 0:
        return "-"
    x, y, z = points.mean(axis=0)
    return f"{x:+.0f}, {y:+.0f}, {z:+.0f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scan", type=Path, default=SCAN, help="the real scan's folder")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "real-masks")
    parser.add_argument("--reference", type=Path, default=REFERENCE)
    parser.add_argument("--results", type=Path, help="also write the table here (markdown)")
    args = parser.parse_args()
    frame = np.asarray(json.loads(args.reference.read_text())["scanner_from_canonical"])
    to_canonical = np.linalg.inv(frame)
    runs = range(1, 7)
    stacks = [args.scan / f"sub-01_run-{i}_T2w.nii.gz" for i in runs]
    autos = [args.out / f"run-{i}_mask.nii.gz" for i in runs]
    if not all(a.exists() for a in autos):
        args.out.mkdir(parents=True, exist_ok=True)
        command = [sys.executable, "-m", "svr", "segment-stack",
                   "--input-stacks", *map(str, stacks),
                   "--output-stack-masks", *map(str, autos), "--overwrite", "-q"]  # fmt: skip
        env = dict(os.environ, OMP_NUM_THREADS="1")
        subprocess.run(command, check=True, env=env)
    rows = []
    for i, stack, auto in zip(runs, stacks, autos, strict=True):
        manual_img = nib.load(args.scan / f"sub-01_run-{i}_T2w_desc-brain_mask.nii.gz")
        manual = np.asarray(manual_img.dataobj) > 0.5
        automatic = np.asarray(nib.load(auto).dataobj) > 0.5
        affine = np.asarray(manual_img.affine)
        ml = abs(np.linalg.det(affine[:3, :3])) / 1000.0
        only_auto = canonical_points(automatic & ~manual, affine, to_canonical)
        only_manual = canonical_points(manual & ~automatic, affine, to_canonical)
        dice = 2 * (manual & automatic).sum() / (manual.sum() + automatic.sum())
        slices = [np.nonzero(m.any(axis=(0, 1)))[0] for m in (manual, automatic)]
        rows.append(
            f"| {stack.name} | {dice:.3f} | {manual.sum() * ml:.0f} / {automatic.sum() * ml:.0f} | "
            f"{len(only_manual) * ml:.1f} | {_centroid(only_manual)} | "
            f"{len(only_auto) * ml:.1f} | {_centroid(only_auto)} | "
            f"{slices[0].min()}-{slices[0].max()} / {slices[1].min()}-{slices[1].max()} |"
        )
    text = "\n".join(
        [
            "| stack | Dice | volume manual / automatic (ml) | missed: ml | centroid x, y, z "
            "(mm) | taken in: ml | centroid x, y, z (mm) | slices manual / automatic |",
            "|---|---:|---|---:|---|---:|---|---|",
            *rows,
        ]
    )
    print(text)
    if args.results is not None:
        write_results(
            args.results,
            "Where the automatic masks differ from the manual ones",
            text,
            f" ({datetime.date.today().isoformat()})",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
