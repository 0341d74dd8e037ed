"""Reconstruction benchmark: quality, time per phase, CPU time and peak memory on the bench cases.

Runs ``svr reconstruct`` as a child process on each bench case (``../shared/data/bench``) and on
each simulated case asked for, with each registration, mask source and schedule, scores the
volume with the shared yardstick (``../shared/tools/score_recon.py``: PSNR, SSIM and NCC inside
the ground-truth brain mask after rigid alignment and a linear intensity fit), and prints one
table with the peers' figures from ``../shared/reference/peer_results.md`` and the ratios ours /
peer. Wall time, CPU time (user + sys) and peak resident memory are those of the child process
(``os.wait4``); the time per phase and the rounds come from the run's ``--output-log``.

``--masks`` chooses where the brain masks come from: ``manual`` (the case's ``masks/``, the
default), ``network`` (none given: ``svr reconstruct`` finds them with the shipped network),
``fused`` (the network's masks fused across the stacks, ``--fuse-masks``) or ``otsu``
(``--auto-masks otsu``). With more than one, the table also gives each automatic kind's PSNR
difference from the manual masks' on the same case and registration (issue 14: automatic masks
must not cost the reconstruction).

``--schedules fixed adaptive`` runs both schedules of ``svr reconstruct --schedule`` and prints
each case's gain of the adaptive schedule over the fixed one (PSNR, SSIM, wall and CPU time as
ratios, rounds run and whether the slices converged). ``--simulated`` adds cases simulated with
``svr simulate`` from atlas ages other than the bench cases', with real fetal motion trajectories
scaled by 0.3-1.0 and orthogonal or oblique stacks (:data:`SIMULATED`; kept in ``--cases-dir``).

Run from the repository root (``--threads 2`` for the 2-core comparison)::

    python benchmarks/bench_reconstruct.py [--cases sb28-moderate sb24-large]
        [--simulated ga21-traj1.0-obl ...] [--registrations stack cnn]
        [--masks manual network fused otsu] [--schedules fixed adaptive] [--device cpu]
        [--out runs/bench-reconstruct] [--results benchmarks/results/NAME.md]
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

from bench_common import (
    ATLAS,
    SHARED,
    case_age,
    neighbour_atlas,
    output_frame_error,
    run_scorer,
    scanner_frame_copy,
    simulate_cases,
    slice_pose_errors,
    verdict_in,
)

from svr.reconstruction.config import SCHEDULES

ROOT = Path(__file__).resolve().parents[1]
PEER_NAMES = ("SVRTK", "NeSVoR")
MASK_KINDS = ("manual", "network", "fused", "otsu")
# name: (atlas age folder, orientations, motion scale of the real trajectories, stacks, seed);
# ages other than the bench cases' (24, 28).
SIMULATED = {
    "ga21-traj1.0-obl": ("GA21_notoperated", "oblique", 1.0, 4, 121),
    "ga22-traj0.5-orth": ("GA22_notoperated", "orthogonal", 0.5, 3, 122),
    "ga25-traj0.3-obl": ("GA25_operated", "oblique", 0.3, 4, 125),
    "ga26-traj1.0-orth": ("GA26_operated", "orthogonal", 1.0, 3, 126),
    "ga30-traj0.7-obl": ("GA30_operated", "oblique", 0.7, 4, 130),
    "ga33-traj0.5-orth": ("GA33_operated", "orthogonal", 0.5, 3, 133),
    # the fetus turns 30-180 degrees between stacks (issue 27)
    "ga23-traj0.5-turn": ("GA23_notoperated", "orthogonal", 0.5, 3, 223, (30.0, 180.0)),
    "ga27-traj0.3-turn": ("GA27_operated", "oblique", 0.3, 4, 227, (30.0, 180.0)),
    "ga29-traj0.7-turn": ("GA29_operated", "orthogonal", 0.7, 3, 229, (30.0, 180.0)),
    "ga31-traj0.5-turn": ("GA31_operated", "oblique", 0.5, 4, 231, (30.0, 180.0)),
}


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


def cnn_options(registration: str, case: Path, args: argparse.Namespace) -> list[str]:
    """``--model`` and, with ``--atlas-offset``, the neighbouring atlases for a cnn run."""
    if registration != "cnn":
        return []
    options = ["--model", args.model]
    if args.atlas_offset:
        pairs = [
            neighbour_atlas(case_age(case), offset, args.atlas_dir) for offset in args.atlas_offset
        ]
        options += ["--atlas-volume", *(str(volume) for volume, _ in pairs)]
        options += ["--atlas-mask", *(str(mask) for _, mask in pairs)]
    if args.no_slice_refinement:
        options.append("--no-slice-refinement")
    if args.slice_trajectory:
        options.append("--slice-trajectory")
    if args.slice_refiner_steps:
        options += ["--slice-refiner-steps", *map(str, args.slice_refiner_steps)]
    return options


def schedule_options(args: argparse.Namespace) -> list[str]:
    """``svr reconstruct``'s schedule options where the bench sets them."""
    options = []
    if args.converged is not None:
        options += [
            "--converged-deg",
            str(args.converged[0]),
            "--converged-mm",
            str(args.converged[1]),
        ]
    if args.polish is not None:
        options += ["--polish", str(args.polish)]
    if args.iterations is not None:
        options += ["--iterations", str(args.iterations)]
    return options


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


def kept_per_stack(log: Path) -> str:
    """The start each stack kept (``initialisation per stack`` of an ``--output-log``)."""
    lines = log.read_text(encoding="utf-8").splitlines()
    try:
        at = lines.index("initialisation per stack:")
    except ValueError:
        return ""
    kept = []
    for line in lines[at + 1 :]:
        if not line.startswith("  "):
            break
        if not line.startswith("    "):  # a stack's note is indented under it
            kept.append(line.rsplit(":", 1)[-1].strip())
    return ",".join(kept)


def rounds_run(log: Path) -> str:
    """The ``rounds:`` line of a ``--output-log`` summary (``"?"`` if absent)."""
    for line in log.read_text().splitlines():
        if line.startswith("rounds: "):
            return line.removeprefix("rounds: ")
    return "?"


def verdict_line(log: Path) -> str:
    """The verdict of a ``--output-log``, ``""`` if it has none."""
    return verdict_in(log.read_text(encoding="utf-8"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=["sb28-moderate", "sb24-large"])
    parser.add_argument("--simulated", nargs="*", default=[], choices=list(SIMULATED))
    parser.add_argument("--cases-dir", type=Path, default=ROOT / "runs" / "simulated-cases")
    parser.add_argument("--registrations", nargs="+", default=["stack", "cnn"])
    parser.add_argument("--masks", nargs="+", default=["manual"], choices=MASK_KINDS)
    parser.add_argument("--schedules", nargs="+", default=["adaptive"], choices=SCHEDULES)
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument("--scorer", type=Path, default=SHARED / "tools" / "score_recon.py")
    parser.add_argument("--peers", type=Path, default=SHARED / "reference" / "peer_results.md")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-reconstruct")
    parser.add_argument("--results", type=Path, help="also write the report (.md, .json beside)")
    parser.add_argument(
        "--model",
        default="default",
        help="--model of the cnn runs ('none': the classical per-stack chain, needs an atlas)",
    )
    parser.add_argument(
        "--atlas-offset",
        type=float,
        nargs="+",
        default=None,
        help="cnn runs also get --atlas-volume/--atlas-mask: the atlas age nearest the case's "
        "own age plus this many weeks (never the case's own age), one atlas per offset (-1 1: "
        "the ages either side, the first's frame unless the other fits clearly better); "
        "default: no atlas",
    )
    parser.add_argument(
        "--atlas-dir",
        type=Path,
        default=ATLAS,
        help="the atlas family of --atlas-offset (age folders GA<weeks>_*/srr.nii.gz, mask.nii.gz)",
    )
    parser.add_argument(
        "--no-slice-refinement",
        action="store_true",
        help="cnn runs leave the slices at their packets' poses (the refiner's baseline)",
    )
    parser.add_argument(
        "--slice-trajectory",
        action="store_true",
        help="cnn runs put a calm head's refined slices on their packets' trajectories",
    )
    parser.add_argument(
        "--slice-refiner-steps",
        type=int,
        nargs=2,
        default=None,
        help="cnn runs: the slice refiner's wide and fine steps (default: svr reconstruct's)",
    )
    parser.add_argument(
        "--converged",
        type=float,
        nargs=2,
        metavar=("DEG", "MM"),
        help="--converged-deg and --converged-mm of every run (default: svr reconstruct's)",
    )
    parser.add_argument(
        "--polish", type=float, help="--polish of every run (default: svr reconstruct's)"
    )
    parser.add_argument(
        "--iterations", type=int, help="--iterations of every run (default: svr reconstruct's)"
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    if not args.data.is_dir():
        print(f"{args.data}: bench cases not found", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    peers = peer_figures(args.peers)
    folders = [args.data / case for case in args.cases]
    folders += simulate_cases(args.cases_dir, {name: SIMULATED[name] for name in args.simulated})
    report: list[str] = []

    def say(line: str = "") -> None:
        print(line, flush=True)
        report.append(line)

    rows = []
    for folder in folders:
        case = folder.name
        thickness = json.loads((folder / "case.json").read_text())["thickness"]
        stacks = sorted((folder / "stacks").glob("*.nii.gz"))
        masks = [folder / "masks" / s.name.replace(".nii.gz", "_mask.nii.gz") for s in stacks]
        runs = [(r, k, c) for r in args.registrations for k in args.masks for c in args.schedules]
        for registration, kind, schedule in runs:
            method = registration if kind == "manual" else f"{registration}, {kind} masks"
            if len(args.schedules) > 1:
                method += f", {schedule}"
            stem = args.out / "-".join(
                [case, registration] + ([] if kind == "manual" else [kind]) + [schedule]
            )
            command = [
                sys.executable, "-m", "svr", "reconstruct",
                "--input-stacks", *map(str, stacks),
                *mask_options(kind, masks),
                "--thicknesses", *map(str, thickness),
                "--registration", registration,
                *cnn_options(registration, folder, args),
                "--schedule", schedule,
                *schedule_options(args),
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
            score = run_scorer(args.scorer, Path(f"{stem}.nii.gz"), folder)
            # A cnn volume (canonical frame) is also scored relabelled into the scanner frame:
            # the yardstick's score depends on the orientation a volume comes in (bench_common).
            scanner_score, frame_error = None, None
            if registration == "cnn":
                frame_error = output_frame_error(folder, Path(f"{stem}.csv"))
                copy = scanner_frame_copy(
                    Path(f"{stem}.nii.gz"), Path(f"{stem}.csv"), Path(f"{stem}-scanner.nii.gz")
                )
                scanner_score = run_scorer(args.scorer, copy, folder)
            phases = phase_times(Path(f"{stem}.log"))
            rounds = rounds_run(Path(f"{stem}.log"))
            slices = None
            if (folder / "truth_slices.json").exists():
                slices = slice_pose_errors(folder, Path(f"{stem}.csv"))
            rows.append(
                {"case": case, "method": method, "registration": registration, "masks": kind,
                 "schedule": schedule, "score": score, "scanner_frame_score": scanner_score,
                 "frame_error": frame_error, "kept": kept_per_stack(Path(f"{stem}.log")),
                 "slice_errors": slices, "verdict": verdict_line(Path(f"{stem}.log")),
                 "wall_s": wall, "cpu_s": cpu,
                 "peak_mb": rss, "phases_s": phases, "rounds": rounds}
            )  # fmt: skip
            print(f"{case} {method}: {score} wall {wall:.1f} s, CPU {cpu:.1f} s, "
                  f"peak {rss:.0f} MB; rounds {rounds}; slices {slices}; phases {phases}",
                  flush=True)  # fmt: skip

    say("| case | method | PSNR (dB) | SSIM | NCC | wall (s) | CPU (s) | peak (MB) | rounds |")
    say("|---|---|---:|---:|---:|---:|---:|---:|---|")
    for folder in folders:
        for row in [row for row in rows if row["case"] == folder.name]:
            sc = row["score"]
            say(f"| {row['case']} | ours, {row['method']} | {sc['psnr']:.2f} | {sc['ssim']:.4f} | "
                f"{sc['ncc']:.4f} | {row['wall_s']:.1f} | {row['cpu_s']:.1f} | "
                f"{row['peak_mb']:.0f} | {row['rounds']} |")  # fmt: skip
        for peer in PEER_NAMES:
            p = peers.get((folder.name, peer))
            if p:
                say(f"| {folder.name} | {peer} (peer_results.md) | {p['psnr']:.2f} | "
                    f"{p['ssim']:.3f} | {p['ncc']:.3f} | — | "
                    f"{p.get('cpu_s', float('nan')):.0f} | — | |")  # fmt: skip
    say()
    say("Per-slice pose errors after reconstruction (one rigid offset of the frame removed), and")
    say("the verdict:")
    say()
    say(
        "| case | method | median (deg) | 90th pct (deg) | within 5 deg | within 10 deg | verdict |"
    )
    say("|---|---|---:|---:|---:|---:|---|")
    for row in rows:
        e = row["slice_errors"]
        if e is not None:
            say(f"| {row['case']} | {row['method']} | {e['median_deg']:.2f} | {e['p90_deg']:.1f} "
                f"| {e['within_5']:.0f}% | {e['within_10']:.0f}% | {row['verdict']} |")  # fmt: skip
    ratios = []
    for row in rows:
        for peer in PEER_NAMES:
            p = peers.get((row["case"], peer))
            if p:
                sc = row["score"]
                cpu_ratio = f", CPU time x{row['cpu_s'] / p['cpu_s']:.2f}" if "cpu_s" in p else ""
                ratios.append(
                    f"  {row['case']} {row['method']} vs {peer}: PSNR "
                    f"{sc['psnr'] - p['psnr']:+.2f} dB, SSIM x{sc['ssim'] / p['ssim']:.3f}, "
                    f"NCC x{sc['ncc'] / p['ncc']:.3f}{cpu_ratio}"
                )
    if ratios:
        say()
        say("Ratios ours / peer (PSNR difference in dB):")
        for line in ratios:
            say(line)
    framed = [r for r in rows if r["frame_error"] is not None]
    if framed:
        say()
        say("cnn: output frame against the true atlas frame, the start each stack kept, and the")
        say("gain over stack registration (same case and schedule; PSNR as written):")
        for row in framed:
            deg, mm = row["frame_error"]
            ref = next(
                (r for r in rows if r["case"] == row["case"] and r["registration"] == "stack"
                 and r["masks"] == row["masks"] and r["schedule"] == row["schedule"]),
                None,
            )  # fmt: skip
            gain = "" if ref is None else f", {row['score']['psnr'] - ref['score']['psnr']:+.2f} dB"
            say(f"  {row['case']} {row['method']}: frame {deg:.1f} deg / {mm:.1f} mm; "
                f"kept {row['kept']}{gain}")  # fmt: skip
    relabelled = [r for r in rows if r["scanner_frame_score"] is not None]
    if relabelled:
        say()
        say("Canonical-frame volumes scored as written and relabelled into the scanner frame")
        say("(same array, affine premultiplied by the frame the slices' poses give):")
        for row in relabelled:
            sc, rs = row["score"], row["scanner_frame_score"]
            gain = rs["psnr"] - sc["psnr"]
            say(f"  {row['case']} {row['method']}: PSNR {sc['psnr']:.2f} as written, "
                f"{rs['psnr']:.2f} in the scanner frame ({gain:+.2f} dB)")  # fmt: skip
    by_key = {(r["case"], r["registration"], r["masks"], r["schedule"]): r for r in rows}
    automatic = [r for r in rows if r["masks"] != "manual"]
    if automatic:
        say()
        say("Automatic masks against the manual masks (same case, registration and schedule):")
        for row in automatic:
            ref = by_key.get((row["case"], row["registration"], "manual", row["schedule"]))
            if ref:
                sc, rs = row["score"], ref["score"]
                say(f"  {row['case']} {row['method']}: PSNR {sc['psnr'] - rs['psnr']:+.2f} dB, "
                    f"SSIM x{sc['ssim'] / rs['ssim']:.3f}, "
                    f"NCC x{sc['ncc'] / rs['ncc']:.3f}")  # fmt: skip
    adaptive = [r for r in rows if r["schedule"] == "adaptive"]
    pairs = [
        (row, by_key[(row["case"], row["registration"], row["masks"], "fixed")])
        for row in adaptive
        if (row["case"], row["registration"], row["masks"], "fixed") in by_key
    ]
    if pairs:
        say()
        say("Adaptive schedule against the fixed one (same case, registration and masks):")
        say()
        say("| case | method | PSNR fixed | PSNR adaptive | gain (dB) | SSIM ratio | "
            "wall ratio | CPU ratio | rounds (adaptive) |")  # fmt: skip
        say("|---|---|---:|---:|---:|---:|---:|---:|---|")
        for row, ref in pairs:
            sc, rs = row["score"], ref["score"]
            say(f"| {row['case']} | {row['registration']}, {row['masks']} masks | "
                f"{rs['psnr']:.2f} | {sc['psnr']:.2f} | {sc['psnr'] - rs['psnr']:+.2f} | "
                f"x{sc['ssim'] / rs['ssim']:.3f} | x{row['wall_s'] / ref['wall_s']:.2f} | "
                f"x{row['cpu_s'] / ref['cpu_s']:.2f} | {row['rounds']} |")  # fmt: skip
    if args.results is not None:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text("\n".join(report) + "\n", encoding="utf-8")
        args.results.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
        print(f"wrote {args.results} and {args.results.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
