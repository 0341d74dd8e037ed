"""Stack-level learned poses: per-stack orientation after mirror disambiguation, and reconstruction.

For each case (the two bench cases and cases simulated here with ``svr simulate`` from atlas ages
that the model did not see, with real fetal motion trajectories, orthogonal and oblique stacks
and several motion levels) this measures, in one run:

* **per-stack orientation error**: the angle (and translation) between each stack's learned
  scanner -> canonical transform
  (:func:`svr.reconstruction.initialisation.slice_model.slice_predictions`) and the true one (the
  robust mean over the stack's slices of ``true canonical pose o nominal scanner pose^-1``), with
  the stack-order disambiguation of mirror twins (the model's planes) and without it (no planes: the
  plain robust consensus), and how many slices each stack flipped;
* **per-slice errors** of the raw predictions, raw and up to the mirror twin;
* with ``--reconstruct``: ``svr reconstruct``'s ``--registration stack`` and ``cnn`` on every case,
  scored by ``../shared/tools/score_recon.py`` (which finds volumes in the atlas orientation), the
  initialisation kept per stack, and the output frame error of ``cnn``: the rigid transform
  between the volume's canonical frame and the true one (robust mean of ``true canonical pose o
  final pose^-1`` over the slices).

Run from the repository root (``--model`` a checkpoint folder, or ``default``)::

    python benchmarks/bench_stack_poses.py --model MODEL [--reconstruct] [--threads 1]

Results: printed as Markdown and written to ``--results`` (JSON beside it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import (
    SHARED,
    load_case_stacks,
    reconstruct_default,
    run_scorer,
    simulate_cases,
    true_slice_poses,
)

from svr.geometry import se3_compose, se3_inverse, se3_to_vector, so3_log
from svr.geometry.averaging import robust_mean_pose
from svr.image import save_nifti
from svr.metrics import nearest_orbit_member, rotation_error_rad, translation_error_mm
from svr.models.predict import load_pose_model
from svr.reconstruction.initialisation.slice_model import learned_consensus, slice_predictions
from svr.reconstruction.slices import SliceSet, extract_slices, plane_poses

ROOT = Path(__file__).resolve().parents[1]
# name: (atlas age folder, orientations, motion scale of the real trajectories, stacks, seed)
SIMULATED = {
    "ga24-traj0.5-orth": ("GA24_notoperated", "orthogonal", 0.5, 3, 11),
    "ga24-traj1.0-obl": ("GA24_notoperated", "oblique", 1.0, 4, 12),
    "ga28-traj0.3-obl": ("GA28_operated", "oblique", 0.3, 4, 13),
    "ga28-traj1.0-orth": ("GA28_operated", "orthogonal", 1.0, 3, 14),
    "ga32-traj0.5-obl": ("GA32_operated", "oblique", 0.5, 4, 15),
    "ga32-traj1.0-orth": ("GA32_operated", "orthogonal", 1.0, 3, 16),
}


def case_truth(case: Path, slices: SliceSet) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 4, 4) true canonical poses and true scanner poses of the slice set's k-planes."""
    info = json.loads((case / "case.json").read_text(encoding="utf-8"))
    centre = torch.tensor(info["atlas_centre_mm"], dtype=torch.float64)
    truth = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))["stacks"]
    by_file = {str((case / s["file"]).resolve()): s["slices"] for s in truth}
    out = []
    for frame, c in (("atlas", centre), ("scanner", None)):
        per_stack = [
            true_slice_poses(by_file[str(Path(n).resolve())], frame, c) for n in slices.stack_names
        ]
        out.append(
            torch.stack(
                [
                    per_stack[int(s)][int(k)]
                    for s, k in zip(slices.stack_ids, slices.slice_indices, strict=True)
                ]
            )
        )
    return out[0], out[1]


def transform_error(estimate: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """Rotation angle (degrees) and translation (mm) of ``truth^-1 o estimate`` at the origin."""
    rel = se3_compose(se3_inverse(truth), estimate)
    return (
        math.degrees(float(so3_log(rel[:3, :3]).norm())),
        float(rel[:3, 3].norm()),
    )


def stack_rows(case: Path, model, planes_off: bool) -> tuple[list[dict], dict]:
    """Per-stack transform errors (with and without disambiguation) and per-slice errors."""
    stacks = load_case_stacks(case)
    slices = extract_slices(stacks)
    canonical_truth, _ = case_truth(case, slices)
    nominal = plane_poses(slices, slices.scanner_poses)
    learned = slice_predictions(model, stacks, slices)
    variants = {"disambiguated": learned}
    if planes_off:
        variants["no twin logic"] = learned_consensus(slices, learned.raw_predicted_poses)
    rows = []
    for sid, name in enumerate(slices.stack_names):
        members = slices.stack_ids == sid
        true_transform = robust_mean_pose(
            se3_compose(canonical_truth[members], se3_inverse(nominal[members]))
        )
        row = {"case": case.name, "stack": Path(name).name, "slices": int(members.sum())}
        for label, init in variants.items():
            # the learned transforms map the slice set's padded-array poses; bring them to the
            # k-plane centres the truth uses: A = P_plane o S_plane^-1 is the same transform.
            rot, trans = transform_error(init.stack_transforms[sid].cpu(), true_transform)
            row[f"{label} rot"] = rot
            row[f"{label} trans"] = trans
            row[f"{label} support"] = float(init.stack_support[sid])
        row["flipped"] = int(learned.flipped(slices.stack_ids)[sid])
        rows.append(row)
    raw = se3_to_vector(plane_poses(slices, learned.raw_predicted_poses).cpu())
    truth_v = se3_to_vector(canonical_truth)
    nearest, _ = nearest_orbit_member(
        raw, truth_v, model.config.symmetry_planes, distance=rotation_error_rad
    )
    ang = rotation_error_rad(raw, nearest).rad2deg()
    per_slice = {
        "rot raw": float(rotation_error_rad(raw, truth_v).rad2deg().median()),
        "rot twin": float(ang.median()),
        "trans raw": float(translation_error_mm(raw, truth_v).median()),
    }
    return rows, per_slice


def frame_error(case: Path, result) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) between a canonical result's frame and the truth."""
    canonical_truth, _ = case_truth(case, result.slices)
    final = plane_poses(result.slices)
    return transform_error(
        torch.eye(4, dtype=torch.float64),
        robust_mean_pose(se3_compose(canonical_truth, se3_inverse(final.cpu().double()))),
    )


def recon_rows(case: Path, model, out: Path, scorer: Path) -> dict:
    stacks = load_case_stacks(case)
    row: dict = {"case": case.name}
    for registration in ("stack", "cnn"):
        start = time.perf_counter()
        result = reconstruct_default(stacks, registration, model)
        path = out / f"{case.name}-{registration}.nii.gz"
        save_nifti(result.volume, path, overwrite=True)
        quality = run_scorer(scorer, path, case)
        row[f"{registration} psnr"] = quality["psnr"]
        row[f"{registration} ssim"] = quality["ssim"]
        row[f"{registration} s"] = time.perf_counter() - start
        if registration == "cnn":
            row["kept"] = ",".join(result.initialisation)
            row["frame rot"], row["frame trans"] = frame_error(case, result)
        print(f"  {case.name} {registration}: PSNR {quality['psnr']:.2f}", flush=True)
    row["cnn - stack dB"] = row["cnn psnr"] - row["stack psnr"]
    return row


def table(rows: list[dict], columns: list[tuple[str, str]]) -> str:
    head = "| " + " | ".join(c for c, _ in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"
    body = [
        "| "
        + " | ".join(
            (f"{r[c]:{fmt}}" if isinstance(r.get(c), float | int) and fmt else str(r.get(c, "—")))
            for c, fmt in columns
        )
        + " |"
        for r in rows
    ]
    return "\n".join([head, rule, *body])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="default", help="checkpoint folder or 'default'")
    parser.add_argument("--bench", nargs="*", default=["sb28-moderate", "sb24-large"])
    parser.add_argument("--simulated", nargs="*", default=list(SIMULATED))
    parser.add_argument("--cases-dir", type=Path, default=ROOT / "runs" / "sim-cases")
    parser.add_argument("--reconstruct", action="store_true", help="also reconstruct and score")
    parser.add_argument("--scorer", type=Path, default=SHARED / "tools" / "score_recon.py")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-stack-poses")
    parser.add_argument(
        "--results", type=Path, default=ROOT / "benchmarks" / "results" / "stack-poses.md"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args()
    if not (SHARED / "data").is_dir():
        print(f"{SHARED / 'data'}: shared data not found", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    args.cases_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    cases = [SHARED / "data" / "bench" / c for c in args.bench]
    cases += simulate_cases(args.cases_dir, {name: SIMULATED[name] for name in args.simulated})
    model = load_pose_model(args.model)
    planes = model.config.symmetry_planes
    all_rows, slice_rows, recon = [], [], []
    for case in cases:
        rows, per_slice = stack_rows(case, model, planes_off=bool(planes))
        all_rows += rows
        slice_rows.append({"case": case.name, **per_slice})
        print(f"{case.name}: {[round(r['disambiguated rot'], 1) for r in rows]}", flush=True)
        if args.reconstruct:
            recon.append(recon_rows(case, model, args.out, args.scorer))
    errs = np.array([r["disambiguated rot"] for r in all_rows])
    summary = {
        "stacks": len(errs),
        "median_rot_deg": float(np.median(errs)),
        "within_10deg": float(np.mean(errs <= 10.0)),
        "within_5deg": float(np.mean(errs <= 5.0)),
    }
    if planes:
        plain = np.array([r["no twin logic rot"] for r in all_rows])
        summary["no_twin_logic_median_rot_deg"] = float(np.median(plain))
        summary["no_twin_logic_within_10deg"] = float(np.mean(plain <= 10.0))
    cols = [
        ("case", ""),
        ("stack", ""),
        ("slices", "d"),
        ("disambiguated rot", ".1f"),
        ("disambiguated trans", ".1f"),
        ("disambiguated support", ".2f"),
        ("flipped", "d"),
    ]
    if planes:
        cols += [("no twin logic rot", ".1f"), ("no twin logic support", ".2f")]
    lines = [
        f"# Stack-level learned poses (model `{args.model}`)",
        "",
        f"Command: `python benchmarks/bench_stack_poses.py --model {args.model}"
        f"{' --reconstruct' if args.reconstruct else ''} --threads {args.threads}` "
        f"({time.perf_counter() - start:.0f} s wall).",
        "",
        "Per-stack orientation error (degrees) and translation (mm) of the learned scanner -> "
        "canonical transform; support = fraction of the stack's slices within 30° / 20 mm of it; "
        "flipped = slices whose mirror twin the stack chose.",
        "",
        table(all_rows, cols),
        "",
        f"**Summary:** {summary['stacks']} stacks, median orientation error "
        f"{summary['median_rot_deg']:.1f}°, {100 * summary['within_10deg']:.0f}% within 10°, "
        f"{100 * summary['within_5deg']:.0f}% within 5°"
        + (
            f"; without the twin logic median {summary['no_twin_logic_median_rot_deg']:.1f}°, "
            f"{100 * summary['no_twin_logic_within_10deg']:.0f}% within 10°."
            if planes
            else "."
        ),
        "",
        "Per-slice raw predictions, median errors:",
        "",
        table(
            slice_rows,
            [("case", ""), ("rot raw", ".1f"), ("rot twin", ".1f"), ("trans raw", ".1f")],
        ),
    ]
    if recon:
        lines += [
            "",
            "Reconstruction (score_recon.py), `--registration stack` vs `cnn`:",
            "",
            table(
                recon,
                [
                    ("case", ""),
                    ("stack psnr", ".2f"),
                    ("cnn psnr", ".2f"),
                    ("cnn - stack dB", "+.2f"),
                    ("stack ssim", ".3f"),
                    ("cnn ssim", ".3f"),
                    ("kept", ""),
                    ("frame rot", ".1f"),
                    ("frame trans", ".1f"),
                    ("stack s", ".0f"),
                    ("cnn s", ".0f"),
                ],
            ),
        ]
    text = "\n".join(lines) + "\n"
    print(text)
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(text, encoding="utf-8")
    args.results.with_suffix(".json").write_text(
        json.dumps(
            {"summary": summary, "stacks": all_rows, "slices": slice_rows, "recon": recon},
            indent=1,
        )
        + "\n",
        encoding="utf-8",
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
