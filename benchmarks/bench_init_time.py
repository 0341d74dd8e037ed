"""Time of the learned initialisation against stack registration alone, on the bench cases.

``learned_start`` (each stack and each of its interleaved packets placed by the
stack-pose model, with or without the atlas fit; stack registration from the three starts; the
per-stack NCC choice against the other stacks) against
``stack_registration`` alone, and the per-stack estimates by themselves; the figure the issue
bounds is the time added per stack. Since 2026-11-27 ``learned_start`` with a model
no longer fits each stack to the atlas (the atlas only sets the output frame), so its
"model + atlas" row times the same work as "model"; the per-stack estimate's "model + atlas" row
still times the fit (what ``svr predict --atlas-volume`` does). The "--packets 1" row leaves the
packets out (one stack registration fewer).

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
from bench_common import SHARED, case_age, load_case_stacks, neighbour_atlas

from svr.models.stack_pose import StackPoseNet, load_stack_pose_model
from svr.reconstruction.atlas_fit import atlas_levels
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation.learned import learned_start
from svr.reconstruction.initialisation.stack_pose import estimate_stack_pose
from svr.reconstruction.registration import stack_registration
from svr.reconstruction.slices import extract_slices
from svr.sampling.volume import CanonicalVolume, load_canonical_volume


def timed(repeats: int, work: Callable[..., object], *args: object) -> float:
    """Median wall time (s) of ``repeats`` calls of ``work(*args)``."""
    seconds = []
    for _ in range(repeats):
        began = time.perf_counter()
        work(*args)
        seconds.append(time.perf_counter() - began)
    return statistics.median(seconds)


def estimates(model: StackPoseNet, stacks: list, with_atlas: CanonicalVolume | None) -> None:
    """Each stack's own estimate (with the atlas fit where an atlas is given)."""
    levels = None if with_atlas is None else atlas_levels(with_atlas)
    for stack in stacks:
        estimate_stack_pose(
            model,
            stack.image,
            stack.mask.data > 0.5,
            atlas=with_atlas,
            levels=levels,
            restart_deg=10.0,
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="stack-pose")
    parser.add_argument("--cases", nargs="*", default=["sb24-large", "sb28-moderate"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--results", type=Path, help="also write the table here (markdown)")
    parser.add_argument(
        "--repeats", type=int, default=3, help="time each step this many times, keep the median"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = load_stack_pose_model(args.model)
    rows = []
    for name in args.cases:
        case = SHARED / "data" / "bench" / name
        stacks = load_case_stacks(case)
        slices = extract_slices(stacks)
        atlas = load_canonical_volume(*neighbour_atlas(case_age(case)))
        config = ReconstructionConfig.preset("learned")
        registration = timed(
            args.repeats, stack_registration, slices, config.initialisation_grid_mm
        )
        variants = (
            ("model", None, config),
            ("model + atlas", atlas, config),
            ("model, --packets 1", None, dataclasses.replace(config, packets=1)),
        )
        for label, with_atlas, settings in variants:
            full = timed(args.repeats, learned_start, slices, stacks, model, settings, with_atlas)
            alone = timed(args.repeats, estimates, model, stacks, with_atlas) / len(stacks)
            added = (full - registration) / len(stacks)
            rows.append(
                f"| {name} ({len(stacks)} stacks) | {label} | {registration:.1f} s | "
                f"{full:.1f} s (x{full / registration:.2f}) | {alone:.2f} s | {added:.2f} s |"
            )
            print(
                f"{name}, {label} ({args.threads} threads): "
                f"stack registration {registration:.1f} s, "
                f"learned initialisation {full:.1f} s (x{full / registration:.2f}); "
                f"estimate {alone:.2f} s per stack; added {added:.2f} s per stack",
                flush=True,
            )
    if args.results is not None:
        command = "python benchmarks/bench_init_time.py " + " ".join(
            [
                f"--threads {args.threads}",
                f"--model {args.model}",
                f"--repeats {args.repeats}",
                "--cases",
                *args.cases,
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
            "estimate per stack | added per stack |",
            "|---|---|---:|---:|---:|---:|",
            *rows,
            "",
        ]
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text("\n".join(lines), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
