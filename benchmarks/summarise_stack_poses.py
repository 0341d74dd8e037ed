"""Per-stack accuracy pooled over runs of ``bench_learned_stack_poses.py`` (its ``.json`` files).

Each run of the bench is one draw of simulated stacks (its ``--seed``); this pools the stacks of
several draws per group (the held-out ages of an atlas folder, each bench case) and prints, per
group and estimate, the number of stacks, the median angle to the true stack pose, the share
within 10 and within 20 degrees and the median centre error, as a markdown table. With
``--against`` it also compares each group's stacks with another model's (same draws: the same
stacks in the same order), pairwise: the stacks that only one of the two placed within 10 degrees
and a two-sided sign test on them (exact binomial).

Run from the repository root::

    python benchmarks/summarise_stack_poses.py RUN_SEED0.json RUN_SEED1.json ...
        [--methods learned] [--label wu] [--against OTHER_SEED0.json ...]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np


def pooled_rows(paths: list[Path]) -> list[dict]:
    """The rows (one per stack) of every results file, in order."""
    rows = []
    for path in paths:
        rows += json.loads(path.read_text(encoding="utf-8"))["rows"]
    return rows


def sign_test(only_a: int, only_b: int) -> float:
    """Two-sided exact sign test of ``only_a`` against ``only_b`` discordant pairs."""
    n = only_a + only_b
    if n == 0:
        return 1.0
    low = min(only_a, only_b)
    tail = sum(math.comb(n, k) for k in range(low + 1)) / 2**n
    return min(1.0, 2 * tail)


def summary_line(label: str, group: str, method: str, members: list[dict]) -> str:
    """One markdown row: n, median, within 10 and 20 degrees, median centre error."""
    rot = np.array([r[method]["rot_deg"] for r in members])
    centre = np.array([r[method]["centre_mm"] for r in members])
    return (
        f"| {label} | {group} | {method} | {len(rot)} | {np.median(rot):.2f} | "
        f"{100 * np.mean(rot <= 10):.1f} % ({int(np.sum(rot <= 10))}) | "
        f"{100 * np.mean(rot <= 20):.1f} % | {np.median(centre):.2f} |"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, nargs="+", help="the bench's .json files")
    parser.add_argument("--methods", nargs="+", default=["learned", "learned, no restarts"])
    parser.add_argument("--label", default="", help="first column (e.g. the model)")
    parser.add_argument("--against", type=Path, nargs="*", default=[])
    args = parser.parse_args()
    rows = pooled_rows(args.results)
    other = pooled_rows(args.against) if args.against else None
    groups = list(dict.fromkeys(r["group"] for r in rows))
    print(
        "| model | stacks | estimate | n | median (deg) | within 10 deg | within 20 deg "
        "| centre median (mm) |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for group in groups:
        members = [r for r in rows if r["group"] == group]
        for method in args.methods:
            print(summary_line(args.label, group, method, members))
    if other is None:
        return 0
    print()
    for group in groups:
        members = [r for r in rows if r["group"] == group]
        theirs = [r for r in other if r["group"] == group]
        if [r["name"] for r in members] != [r["name"] for r in theirs]:
            print(f"- {group}: not the same stacks; no paired comparison")
            continue
        for method in args.methods:
            mine = np.array([r[method]["rot_deg"] <= 10 for r in members])
            base = np.array([r[method]["rot_deg"] <= 10 for r in theirs])
            only_mine, only_base = int(np.sum(mine & ~base)), int(np.sum(base & ~mine))
            print(
                f"- {group}, {method}: within 10 deg {int(mine.sum())} against "
                f"{int(base.sum())} of {len(mine)}; only this model {only_mine}, only the other "
                f"{only_base}; sign test p = {sign_test(only_mine, only_base):.3g}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
