"""Pose initialisation benchmark: how close each initialisation puts the slices to their truth.

For each bench case (``../shared/data/bench``, every slice's true pose in ``truth_slices.json``)
this measures, in one run, the per-slice pose errors of

* the classical initialisation: rigid stack-to-template registration (scanner frame);
* the learned initialisation: the model's per-slice predictions and their per-stack robust
  consensus (canonical frame; the consensus is what ``--registration cnn`` starts from);
* the final poses of ``reconstruct`` with ``--registration stack`` and ``cnn``;
* ``--registration cnn`` with oracle models: every prediction is the true canonical pose moved
  by a rigid error of a set size (a random axis and direction), passed through the same learned
  initialisation (:func:`svr.reconstruction.initialisation.slice_model.consensus_start`) and
  reconstruction. They show how accurate a model must be for the learned initialisation to beat the
  classical one.

and scores every reconstructed volume with ``../shared/tools/score_recon.py`` (canonical-frame
volumes also after placing them in the scanner frame with the case's true atlas -> scanner
transform, since the yardstick's own search misses the atlas orientation on sb28-moderate).
Errors are the geodesic rotation angle and the distance between slice centres. A reconstruction
in the scanner frame is defined only up to one rigid transform (the template stack's), so
"relative" errors are measured after the robust mean
(:func:`svr.geometry.averaging.robust_mean_pose`) of ``truth o estimate^-1`` has been applied;
canonical-frame estimates also get "absolute" errors.

Run from the repository root::

    python benchmarks/bench_init_poses.py [--cases sb24-large] [--model default]
        [--oracle-deg 2 5 10 15] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import load_case_stacks, reconstruct_default, run_scorer, true_slice_poses

from svr.geometry import se3_compose, se3_inverse, se3_to_vector, so3_exp
from svr.geometry.averaging import robust_mean_pose
from svr.image import Image, save_nifti
from svr.metrics import rotation_error_rad, translation_error_mm
from svr.models.predict import load_pose_model
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation.slice_model import (
    consensus_start,
    learned_consensus,
    slice_predictions,
)
from svr.reconstruction.pipeline import reconstruct_from_poses
from svr.reconstruction.registration import stack_registration
from svr.reconstruction.result import ReconstructionResult
from svr.reconstruction.slices import SliceSet, Stack, array_poses, extract_slices, plane_poses
from svr.sampling.volume import load_canonical_volume

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
# Translation error of an oracle initialisation per degree of rotation error: the bench cases'
# motion bound, 6 mm with 15 degrees (``case.json``).
ORACLE_MM_PER_DEG = 6.0 / 15.0


def slice_truth(
    case: Path, slices: SliceSet, frame: str, centre_mm: torch.Tensor | None
) -> torch.Tensor:
    """(N, 4, 4) true poses of the slice set's k-planes (origin at the file's plane centre)."""
    truth = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))["stacks"]
    by_file = {str((case / s["file"]).resolve()): s["slices"] for s in truth}
    per_stack = [
        true_slice_poses(by_file[str(Path(name).resolve())], frame, centre_mm)
        for name in slices.stack_names
    ]
    return torch.stack(
        [
            per_stack[int(s)][int(k)]
            for s, k in zip(slices.stack_ids.cpu(), slices.slice_indices.cpu(), strict=True)
        ]
    )


def errors(
    estimate: torch.Tensor, truth: torch.Tensor, align: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Per-slice rotation (degrees) and translation (mm) errors of (N, 4, 4) plane poses.

    With ``align``, the estimate is first moved by the robust mean of ``truth o estimate^-1``.
    """
    estimate = estimate.to(torch.float64).cpu()
    if align:
        shift = robust_mean_pose(se3_compose(truth, se3_inverse(estimate)))
        estimate = se3_compose(shift.expand_as(estimate), estimate)
    p, t = se3_to_vector(estimate), se3_to_vector(truth)
    return (
        rotation_error_rad(p, t).rad2deg().numpy(),
        translation_error_mm(p, t).numpy(),
    )


def perturbed(truth: torch.Tensor, degrees: float, generator: torch.Generator) -> torch.Tensor:
    """Each pose rotated by ``degrees`` about a random axis through its slice centre.

    The slice centre also moves by ``degrees * ORACLE_MM_PER_DEG`` mm in a random direction.
    """
    n = len(truth)
    axis = torch.randn(n, 3, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm(dim=1, keepdim=True)
    direction = torch.randn(n, 3, generator=generator, dtype=torch.float64)
    direction = direction / direction.norm(dim=1, keepdim=True)
    out = truth.clone()
    out[:, :3, :3] = so3_exp(axis * np.deg2rad(degrees)) @ truth[:, :3, :3]
    out[:, :3, 3] += direction * degrees * ORACLE_MM_PER_DEG
    return out


def score(
    result: ReconstructionResult, path: Path, case: Path, scorer: Path
) -> dict[str, float | None]:
    """PSNR, SSIM and NCC of a reconstruction by the shared yardstick.

    A volume in the canonical frame is also scored after being placed in the ground truth's
    scanner frame by the case's true atlas -> scanner transform (``x = R x_canonical + c`` with
    ``R = scanner_from_atlas_R``, ``c = scanner_centre``), keys ``placed_*``: the yardstick's
    own search over starting orientations does not find the atlas orientation on every case
    (the atlas itself scores about 14.7 dB on sb28-moderate unplaced, 300 dB placed).
    """

    def run(volume_path: Path) -> dict[str, float]:
        return run_scorer(scorer, volume_path, case)

    save_nifti(result.volume, path, overwrite=True)
    quality: dict[str, float | None] = dict(run(path))
    quality["placed_psnr"] = quality["placed_ssim"] = None
    if result.slices.frame == "canonical":
        info = json.loads((case / "case.json").read_text(encoding="utf-8"))
        placement = torch.eye(4, dtype=torch.float64)
        placement[:3, :3] = torch.tensor(info["scanner_from_atlas_R"], dtype=torch.float64)
        placement[:3, 3] = torch.tensor(info["scanner_centre"], dtype=torch.float64)
        placed = Image(result.volume.data, placement @ result.volume.affine.to(torch.float64))
        placed_path = path.with_name(path.name.replace(".nii.gz", "-placed.nii.gz"))
        save_nifti(placed, placed_path, overwrite=True)
        placed_quality = run(placed_path)
        quality["placed_psnr"] = placed_quality["psnr"]
        quality["placed_ssim"] = placed_quality["ssim"]
    return quality


def row(name: str, rot: np.ndarray, trans: np.ndarray, quality: dict | None = None) -> dict:
    return {
        "name": name,
        "rot_median": float(np.median(rot)),
        "rot_p90": float(np.percentile(rot, 90)),
        "trans_median": float(np.median(trans)),
        "within_5deg": float(np.mean(rot <= 5.0 + 1e-6)),
        "psnr": quality["psnr"] if quality else None,
        "ssim": quality["ssim"] if quality else None,
        "placed_psnr": quality["placed_psnr"] if quality else None,
        "placed_ssim": quality["placed_ssim"] if quality else None,
    }


def bench_case(
    case: Path, model, atlas_dir: Path, oracle_deg: list[float], out: Path, scorer: Path, seed: int
) -> list[dict]:
    info = json.loads((case / "case.json").read_text(encoding="utf-8"))
    atlas = atlas_dir / info["source"].removeprefix("fetal_SB_atlas_")
    centre = load_canonical_volume(atlas / "srr.nii.gz", atlas / "mask.nii.gz").centre_mm
    stacks: list[Stack] = load_case_stacks(case)
    slices = extract_slices(stacks)
    scanner_truth = slice_truth(case, slices, "scanner", None)
    canonical_truth = slice_truth(case, slices, "atlas", centre)
    config = ReconstructionConfig()
    rows = []

    registered, _ = stack_registration(
        slices, config.initialisation_grid_mm, config.initialisation.template
    )
    rows.append(
        row(
            "classical init (stack registration), relative",
            *errors(plane_poses(slices, registered), scanner_truth, align=True),
        )
    )
    learned = slice_predictions(model, stacks, slices)
    for label, poses in (
        ("per-slice predictions", learned.predicted_poses),
        ("per-stack consensus", learned.consensus_poses),
        (
            "refined per slice",
            learned.refined_poses(
                config.initialisation.slice_max_deviation_deg,
                config.initialisation.slice_max_deviation_mm,
            ),
        ),
    ):
        planes = plane_poses(slices, poses)
        rows.append(
            row(f"learned init ({label}), absolute", *errors(planes, canonical_truth, False))
        )
        rows.append(
            row(f"learned init ({label}), relative", *errors(planes, canonical_truth, True))
        )

    for registration in ("stack", "cnn"):
        start = time.perf_counter()
        result = reconstruct_default(stacks, registration, model)
        quality = score(result, out / f"{case.name}-{registration}.nii.gz", case, scorer)
        frame_truth = canonical_truth if result.slices.frame == "canonical" else scanner_truth
        rot, trans = errors(plane_poses(result.slices), frame_truth, align=True)
        rows.append(
            row(
                f"final, --registration {registration} (kept: {','.join(result.initialisation)})",
                rot,
                trans,
                quality,
            )
        )
        print(f"  {case.name} {registration}: {time.perf_counter() - start:.1f} s", flush=True)

    generator = torch.Generator().manual_seed(seed)
    for degrees in oracle_deg:
        # An oracle model: every prediction the truth moved by a rigid error of a set size, fed
        # through the same learned initialisation (consensus, per-stack NCC choice) as the CNN.
        predicted = perturbed(canonical_truth, degrees, generator)
        oracle = learned_consensus(slices, array_poses(slices, predicted))
        start, kept, _, *_ = consensus_start(slices, oracle, config)
        result = reconstruct_from_poses(stacks, start.poses, "canonical", config, progress=False)
        quality = score(result, out / f"{case.name}-oracle-{degrees:g}.nii.gz", case, scorer)
        label = f"oracle model, {degrees:g} deg / {degrees * ORACLE_MM_PER_DEG:g} mm per slice"
        rows.append(
            row(
                f"{label}: initial poses (kept: {','.join(kept)})",
                *errors(plane_poses(start), canonical_truth, align=False),
            )
        )
        rot, trans = errors(plane_poses(result.slices), canonical_truth, align=True)
        rows.append(row(f"{label}: final", rot, trans, quality))
        print(
            f"  {case.name} oracle {degrees:g} deg: PSNR {quality['psnr']:.2f}, placed "
            f"{quality['placed_psnr']:.2f}",
            flush=True,
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["sb24-large", "sb28-moderate"])
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument(
        "--atlas-dir", type=Path, default=SHARED / "data" / "atlas" / "sb-fidon2021"
    )
    parser.add_argument("--scorer", type=Path, default=SHARED / "tools" / "score_recon.py")
    parser.add_argument("--model", default="default", help="checkpoint folder or 'default'")
    parser.add_argument("--oracle-deg", type=float, nargs="*", default=[2.0, 5.0, 10.0, 15.0])
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-init-poses")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not args.data.is_dir():
        print(f"{args.data}: bench cases not found", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    model = load_pose_model(args.model)
    for case in args.cases:
        rows = bench_case(
            args.data / case,
            model,
            args.atlas_dir,
            args.oracle_deg,
            args.out,
            args.scorer,
            args.seed,
        )
        classical = rows[0]["rot_median"]
        print(f"\n{case}: per-slice pose errors against the truth (model {args.model})\n")
        print(
            "| poses | rotation median (°) | p90 (°) | within 5° | translation median (mm) "
            "| median rotation / classical init | PSNR (dB) | SSIM | placed PSNR (dB) "
            "| placed SSIM |"
        )
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for r in rows:
            cells = [
                "—" if r[key] is None else f"{r[key]:{fmt}}"
                for key, fmt in (
                    ("psnr", ".2f"),
                    ("ssim", ".4f"),
                    ("placed_psnr", ".2f"),
                    ("placed_ssim", ".4f"),
                )
            ]
            print(
                f"| {r['name']} | {r['rot_median']:.2f} | {r['rot_p90']:.2f} | "
                f"{100 * r['within_5deg']:.0f}% | {r['trans_median']:.2f} | "
                f"x{r['rot_median'] / classical:.2f} | {' | '.join(cells)} |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
