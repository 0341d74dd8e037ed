r"""The paper's claim per slice, in context: one stack-pose network trained with each loss.

Each slice of simulated cases placed as ``svr reconstruct --registration cnn`` starts it (its
interleaved packet's transform from the network alone, before any registration), by networks
trained alike with the SE(3) geodesic loss and with the PoseNet, Anchor Points and 6D baselines.
The measurement is ``svr evaluate --cases`` (run here, its report kept under ``--report``); this
script adds, per group of cases, each loss against the reference loss on the same slices: the
ratio of median rotation errors, the share of slices where it is worse, and the Wilcoxon
signed-rank test.

Train the runs (one core each, same seed and steps)::

    svr train-stack-pose --atlas-dir ATLAS --hold-out 24 28 32 --motion-path MOTION \\
        --output-dir runs/slice-losses/LOSS --steps 3000 --fine-tune-steps 0 \\
        --learning-rate 3e-4 --loss LOSS --seed 0

then, from the repository root::

    python benchmarks/bench_slice_losses.py --checkpoints se3=runs/slice-losses/se3 \\
        posenet=runs/slice-losses/posenet anchor=runs/slice-losses/anchor \\
        rot6d=runs/slice-losses/rot6d --cases CASE [CASE ...] \\
        --group training=sb24,sb28,sb32 held-out=wu,crl \\
        --report runs/slice-losses/report --results benchmarks/results/slice-losses.md
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import wilcoxon

from svr.cli import main as svr_main


def read_report(report: Path) -> tuple[dict[str, dict[str, np.ndarray]], np.ndarray]:
    """Per method, each metric's per-slice values; and each slice's case (folder name)."""
    with (report / "per_slice.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    metrics = [k for k in rows[0] if k not in ("method", "slice")]
    methods: dict[str, dict[str, list[float]]] = {}
    for row in rows:
        per = methods.setdefault(row["method"], {k: [] for k in metrics})
        for k in metrics:
            per[k].append(float(row[k]))
    with (report / "poses.csv").open(newline="") as f:
        cases = [Path(r["volume"]).name for r in csv.DictReader(f) if r["poses"] == "true"]
    arrays = {m: {k: np.asarray(v) for k, v in per.items()} for m, per in methods.items()}
    return arrays, np.asarray(cases)


def group_of(cases: np.ndarray, groups: dict[str, tuple[str, ...]]) -> dict[str, np.ndarray]:
    """(N,) bool per group: the slices of cases whose name starts with one of its prefixes."""
    out = {"all": np.ones(len(cases), dtype=bool)}
    for name, prefixes in groups.items():
        out[name] = np.array([c.startswith(prefixes) for c in cases])
    return out


def table(
    results: dict[str, dict[str, np.ndarray]], masks: dict[str, np.ndarray], reference: str
) -> tuple[list[str], dict]:
    """Markdown rows and a JSON summary: each loss per group, against ``reference``."""
    lines = [
        "| cases | loss | slices | rotation median / p90 (deg) | within 5 / 10 deg | "
        "translation median (mm) | CC mean | vs "
        f"{reference}: median ratio | worse than {reference} | Wilcoxon p |",
        "|---|---|---:|---|---|---:|---:|---:|---:|---:|",
    ]
    summary: dict = {}
    for group, mask in masks.items():
        ref = results[reference]["rotation_deg"][mask]
        for method, per in results.items():
            rot = per["rotation_deg"][mask]
            if method == reference:
                ratio, worse, p = "1.00", "-", "-"
            else:
                ratio = f"{np.median(rot) / np.median(ref):.2f}"
                worse = f"{100 * (rot > ref).mean():.0f} %"
                p = f"{wilcoxon(rot, ref).pvalue:.2g}"
            entry = {
                "slices": int(mask.sum()),
                "median_deg": float(np.median(rot)),
                "p90_deg": float(np.percentile(rot, 90)),
                "within5": float((rot <= 5).mean()),
                "within10": float((rot <= 10).mean()),
                "median_mm": float(np.median(per["translation_mm"][mask])),
                "cc_mean": float(np.mean(per["cc"][mask])),
            }
            summary[f"{group}/{method}"] = entry
            lines.append(
                f"| {group} | {method} | {entry['slices']} | {entry['median_deg']:.1f} / "
                f"{entry['p90_deg']:.1f} | {100 * entry['within5']:.0f} % / "
                f"{100 * entry['within10']:.0f} % | {entry['median_mm']:.1f} | "
                f"{entry['cc_mean']:.3f} | {ratio} | {worse} | {p} |"
            )
    return lines, summary


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoints", nargs="+", required=True, metavar="NAME=DIR")
    parser.add_argument("--cases", nargs="+", required=True, type=Path)
    parser.add_argument("--reference", default="se3", help="the loss the others are paired with")
    parser.add_argument(
        "--group",
        nargs="*",
        default=[],
        metavar="NAME=PREFIX,...",
        help="groups of cases by folder-name prefixes, reported beside all cases",
    )
    parser.add_argument("--report", type=Path, required=True, help="svr evaluate's report folder")
    parser.add_argument("--results", type=Path, default=None)
    args = parser.parse_args()
    names = [spec.partition("=")[0] for spec in args.checkpoints]
    if args.reference not in names:
        parser.error(f"--reference {args.reference} must be one of the --checkpoints names")
    groups = {}
    for spec in args.group:
        name, _, prefixes = spec.partition("=")
        groups[name] = tuple(p for p in prefixes.split(",") if p)
    if not (args.report / "per_slice.csv").is_file():
        code = svr_main(
            [
                "evaluate",
                "--checkpoints",
                *args.checkpoints,
                "--cases",
                *map(str, args.cases),
                "--output-dir",
                str(args.report),
                "--device",
                "cpu",
                "--quiet",
            ]
        )
        if code:
            return code
    results, cases = read_report(args.report)
    lines, summary = table(results, group_of(cases, groups), args.reference)
    case_list = ", ".join(sorted(set(cases.tolist())))
    text = "\n".join([f"Cases: {case_list}.", "", *lines])
    print(text)
    if args.results is not None:
        command = "python benchmarks/bench_slice_losses.py " + " ".join(sys.argv[1:])
        args.results.write_text(
            f"# Per slice in context: the losses\n\nCommand: `{command}`\n\n{text}\n",
            encoding="utf-8",
        )
        args.results.with_suffix(".json").write_text(
            json.dumps(summary, indent=1) + "\n", encoding="utf-8"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
