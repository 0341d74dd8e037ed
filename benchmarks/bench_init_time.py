"""Time of the learned initialisation against stack registration alone, on the bench cases.

``learned_start`` (each stack and each of its interleaved packets placed by the
stack-pose model; stack registration from the three starts; the per-stack NCC choice against the
other stacks) against ``stack_registration`` alone; the network's placement by itself
(``network_placement``: every stack's and packet's transform, what places each slice before
registration), per slice; and the per-stack estimates by themselves. The figure the issue bounds
is the time added per stack. The "--packets 1" row leaves the packets out (one stack
registration fewer).

Run from the repository root::

    python benchmarks/bench_init_time.py [--threads 2] [--model stack-pose] \
        [--results benchmarks/results/init-time.md]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from bench_common import SHARED, load_case_stacks

from svr.models.slice_refiner import shipped_slice_refiners
from svr.models.stack_pose import StackPoseNet, load_stack_pose_model
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation import initialise
from svr.reconstruction.initialisation.learned import learned_start, network_placement
from svr.reconstruction.initialisation.slice_refinement import place_slices
from svr.reconstruction.initialisation.stack_pose import estimate_stack_pose
from svr.reconstruction.registration import stack_registration
from svr.reconstruction.slices import SliceSet, extract_slices
from svr.sampling.volume import load_canonical_volume


def timed(repeats: int, work: Callable[..., object], *args: object) -> float:
    """Median wall time (s) of ``repeats`` calls of ``work(*args)``."""
    seconds = []
    for _ in range(repeats):
        began = time.perf_counter()
        work(*args)
        seconds.append(time.perf_counter() - began)
    return statistics.median(seconds)


def estimates(model: StackPoseNet, stacks: list) -> None:
    """Each stack's own estimate, alone."""
    for stack in stacks:
        estimate_stack_pose(model, stack.image, stack.mask.data > 0.5, restart_deg=10.0)


def refiner_time(
    repeats: int,
    slices: SliceSet,
    stacks: list,
    model: StackPoseNet,
    config: ReconstructionConfig,
    atlas_folder: Path,
) -> float:
    """Median seconds per slice of the slice refiner with its keep rule, from the learned start.

    The first call is left out of the median (once per process: the refiner's first
    convolutions); ``repeats`` calls are timed after it.
    """
    start = initialise(slices, stacks, config, model)
    atlas = load_canonical_volume(atlas_folder / "srr.nii.gz", atlas_folder / "mask.nii.gz")
    steps = config.initialisation.slice_refiner_steps
    stages = list(zip(shipped_slice_refiners(), steps, strict=True))
    grid = config.initialisation_grid_mm
    place_slices(start.slices, atlas, stages, grid)
    return timed(repeats, place_slices, start.slices, atlas, stages, grid) / len(slices)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="stack-pose")
    parser.add_argument(
        "--cases",
        nargs="*",
        type=Path,
        default=[Path("sb24-large"), Path("sb28-moderate")],
        help="bench case names, or case folders",
    )
    parser.add_argument(
        "--atlases",
        nargs="*",
        type=Path,
        default=[],
        help="one atlas age folder per case: also time the slice refiner against it",
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--results", type=Path, help="also write the table here (markdown)")
    parser.add_argument(
        "--repeats", type=int, default=3, help="time each step this many times, keep the median"
    )
    args = parser.parse_args()
    if args.atlases and len(args.atlases) != len(args.cases):
        parser.error(f"--atlases: one per case ({len(args.cases)}), got {len(args.atlases)}")
    torch.set_num_threads(args.threads)
    model = load_stack_pose_model(args.model)
    rows = []
    for index, name in enumerate(args.cases):
        case = name if name.exists() else SHARED / "data" / "bench" / str(name)
        stacks = load_case_stacks(case)
        slices = extract_slices(stacks)
        config = ReconstructionConfig.preset("learned")
        registration = timed(
            args.repeats, stack_registration, slices, config.initialisation_grid_mm
        )
        alone = timed(args.repeats, estimates, model, stacks) / len(stacks)
        variants = (
            ("model", config),
            ("model, --packets 1", dataclasses.replace(config, packets=1)),
        )
        for label, settings in variants:
            full = timed(args.repeats, learned_start, slices, stacks, model, settings)
            placement = timed(
                args.repeats,
                network_placement,
                stacks,
                model,
                settings.packets,
                settings.initialisation.restart_deg,
            )
            per_slice_ms = 1000.0 * placement / len(slices)
            added = (full - registration) / len(stacks)
            refiner = "" if not args.atlases else "-"
            if args.atlases and label == "model":
                refiner_ms = 1000.0 * refiner_time(
                    args.repeats, slices, stacks, model, settings, args.atlases[index]
                )
                refiner = f"{refiner_ms:.1f} ms ({args.atlases[index].name})"
            rows.append(
                f"| {case.name} ({len(stacks)} stacks, {len(slices)} slices) | {label} | "
                f"{registration:.1f} s | {full:.1f} s (x{full / registration:.2f}) | "
                f"{per_slice_ms:.1f} ms | {alone:.2f} s | {added:.2f} s |"
                + (f" {refiner} |" if args.atlases else "")
            )
            print(
                f"{case.name}, {label} ({args.threads} threads): "
                f"stack registration {registration:.1f} s, "
                f"learned initialisation {full:.1f} s (x{full / registration:.2f}); "
                f"network placement {per_slice_ms:.1f} ms per slice; "
                f"estimate {alone:.2f} s per stack; added {added:.2f} s per stack"
                + (f"; slice refiner {refiner} per slice" if refiner not in ("", "-") else ""),
                flush=True,
            )
    if args.results is not None:
        command = "python benchmarks/bench_init_time.py " + " ".join(
            [
                f"--threads {args.threads}",
                f"--model {args.model}",
                f"--repeats {args.repeats}",
                "--cases",
                *map(str, args.cases),
                *(["--atlases", *map(str, args.atlases)] if args.atlases else []),
            ]
        )
        lines = [
            "# Time of the learned initialisation against stack registration alone",
            "",
            f"Command: `{command}`",
            f"Measured {datetime.date.today().isoformat()}, {args.threads} torch threads; each "
            f"time the median of {args.repeats} runs.",
            "",
            "| case | learned initialisation | stack registration | learned (ratio) | "
            "network placement per slice | estimate per stack | added per stack |"
            + (" slice refiner per slice (atlas) |" if args.atlases else ""),
            "|---|---|---:|---:|---:|---:|---:|" + ("---:|" if args.atlases else ""),
            *rows,
            "",
        ]
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text("\n".join(lines), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
