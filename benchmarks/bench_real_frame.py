"""Is the real scan's output frame the same however the reconstruction runs?

``svr reconstruct --registration cnn`` ends by bringing the volume into the atlas's frame
(:func:`svr.reconstruction.atlas_frame.atlas_transform`). On the real clinical scan (a fetus without
spina bifida, unlike the atlas's brains) a frame and its front-back twin fit the atlas almost
equally well, so a choice by NCC alone followed rounding: the output flipped with the number of
threads. This reconstructs the real scan once per thread count (``OMP_NUM_THREADS``, a fresh process
each) and reports, per run, the frame chosen (the start that won and the final NCCs of the frames
compared) and the angle between the output's frame and a reference frame.

A canonical output's frame is ``G`` (:func:`bench_common.scanner_from_canonical`: canonical mm ->
the stacks' scanner mm, from its transforms table), not its affine: the affine maps voxels to
canonical mm on a grid built in the slices' frame before the last turns (onto an atlas, onto the
mid-sagittal plane), so its rotation is those turns alone. The reference
(``benchmarks/results/real-scan-frame-reference.json``) is ``G`` of a run whose axial, coronal and
sagittal views were looked at and found to be the standard planes (``--write-reference`` records
it from the first run). There is no ground truth on a real scan; what this measures is whether
every run lands on that frame (a few degrees) rather than its twin (150-180 degrees). Its pitch
(the turn about the left-right axis) is uncertain by several degrees: a symmetric view does not
show it, and no atlas pins it on this scan (``bench_real_pitch.py``).

``--fabian`` also reconstructs each subject of the FaBiAN stacks (simulated normal brains from
another atlas family; ``bench_real_stacks.py``) with the atlas whose brain volume is nearest its
mask's, and measures ``G`` against the identity: the files' world frame is the simulated brain's
anatomical frame, a second brain unlike the training atlas's, with a reference from the files
rather than from a look; and against the files' frame levelled on the brain's mid-sagittal plane
as measured on the raw stacks (only the files' pitch is then the reference: one subject's files'
``x = 0`` is 5-6 degrees from its brain's symmetry plane). The output's last turns are shown
beside it. ``--fabian-atlas-family`` takes each subject's atlas from another family.

Run from the repository root (about 2-4 minutes per run on one core)::

    python benchmarks/bench_real_frame.py [--threads 1 2] [--out runs/real-frame] [--fabian] \
        [--auto-masks] [--atlas AGE_FOLDER ...] [--fabian-atlas-family FOLDER] \
        [--write-reference] [--polish F] [--slice-trajectory] \
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
from collections.abc import Sequence
from pathlib import Path

import nibabel as nib
import numpy as np
from bench_common import (
    ATLAS,
    FABIAN,
    FABIAN_STACKS,
    SHARED,
    scanner_from_canonical,
    verdict_in,
    write_results,
)
from scipy.spatial.transform import Rotation

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


def _reconstruct(
    stacks: list[str],
    masks: list[str],
    atlas: Path | Sequence[Path],
    model: str,
    output: Path,
    threads: int,
    options: tuple[str, ...] = (),
) -> tuple[str, float]:
    """``svr reconstruct --registration cnn`` in a fresh process; its log and wall seconds.

    The log (``-v``) is also written beside the output (``.stderr.txt``).

    ``atlas``: one atlas folder (``srr.nii.gz``, ``mask.nii.gz``) or several (the output takes
    the first's frame unless another fits clearly better).
    """
    folders = [atlas] if isinstance(atlas, Path) else list(atlas)
    command = [
        sys.executable, "-m", "svr", "reconstruct", "--input-stacks", *stacks,
        *(["--stack-masks", *masks] if masks else []), "--registration", "cnn", "--model", model,
        "--atlas-volume", *(str(f / "srr.nii.gz") for f in folders),
        "--atlas-mask", *(str(f / "mask.nii.gz") for f in folders),
        "--output-volume", str(output), "--output-transforms", str(_beside(output, ".csv")),
        "--output-qa", str(_beside(output, ".png")),
        "--overwrite", "-v", *options,
    ]  # fmt: skip
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    began = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - began
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
    _beside(output, ".stderr.txt").write_text(done.stderr, encoding="utf-8")
    return done.stderr, seconds


def _beside(output: Path, suffix: str) -> Path:
    """A file written beside an output volume (its transforms table, its QA figure)."""
    return output.with_name(output.name.split(".")[0] + suffix)


def _mask_ml(path: Path) -> float:
    """A brain mask's volume in millilitres."""
    image = nib.load(path)
    voxels = int((np.asarray(image.dataobj) > 0.5).sum())
    return voxels * abs(float(np.linalg.det(image.affine[:3, :3]))) / 1000.0


def nearest_atlas(mask: Path, family: Path = ATLAS) -> Path:
    """The age folder of an atlas ``family`` whose brain mask's volume is nearest ``mask``'s."""
    folders = sorted(p.parent for p in family.glob("GA*/mask.nii.gz"))
    ml = _mask_ml(mask)
    return min(folders, key=lambda f: abs(_mask_ml(f / "mask.nii.gz") - ml))


def levelled_frame(normals: Sequence[np.ndarray]) -> np.ndarray:
    """(4, 4) the world frame turned, by the least rotation, so that its x axis is the normal.

    ``normals``: (3,) mid-sagittal normals in the world frame (x component > 0), averaged.
    """
    normal = np.mean([n / np.linalg.norm(n) for n in normals], axis=0)
    normal = normal / np.linalg.norm(normal)
    axis = np.cross([1.0, 0.0, 0.0], normal)
    sine, cosine = float(np.linalg.norm(axis)), float(normal[0])
    frame = np.eye(4)
    if sine > 1e-12:
        frame[:3, :3] = Rotation.from_rotvec(axis / sine * math.atan2(sine, cosine)).as_matrix()
    return frame


def fabian_rows(
    model: str,
    threads: list[int],
    out: Path,
    options: tuple[str, ...] = (),
    family: Path = ATLAS,
) -> list[str]:
    """One row per FaBiAN subject and thread count: its output frame vs the files' frame.

    Also against the files' frame levelled on the brain's own mid-sagittal plane, measured on
    each raw stack (:func:`midplane_oracle.midplane_in_world`, SimpleITK, no library code): the
    canonical frame's ``x = 0`` is that plane, and where the files' frame is tilted from it only
    its pitch is a reference.

    ``options``: more ``svr reconstruct`` options for every run; ``family``: the atlas family
    (a folder of ``GA*`` age folders) whose nearest age is each subject's atlas.
    """
    from midplane_oracle import midplane_in_world  # it imports this module

    subjects: dict[str, list[str]] = {}
    for name in FABIAN_STACKS:
        subjects.setdefault(name.split("_")[0], []).append(name)
    rows = []
    for subject, names in subjects.items():
        stacks = [str(FABIAN / n) for n in names]
        masks = [str(FABIAN / FABIAN_STACKS[n]) for n in names]
        atlas = nearest_atlas(FABIAN / FABIAN_STACKS[names[0]], family)
        planes = [midplane_in_world(FABIAN / n, FABIAN / FABIAN_STACKS[n]) for n in names]
        levelled = levelled_frame([plane.normal for plane in planes])
        tilts = ", ".join(f"{plane.tilt_deg:.1f}" for plane in planes)
        for n in threads:
            tag = "" if family == ATLAS else f"-{atlas.name}"
            output = out / f"fabian-{subject}{tag}-cnn-{n}t.nii.gz"
            log, seconds = _reconstruct(
                stacks, masks, atlas, model, output, n, ("--thicknesses", "3.2", *options)
            )
            frame = scanner_from_canonical(_beside(output, ".csv"))
            angle = frame_angle_deg(np.eye(4), frame)
            turns = frame_angle_deg(np.eye(4), nib.load(output).affine)
            split = "split" if "stacks disagree" in log else "agree"
            rows.append(
                f"| {subject.removeprefix('sub-')} | {len(names)} | {atlas.name} | {n} | "
                f"**{angle:.1f}** | {tilts} | **{frame_angle_deg(levelled, frame):.1f}** | "
                f"{turns:.1f} | {split} | {verdict_in(log)} | {seconds:.0f} |"
            )
            print(rows[-1], flush=True)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scan", type=Path, default=SCAN, help="the real scan's folder")
    parser.add_argument(
        "--atlas",
        type=Path,
        nargs="+",
        default=[ATLAS / "GA28_operated"],
        help="atlas folder(s) of the real scan's run; several, the preferred first: the output "
        "takes its frame unless another fits clearly better",
    )
    parser.add_argument("--model", default="stack-pose")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--reference", type=Path, default=REFERENCE)
    parser.add_argument(
        "--write-reference",
        action="store_true",
        help="record the first run's frame as the reference (after its views were looked at)",
    )
    parser.add_argument(
        "--auto-masks", action="store_true", help="the automatic masks (the README's example)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "real-frame")
    parser.add_argument("--results", type=Path, help="also write the table here (markdown)")
    parser.add_argument(
        "--polish", type=float, help="svr reconstruct's --polish (default: its own)"
    )
    parser.add_argument(
        "--fabian", action="store_true", help="also the FaBiAN subjects' output frames"
    )
    parser.add_argument(
        "--fabian-atlas-family",
        type=Path,
        default=ATLAS,
        help="the atlas family (GA* age folders) whose age nearest each FaBiAN subject's brain "
        "volume is its atlas (default: the spina bifida atlas)",
    )
    parser.add_argument(
        "--slice-trajectory",
        action="store_true",
        help="svr reconstruct's --slice-trajectory (a calm head's slices on their trajectories)",
    )
    args = parser.parse_args()
    recorded = json.loads(args.reference.read_text(encoding="utf-8"))
    if "scanner_from_canonical" not in recorded and not args.write_reference:
        parser.error(f"--reference {args.reference}: no 'scanner_from_canonical' frame recorded")
    reference = np.asarray(recorded.get("scanner_from_canonical", np.eye(4)))
    runs = range(1, 7)
    stacks = [str(args.scan / f"sub-01_run-{i}_T2w.nii.gz") for i in runs]
    masks = [str(args.scan / f"sub-01_run-{i}_T2w_desc-brain_mask.nii.gz") for i in runs]
    args.out.mkdir(parents=True, exist_ok=True)
    rows, frames = [], []
    tag = "auto" if args.auto_masks else "manual"
    options = () if args.polish is None else ("--polish", str(args.polish))
    if args.slice_trajectory:
        options += ("--slice-trajectory",)
    for threads in args.threads:
        other = "" if args.atlas == [ATLAS / "GA28_operated"] else f"-{args.atlas[0].name}"
        output = args.out / f"real-cnn-{tag}{other}-{threads}t.nii.gz"
        log, seconds = _reconstruct(
            stacks,
            [] if args.auto_masks else masks,
            args.atlas,
            args.model,
            output,
            threads,
            options,
        )
        match = FRAME_LINE.search(log)
        start, detail = (match.group(3), match.group(4)) if match else ("?", "")
        frame = scanner_from_canonical(_beside(output, ".csv"))
        frames.append(frame)
        if args.write_reference and len(frames) == 1:
            reference = frame
            record = {
                "what": f"canonical mm -> scanner mm frame G (benchmarks/bench_common."
                f"scanner_from_canonical) of {output.name}: svr reconstruct --registration cnn "
                f"of the real scan (sub-01, runs 1-6, {tag} masks, atlas "
                f"{', '.join(a.name for a in args.atlas)}, {datetime.date.today().isoformat()}), "
                "whose axial, coronal and sagittal views were looked at and are the standard "
                "planes; the reference frame of benchmarks/bench_real_frame.py",
                "scanner_from_canonical": np.round(frame, 6).tolist(),
            }
            args.reference.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
        angle = frame_angle_deg(reference, frame)
        final = detail.split("; coarse")[0].removeprefix("final NCC ")
        rows.append(
            f"| {tag} | {threads} | **{angle:.1f}** | {start} | {final} | {verdict_in(log)} | "
            f"{seconds:.0f} |"
        )
        print(rows[-1], flush=True)
    spread = max(
        (frame_angle_deg(a, b) for i, a in enumerate(frames) for b in frames[i + 1 :]),
        default=0.0,
    )
    lines = [
        "| masks | threads | frame vs reference (deg) | start kept | final NCC of the frames "
        "compared | verdict | wall (s) |",
        "|---|---:|---:|---|---|---|---:|",
        *rows,
        "",
        f"Largest angle between two runs' frames: {spread:.1f} deg.",
    ]
    if args.fabian:
        lines += [
            "",
            "FaBiAN subjects (output frame against the files' world frame):",
            "",
            "| subject | stacks | atlas | threads | frame vs files' frame (deg) | the brain's "
            "mid-sagittal plane vs the files' x = 0, per stack (deg) | frame vs the files' frame "
            "levelled on it (deg) | last turns of the output (deg) | stacks' frames | verdict | "
            "wall (s) |",
            "|---|---:|---|---:|---:|---|---:|---:|---|---|---:|",
            *fabian_rows(args.model, args.threads, args.out, options, args.fabian_atlas_family),
        ]
    text = "\n".join(lines)
    print(text)
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
