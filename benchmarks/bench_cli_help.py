r"""How long ``svr --help`` and ``svr reconstruct --help`` take, against starting Python alone.

Building the parser imports no torch (the options read library defaults from light modules), so
the help is about as quick as the interpreter's start. Each command runs ``--runs`` times as a
whole process; the median wall time is printed beside Python's own start-up and the ratio::

    python benchmarks/bench_cli_help.py --runs 9 --results benchmarks/results/cli-help.md
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

COMMANDS = {
    "python -c pass": [sys.executable, "-c", "pass"],
    "svr --help": [sys.executable, "-m", "svr", "--help"],
    "svr reconstruct --help": [sys.executable, "-m", "svr", "reconstruct", "--help"],
    "svr bids --help": [sys.executable, "-m", "svr", "bids", "--help"],
}


def median_seconds(argv: list[str], runs: int) -> float:
    times = []
    for _ in range(runs + 1):  # the first run warms the file cache and is not counted
        began = time.perf_counter()
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, cwd="/")
        times.append(time.perf_counter() - began)
    return statistics.median(times[1:])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=9)
    parser.add_argument("--results", type=Path)
    args = parser.parse_args()
    base = median_seconds(COMMANDS["python -c pass"], args.runs)
    lines = ["| command | median wall (s) | / python start |", "|---|---|---|"]
    for name, argv in COMMANDS.items():
        seconds = base if name == "python -c pass" else median_seconds(argv, args.runs)
        lines.append(f"| `{name}` | {seconds:.3f} | {seconds / base:.1f} |")
    text = "\n".join(lines)
    print(text)
    if args.results is not None:
        args.results.write_text(
            "# `svr --help` speed\n\n"
            f"`python benchmarks/bench_cli_help.py --runs {args.runs}`, median of {args.runs} "
            "whole-process runs each (2-core VM, 2026-12-06):\n\n" + text + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
