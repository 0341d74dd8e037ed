"""Reconstruction benchmark: quality, time per phase, CPU time and peak memory on the bench cases.

Runs ``svr reconstruct`` as a child process on each bench case (``../shared/data/bench``) with
each registration, scores the volume with the shared yardstick (``../shared/tools/score_recon.py``:
PSNR, SSIM and NCC inside the ground-truth brain mask after rigid alignment and a linear intensity
fit), and prints one table with the peers' figures from ``../shared/reference/peer_results.md``
and the ratios ours / peer. Wall time, CPU time (user + sys) and peak resident memory are those of
the child process (``os.wait4``); the time per phase comes from the run's ``--output-log``.

``--masks`` chooses where the brain masks come from: ``manual`` (the case's ``masks/``, the
default), ``network`` (none given: ``svr reconstruct`` finds them with the shipped network),
``fused`` (the network's masks fused across the stacks, ``--fuse-masks``) or ``otsu``
(``--auto-masks otsu``). With more than one, the table also gives each automatic kind's PSNR
difference from the manual masks' on the same case and registration (issue 14: automatic masks
must not cost the reconstruction).

Run from the repository root (``--threads 2`` for the 2-core comparison)::

    python benchmarks/bench_reconstruct.py [--cases sb28-moderate sb24-large]
        [--registrations stack cnn] [--masks manual network fused otsu] [--device cpu]
        [--out runs/bench-reconstruct]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
PEER_NAMES = ("SVRTK", "NeSVoR")
MASK_KINDS = ("manual", "network", "fused", "otsu")


def mask_options(kind: str, masks: list[Path]) -> list[str]:
    """``svr reconstruct``'s mask options for a kind of ``--masks``."""
    if kind == "manual":
        return ["--stack-masks", *map(str, masks)]
    if kind == "fused":
        return ["--fuse-masks"]
    return ["--auto-masks", kind]


def peer_figures(path: Path) -> dict[tuple[str, str], dict[str, float]]:
    """(case, peer) -> PSNR, SSIM, NCC and CPU seconds read from the peers' results table."""
    figures: dict[tuple[str, str], dict[str, float]] = {}
    if not path.exists():
        return figures
    for line in path.read_text().splitlines():
        cells = [c.strip().replace("*", "") for c in line.strip().strip("|").split("|")]
        if len(cells) < 6:
            continue
        case, method = cells[0], cells[1]
        peer = next((p for p in PEER_NAMES if method.startswith(p)), None)
        if peer is None:
            continue
        try:
            row = {"psnr": float(cells[2]), "ssim": float(cells[3]), "ncc": float(cells[4])}
        except ValueError:
            continue
        cpu = re.search(r"([\d.]+) CPU-s", cells[5])
        if cpu:
            row["cpu_s"] = float(cpu.group(1))
        figures[(case, peer)] = row
    return figures


def run_child(command: list[str], threads: int) -> tuple[int, float, float, float]:
    """Run a command; return its exit code, wall s, CPU s (user + sys) and peak RSS in MB."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    start = time.perf_counter()
    process = subprocess.Popen(command, env=env)
    _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    code = os.waitstatus_to_exitcode(status)
    return code, wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def phase_times(log: Path) -> dict[str, float]:
    """The ``time per phase`` block of a ``--output-log`` file."""
    phases: dict[str, float] = {}
    inside = False
    for line in log.read_text().splitlines():
        if line.startswith("time per phase"):
            inside = True
            continue
        if inside:
            match = re.match(r"\s+(.+): ([\d.]+)$", line)
            if not match:
                break
            phases[match.group(1)] = float(match.group(2))
    return phases


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["sb28-moderate", "sb24-large"])
    parser.add_argument("--registrations", nargs="+", default=["stack", "cnn"])
    parser.add_argument("--masks", nargs="+", default=["manual"], choices=MASK_KINDS)
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument("--scorer", type=Path, default=SHARED / "tools" / "score_recon.py")
    parser.add_argument("--peers", type=Path, default=SHARED / "reference" / "peer_results.md")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-reconstruct")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    if not args.data.is_dir():
        print(f"{args.data}: bench cases not found", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    peers = peer_figures(args.peers)
    rows = []
    for case in args.cases:
        folder = args.data / case
        thickness = json.loads((folder / "case.json").read_text())["thickness"]
        stacks = sorted((folder / "stacks").glob("*.nii.gz"))
        masks = [folder / "masks" / s.name.replace(".nii.gz", "_mask.nii.gz") for s in stacks]
        for registration, kind in [(r, k) for r in args.registrations for k in args.masks]:
            method = registration if kind == "manual" else f"{registration}, {kind} masks"
            stem = args.out / (f"{case}-{registration}" + ("" if kind == "manual" else f"-{kind}"))
            command = [
                sys.executable, "-m", "svr", "reconstruct",
                "--input-stacks", *map(str, stacks),
                *mask_options(kind, masks),
                "--thicknesses", *map(str, thickness),
                "--registration", registration,
                "--output-volume", f"{stem}.nii.gz",
                "--output-transforms", f"{stem}.csv",
                "--output-qa", f"{stem}.png",
                "--output-log", f"{stem}.log",
                "--device", args.device,
                "--overwrite", "--quiet",
            ]  # fmt: skip
            code, wall, cpu, rss = run_child(command, args.threads)
            if code != 0:
                print(f"{case} {method}: svr reconstruct failed ({code})", file=sys.stderr)
                return 1
            score = json.loads(
                subprocess.run(
                    [sys.executable, str(args.scorer), f"{stem}.nii.gz", str(folder)],
                    capture_output=True, text=True, check=True,
                ).stdout.strip().splitlines()[-1]
            )  # fmt: skip
            phases = phase_times(Path(f"{stem}.log"))
            rows.append((case, method, score, wall, cpu, rss, phases))
            print(f"{case} {method}: {score} wall {wall:.1f} s, CPU {cpu:.1f} s, "
                  f"peak {rss:.0f} MB; phases {phases}", flush=True)  # fmt: skip

    print("\n| case | method | PSNR (dB) | SSIM | NCC | wall (s) | CPU (s) | peak (MB) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for case in args.cases:
        for _, method, score, wall, cpu, rss, _ in [row for row in rows if row[0] == case]:
            quality = f"{score['psnr']:.2f} | {score['ssim']:.4f} | {score['ncc']:.4f}"
            print(f"| {case} | ours, {method} | {quality} | {wall:.1f} | {cpu:.1f} | {rss:.0f} |")
        for peer in PEER_NAMES:
            p = peers.get((case, peer))
            if p:
                print(f"| {case} | {peer} (peer_results.md) | {p['psnr']:.2f} | {p['ssim']:.3f} | "
                      f"{p['ncc']:.3f} | — | {p.get('cpu_s', float('nan')):.0f} | — |")  # fmt: skip
    print("\nRatios ours / peer (PSNR difference in dB):")
    for case, method, score, _, cpu, _, _ in rows:
        for peer in PEER_NAMES:
            p = peers.get((case, peer))
            if p:
                cpu_ratio = f", CPU time x{cpu / p['cpu_s']:.2f}" if "cpu_s" in p else ""
                print(
                    f"  {case} {method} vs {peer}: PSNR {score['psnr'] - p['psnr']:+.2f} dB, "
                    f"SSIM x{score['ssim'] / p['ssim']:.3f}, NCC x{score['ncc'] / p['ncc']:.3f}"
                    f"{cpu_ratio}"
                )
    scored = {(case, method): score for case, method, score, *_ in rows}
    automatic = [row for row in rows if row[1].endswith(" masks")]
    if automatic:
        print("\nAutomatic masks against the manual masks (same case and registration):")
        for case, method, score, *_ in automatic:
            ref = scored.get((case, method.split(",")[0]))  # the manual masks' run
            if ref:
                print(
                    f"  {case} {method}: PSNR {score['psnr'] - ref['psnr']:+.2f} dB, "
                    f"SSIM x{score['ssim'] / ref['ssim']:.3f}, NCC x{score['ncc'] / ref['ncc']:.3f}"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
