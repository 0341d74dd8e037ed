"""``svr bids`` on this machine: the real scan as a BIDS dataset, and participants in parallel.

Two measurements, each printed as a comparison and written to ``--results``:

* **identity** (``--real``): the real clinical scan (six T2w runs and their manual masks) copied
  into a temporary BIDS dataset (``sub-01/anat/sub-01_run-N_T2w.nii.gz`` + sidecars, masks as a
  derivatives folder ``sub-01_run-N_desc-brain_mask.nii.gz``), reconstructed by ``svr bids ...
  participant`` and by ``svr reconstruct`` on the same stacks, masks and thickness; the two
  volumes must be identical (voxel for voxel and affine). Then the group level over it.
* **scaling** (``--participants N``): N participants simulated from atlas ages (three 1 x 1 x
  3 mm stacks each, real fetal motion at half size), reconstructed by ``svr bids`` with
  ``--n-jobs 1`` and with ``--n-jobs 2`` into fresh folders: wall time and peak memory (the sum
  of the resident memory of the process and its workers, sampled every 0.2 s), as ratios.

Run from the repository root (2 free CPU cores for the scaling)::

    python benchmarks/bench_bids.py --real --participants 4 --results benchmarks/results/bids.md
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch
from bench_common import ATLAS, MOTION, SHARED, write_results

from svr.image import load_nifti, save_nifti
from svr.sampling.simulate import SimulationConfig, simulate_case
from svr.sampling.volume import atlas_volume_paths, load_canonical_volume

REAL = SHARED / "data" / "stacks" / "real-mialsrtk-sub01"
SVR = [sys.executable, "-m", "svr"]


def _tree_rss_mb(pid: int) -> float:
    """Resident memory (MB) of a process and all its descendants, from /proc."""
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        try:
            status = Path(f"/proc/{p}/status").read_text()
            total += next(
                float(line.split()[1]) / 1024
                for line in status.splitlines()
                if line.startswith("VmRSS:")
            )
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (FileNotFoundError, ProcessLookupError, StopIteration):
            continue
    return total


def run_measured(argv: list[str]) -> tuple[float, float, subprocess.CompletedProcess]:
    """Run a command; its wall time (s) and peak summed memory of its process tree (MB)."""
    began = time.perf_counter()
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = [0.0]

    def sample() -> None:
        while process.poll() is None:
            peak[0] = max(peak[0], _tree_rss_mb(process.pid))
            time.sleep(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    stdout, stderr = process.communicate()
    seconds = time.perf_counter() - began
    sampler.join()
    done = subprocess.CompletedProcess(argv, process.returncode, stdout, stderr)
    if process.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{stderr[-3000:]}")
    return seconds, peak[0], done


def _description(path: Path, name: str, derivative: bool = False) -> None:
    data = {"Name": name, "BIDSVersion": "1.9.0"}
    if derivative:
        data |= {"DatasetType": "derivative", "GeneratedBy": [{"Name": "manual"}]}
    (path / "dataset_description.json").write_text(json.dumps(data), encoding="utf-8")


def identity(work: Path, settings: list[str]) -> list[str]:
    """The real scan through svr bids and svr reconstruct: identical volumes?"""
    bids_dir, masks_dir = work / "real", work / "real-masks"
    for root in (bids_dir, masks_dir):
        (root / "sub-01" / "anat").mkdir(parents=True)
    _description(bids_dir, "real scan")
    _description(masks_dir, "manual masks", derivative=True)
    stacks, masks = [], []
    for run in range(1, 7):
        name = f"sub-01_run-{run}_T2w"
        shutil.copy(REAL / f"{name}.nii.gz", bids_dir / "sub-01" / "anat" / f"{name}.nii.gz")
        shutil.copy(REAL / f"{name}.json", bids_dir / "sub-01" / "anat" / f"{name}.json")
        mask = masks_dir / "sub-01" / "anat" / f"sub-01_run-{run}_desc-brain_mask.nii.gz"
        shutil.copy(REAL / f"{name}_desc-brain_mask.nii.gz", mask)
        stacks.append(str(bids_dir / "sub-01" / "anat" / f"{name}.nii.gz"))
        masks.append(str(mask))
    thickness = json.loads((REAL / "sub-01_run-1_T2w.json").read_text())["SliceThickness"]
    out = work / "real-svr"
    t_bids, m_bids, _ = run_measured(
        [
            *SVR,
            "bids",
            str(bids_dir),
            str(out),
            "participant",
            "--masks-dir",
            str(masks_dir),
            *settings,
        ]
    )
    single = work / "real-reconstruct.nii.gz"
    t_rec, m_rec, _ = run_measured(
        [
            *SVR,
            "reconstruct",
            "--input-stacks",
            *stacks,
            "--stack-masks",
            *masks,
            "--thicknesses",
            str(thickness),
            "--output-volume",
            str(single),
            *settings,
        ]
    )
    run_measured([*SVR, "bids", str(bids_dir), str(out), "group"])
    ours = load_nifti(out / "sub-01" / "anat" / "sub-01_rec-svr_T2w.nii.gz")
    reference = load_nifti(single)
    same = torch.equal(ours.data, reference.data) and torch.equal(ours.affine, reference.affine)
    differ = (
        float((ours.data - reference.data).abs().max())
        if ours.data.shape == reference.data.shape
        else float("nan")
    )
    sidecar = json.loads((out / "sub-01" / "anat" / "sub-01_rec-svr_T2w.json").read_text())
    return [
        "## The real scan as a BIDS dataset",
        "",
        "| run | wall (s) | peak memory (MB) |",
        "|---|---|---|",
        f"| `svr bids ... participant` | {t_bids:.1f} | {m_bids:.0f} |",
        f"| `svr reconstruct` (same stacks, masks, thickness {thickness:g} mm) | {t_rec:.1f} | "
        f"{m_rec:.0f} |",
        "",
        f"Volumes identical: **{'yes' if same else 'NO'}** (largest voxel difference {differ:g}); "
        f"{sidecar['svr']['slices']} slices, {sidecar['svr']['slices_excluded']} excluded, "
        f"initialisation kept: {', '.join(sidecar['svr']['initialisation'].values())}.",
        f"Group page: `{out / 'svr_group.html'}`.",
        "",
    ]


def simulate_participants(work: Path, count: int) -> Path:
    """``count`` participants from atlas ages, one per age, as a BIDS dataset."""
    bids_dir = work / "cohort"
    bids_dir.mkdir()
    _description(bids_dir, "simulated cohort")
    pairs = atlas_volume_paths(ATLAS)
    chosen = [pairs[round(i * (len(pairs) - 1) / max(count - 1, 1))] for i in range(count)]
    for i, (volume_path, mask_path) in enumerate(chosen, start=1):
        volume = load_canonical_volume(volume_path, mask_path)
        case = simulate_case(
            volume,
            SimulationConfig(
                thickness_mm=3.0,
                in_plane_mm=1.0,
                motion="trajectories",
                motion_path=str(MOTION),
                motion_scale=0.5,
                noise=0.02,
                seed=i,
            ),
        )
        anat = bids_dir / f"sub-{i:02d}" / "anat"
        anat.mkdir(parents=True)
        for run, stack in enumerate(case.stacks, start=1):
            save_nifti(stack.image, anat / f"sub-{i:02d}_run-{run}_T2w.nii.gz")
            (anat / f"sub-{i:02d}_run-{run}_T2w.json").write_text('{"SliceThickness": 3.0}')
    return bids_dir


def scaling(work: Path, count: int, settings: list[str]) -> list[str]:
    bids_dir = simulate_participants(work, count)
    rows = {}
    for jobs in (1, 2):
        out = work / f"cohort-svr-{jobs}"
        seconds, peak, done = run_measured(
            [*SVR, "bids", str(bids_dir), str(out), "participant", "--n-jobs", str(jobs), *settings]
        )
        rows[jobs] = (seconds, peak)
        print(
            f"--n-jobs {jobs}: {seconds:.1f} s, peak {peak:.0f} MB; {done.stdout.strip()}",
            flush=True,
        )
    (t1, m1), (t2, m2) = rows[1], rows[2]
    return [
        f"## {count} simulated participants, --n-jobs 1 vs 2",
        "",
        "| --n-jobs | wall (s) | peak memory (MB) |",
        "|---|---|---|",
        f"| 1 | {t1:.1f} | {m1:.0f} |",
        f"| 2 | {t2:.1f} | {m2:.0f} |",
        f"| ratio 2 / 1 | **{t2 / t1:.2f}** | **{m2 / m1:.2f}** |",
        "",
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", action="store_true", help="the identity check on the real scan")
    parser.add_argument("--participants", type=int, default=0, help="scaling over N participants")
    parser.add_argument("--work", type=Path, default=None, help="keep the data here")
    parser.add_argument("--results", type=Path, default=None)
    parser.add_argument(
        "--settings", nargs=argparse.REMAINDER, default=[], help="more options for both commands"
    )
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-bids-"))
    work.mkdir(parents=True, exist_ok=True)
    settings = [*args.settings, "-q"]
    lines = [
        f"Machine: {os.cpu_count()} CPUs; torch {torch.__version__}; {time.strftime('%Y-%m-%d')}.",
        "",
    ]
    if args.real:
        lines += identity(work, settings)
    if args.participants:
        lines += scaling(work, args.participants, settings)
    text = "\n".join(lines)
    print(text)
    if args.results is not None:
        write_results(args.results, "svr bids: the real scan, participants in parallel", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
