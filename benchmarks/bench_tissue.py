"""Tissue labels, volumes and biometry of reconstructions against the truth, method by method.

Cases (made by ``--prepare``, :mod:`tissue_cases`): atlas ages' own volumes moved into a frame a
few degrees off (``gt-*``), and ``svr reconstruct --registration cnn`` outputs of bench cases
(``recon-*``), each with its true labels. Every method leaves the case's own age out of its
atlases (``hold_out``). Printed per case: the mean Dice over the 8 labels, per label, the volume
error per label and the linear measures' errors; then the summary against the targets.

    python benchmarks/bench_tissue.py --prepare --recon-dir runs/s53   # once
    python benchmarks/bench_tissue.py --methods multi-atlas --results benchmarks/results/tissue.md
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_common import ATLAS, write_results

from svr.image import load_nifti
from svr.tissue.biometry import LINEAR_MEASURES, measure_labels
from svr.tissue.labels import TISSUE_LABELS
from svr.tissue.registration import AtlasRegistrationConfig
from svr.tissue.segment import TissueConfig, segment_volume

ROOT = Path(__file__).resolve().parents[1]
FAMILIES = {"fidon": ATLAS, "wu": Path("/work/atlases/wu"), "crl": Path("/work/atlases/crl")}
RECON_CASES = {  # bench case -> (family, age folder, the output's folder under --recon-dir)
    "sb24-large": ("fidon", "GA24_notoperated", "recon-i"),
    "sb28-moderate": ("fidon", "GA28_operated", "recon-i"),
    "sb32-severe": ("fidon", "GA32_operated", "recon-d"),
    "wu28-severe": ("wu", "GA28_wu", "recon-e"),
    "wu32-severe": ("wu", "GA32_wu", "recon-e"),
    "crl30-severe": ("crl", "GA30_crl", "recon-e"),
}
GT_CASES = {
    "fidon": ("GA24_notoperated", "GA28_operated", "GA32_operated"),
    "wu": ("GA24_wu", "GA28_wu", "GA32_wu"),
}


def dice(a: np.ndarray, b: np.ndarray) -> float:
    total = int(a.sum() + b.sum())
    return 2.0 * int((a & b).sum()) / total if total else 1.0


def prepare(out: Path, recon_dir: Path) -> None:
    from tissue_cases import gt_volume_case, recon_case

    for i, (family, ages) in enumerate(GT_CASES.items()):
        for j, age in enumerate(ages):
            weeks = float(age[2:4])
            gt_volume_case(
                FAMILIES[family] / age, out / f"gt-{family}{int(weeks)}", family, weeks, 10 * i + j
            )
    for case, (family, age, folder) in RECON_CASES.items():
        recon = recon_dir / folder / f"{case}-cnn-adaptive.nii.gz"
        ncc = recon_case(
            recon, FAMILIES[family] / age, out / f"recon-{case}", family, float(age[2:4])
        )
        print(f"{case}: truth placed, NCC {ncc:.3f}")


def run_multi_atlas(
    volume_path: Path, info: dict, config: TissueConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The labels and the rotation the best atlas fit says the volume is turned by."""
    volume = load_nifti(volume_path)
    result = segment_volume(volume, [FAMILIES[info["family"]]], info["weeks"], config)
    best = max(result.atlases, key=lambda fit: fit.weight)
    return result.labels, best.rotation


def true_measures(info: dict) -> dict[str, float]:
    """The linear measures of the case's source age, in the atlas's own frame."""
    image = load_nifti(Path(info["source"]) / "parcellation.nii.gz")
    return measure_labels(image.data.numpy().round().astype(int), image.affine.numpy()).measures_mm


def cli_time(folder: Path, threads: int) -> tuple[float, float]:
    """Wall time (s) and peak memory (MiB) of ``svr segment-volume`` on a case, with a report."""
    import subprocess
    import tempfile

    info = json.loads((folder / "case.json").read_text())
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            "/usr/bin/time", "-f", "peak_kib %M", sys.executable, "-m", "svr", "segment-volume",
            "--input-volume",
            str(folder / "volume.nii.gz"), "--atlas-dir", str(FAMILIES[info["family"]]),
            "--gestational-age", str(info["weeks"]), "--output-labels", f"{tmp}/l.nii.gz",
            "--output-report", f"{tmp}/r.html", "--output-measures", f"{tmp}/m.tsv",
            "--threads", str(threads), "-q",
        ]  # fmt: skip
        env = {**__import__("os").environ, "OMP_NUM_THREADS": str(threads)}
        start = time.perf_counter()
        done = subprocess.run(command, check=True, env=env, capture_output=True, text=True)
        seconds = time.perf_counter() - start
    peak = float(done.stderr.rsplit("peak_kib", 1)[1].split()[0]) / 1024.0
    return seconds, peak


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--cases-dir", type=Path, default=ROOT / "runs" / "tissue-cases")
    parser.add_argument("--cases", nargs="*", default=None, help="default: every case folder")
    parser.add_argument("--prepare", action="store_true", help="make the cases first")
    parser.add_argument("--recon-dir", type=Path, default=ROOT / "runs" / "s53")
    parser.add_argument(
        "--methods", nargs="+", default=["multi-atlas"], choices=["multi-atlas", "learned"]
    )
    parser.add_argument("--learned-checkpoint", type=Path, default=ROOT / "runs" / "tissue-unet")
    parser.add_argument("--window", type=float, default=1.0)
    parser.add_argument("--max-atlases", type=int, default=3)
    parser.add_argument("--demons-iterations", type=int, nargs="+", default=None)
    parser.add_argument("--demons-levels", type=float, nargs="+", default=None)
    parser.add_argument("--field-sigma", type=float, default=None)
    parser.add_argument("--fusion-sigma", type=float, default=2.0)
    parser.add_argument("--fusion-power", type=float, default=1.0)
    parser.add_argument("--affine-only", action="store_true")
    parser.add_argument("--no-trim", action="store_true", help="labels over the whole mask")
    parser.add_argument(
        "--no-refine", action="store_true", help="one registration pass, on the output's own mask"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--results", type=Path)
    parser.add_argument("--json", type=Path, help="also write every case's figures here")
    parser.add_argument(
        "--cli-time",
        action="store_true",
        help="instead: time svr segment-volume (labels, measures, report) per case in a "
        "subprocess with --threads, and its peak memory (the atlases' own ages not held out)",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    import SimpleITK as sitk  # noqa: N813

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(args.threads)
    if args.prepare:
        prepare(args.cases_dir, args.recon_dir)
    if args.cli_time:
        names = args.cases or sorted(p.name for p in args.cases_dir.iterdir() if p.is_dir())
        rows = []
        for case in names:
            seconds, peak = cli_time(args.cases_dir / case, args.threads)
            rows.append(f"| {case} | {seconds:.1f} | {peak:.0f} |")
            print(rows[-1], flush=True)
        text = "| case | wall s | peak MiB |\n|---|---|---|\n" + "\n".join(rows)
        if args.results:
            write_results(args.results, "svr segment-volume: time and memory", text)
        return
    registration = AtlasRegistrationConfig(deformable=not args.affine_only)
    changes = {}
    if args.demons_iterations:
        changes["demons_iterations"] = tuple(args.demons_iterations)
    if args.demons_levels:
        changes["demons_levels_mm"] = tuple(args.demons_levels)
    if args.field_sigma:
        changes["field_sigma_mm"] = args.field_sigma
    if changes:
        registration = AtlasRegistrationConfig(**{**registration.__dict__, **changes})
    cases = args.cases or sorted(
        p.name for p in args.cases_dir.iterdir() if (p / "case.json").exists()
    )
    lines = []
    summary: dict[str, dict[str, list]] = {}
    for method in args.methods:
        rows = summary.setdefault(
            method,
            {
                "case": [],
                "dice": [],
                "per_label": [],
                "vol_err": [],
                "time": [],
                "kind": [],
                "mm": [],
            },
        )
        for case in cases:
            folder = args.cases_dir / case
            info = json.loads((folder / "case.json").read_text())
            truth = (
                np.asarray(load_nifti(folder / "truth_labels.nii.gz").data.numpy())
                .round()
                .astype(int)
            )
            start = time.perf_counter()
            if method == "multi-atlas":
                config = TissueConfig(
                    window_weeks=args.window,
                    max_atlases=args.max_atlases,
                    hold_out=(info["weeks"],),
                    registration=registration,
                    fusion_sigma_mm=args.fusion_sigma,
                    fusion_power=args.fusion_power,
                    trim_to_affine_brain=not args.no_trim,
                    refine_brain=not args.no_refine,
                )
                labels, rotation = run_multi_atlas(folder / "volume.nii.gz", info, config)
            else:
                sys.path.insert(0, str(ROOT / "benchmarks" / "experiments"))
                from tissue_unet import segment  # type: ignore[import-not-found]

                labels = segment(folder / "volume.nii.gz", args.learned_checkpoint)
                rotation = np.eye(3)
            seconds = time.perf_counter() - start
            affine = load_nifti(folder / "volume.nii.gz").affine.numpy()
            measured = measure_labels(labels, affine, rotation).measures_mm
            truth_mm = true_measures(info)
            measure_err = [measured[k] - truth_mm[k] for k in LINEAR_MEASURES]
            per_label = [dice(labels == lab.value, truth == lab.value) for lab in TISSUE_LABELS]
            errors = [
                100.0
                * ((labels == lab.value).sum() - (truth == lab.value).sum())
                / max(1, (truth == lab.value).sum())
                for lab in TISSUE_LABELS
            ]
            rows["dice"].append(float(np.mean(per_label)))
            rows["per_label"].append(per_label)
            rows["vol_err"].append(errors)
            rows["time"].append(seconds)
            rows["kind"].append(info["kind"])
            rows["mm"].append(measure_err)
            rows["case"].append(case)
            line = (
                f"| {method} | {case} | {np.mean(per_label):.3f} | "
                + " | ".join(f"{d:.2f}" for d in per_label)
                + f" | {np.median(np.abs(errors)):.1f} | "
                + " ".join(f"{e:+.1f}" for e in measure_err)
                + f" | {seconds:.0f} |"
            )
            print(line, flush=True)
            lines.append(line)
    header = (
        "| method | case | mean Dice | "
        + " | ".join(lab.key[:6] for lab in TISSUE_LABELS)
        + " | median abs vol err % | measure errors mm ("
        + ", ".join(LINEAR_MEASURES)
        + ") | s |\n|"
        + "---|" * (len(TISSUE_LABELS) + 6)
    )
    text = [header, *lines, ""]
    for method, rows in summary.items():
        for kind in ("gt-volume", "recon"):
            pick = [i for i, k in enumerate(rows["kind"]) if k == kind]
            if not pick:
                continue
            d = np.array([rows["dice"][i] for i in pick])
            per = np.array([rows["per_label"][i] for i in pick]).mean(0)
            err = np.abs(np.array([rows["vol_err"][i] for i in pick]))
            times = np.median([rows["time"][i] for i in pick])
            mm = np.abs(np.array([rows["mm"][i] for i in pick]))
            labels_text = ", ".join(
                f"{lab.key} {v:.2f}" for lab, v in zip(TISSUE_LABELS, per, strict=True)
            )
            measures_text = ", ".join(
                f"{k} {v:.1f}" for k, v in zip(LINEAR_MEASURES, np.nanmedian(mm, 0), strict=True)
            )
            text.append(
                f"- {method}, {kind} ({len(pick)} cases): mean Dice {d.mean():.3f} "
                f"(min {d.min():.3f}); per label {labels_text}; volume error median "
                f"{np.median(err):.1f} % (per label medians "
                f"{', '.join(f'{v:.1f}' for v in np.median(err, 0))}); time median {times:.0f} s; "
                f"linear measures: median abs error {np.nanmedian(mm):.2f} mm ({measures_text})"
            )
    print("\n".join(text[len(lines) + 2 :]))
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1, default=float))
    if args.results:
        write_results(args.results, "Tissue labels against the truth", "\n".join(text))


if __name__ == "__main__":
    main()
