"""Slices and packets follow their stack: learned packet refinement vs classical SVR, same start.

For each case, every stack is first placed in canonical space on its own
(:func:`svr.models.stack_pose.estimate_stack_pose`, with the neighbouring-age atlas), so every
slice starts at its stack's pose. Then:

* ``learned packets``: each interleaved packet of each stack (slices ``k = j, j + m, ...`` of the
  file, ``m = --packets``) is refined on its own by the stack-pose network from its stack's pose
  (:func:`svr.models.stack_pose.refine_transforms` on the packet's slices only), and its slices take
  the packet's pose;
* ``classical``: nothing more before reconstruction: the slice-to-volume registration rounds of
  ``reconstruct`` (adaptive schedule) start from the stacks' poses.

With ``--oracle``, the same reconstruction also starts from perfect estimates at each level (the
bounds on what any initialisation can give): every stack at the robust mean of its slices' true
poses (a perfect stack estimator), every packet at that of its own slices (a perfect packet
estimator), and every slice at its true pose.

Measured: the slices' pose errors against the truth (up to one global rigid transform, the
robust mean of ``T_i o P_i^-1``, so that only how the slices sit relative to each other counts)
at the start and after the learned packet step, and the reconstruction from each start
(``initial_poses``, adaptive schedule) scored by ``../shared/tools/score_recon.py`` with its
final pose errors.

Run from the repository root::

    python benchmarks/bench_packet_refinement.py --model MODEL [--cases sb24-large]
        [--simulated ga21-traj1.0-obl ...] [--threads 2] [--results PATH.md]
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
    case_age,
    load_case_stacks,
    neighbour_atlas,
    run_scorer,
    true_slice_poses,
)

from svr.geometry import se3_compose, se3_inverse, vector_to_se3
from svr.geometry.averaging import robust_mean_pose
from svr.image import save_nifti
from svr.models.stack_pose import load_stack_pose_model
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation.stack_pose import estimate_stack_pose, refine_transforms
from svr.reconstruction.pipeline import reconstruct_from_poses
from svr.reconstruction.slices import SliceSet, array_poses, extract_slices
from svr.sampling.blocks import coarsen_stack
from svr.sampling.volume import load_canonical_volume

ROOT = Path(__file__).resolve().parents[1]


def true_canonical(case: Path, slices: SliceSet) -> torch.Tensor:
    """(N, 4, 4) true canonical poses of the slices' arrays."""
    info = json.loads((case / "case.json").read_text(encoding="utf-8"))
    centre = torch.tensor(info["atlas_centre_mm"], dtype=torch.float64)
    truth = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))["stacks"]
    by_name = {Path(s["file"]).name: s["slices"] for s in truth}
    per_stack = [
        true_slice_poses(by_name[Path(n).name], "atlas", centre) for n in slices.stack_names
    ]
    planes = torch.stack(
        [
            per_stack[int(s)][int(k)]
            for s, k in zip(slices.stack_ids, slices.slice_indices, strict=True)
        ]
    )
    return array_poses(slices, planes)


def relative_errors(truth: torch.Tensor, poses: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Per-slice rotation (deg) and centre (mm) errors after the best global rigid transform."""
    poses = poses.double().cpu()
    frame = robust_mean_pose(se3_compose(truth, se3_inverse(poses)))
    moved = se3_compose(frame[None], poses)
    rel = se3_compose(se3_inverse(truth), moved)
    cos = ((rel[:, :3, :3].diagonal(dim1=1, dim2=2).sum(1) - 1) / 2).clamp(-1, 1)
    return np.degrees(np.arccos(cos.numpy())), (moved[:, :3, 3] - truth[:, :3, 3]).norm(
        dim=1
    ).numpy()


def oracle_starts(
    truth: torch.Tensor,
    scanner: torch.Tensor,
    ids: torch.Tensor,
    slice_k: torch.Tensor,
    packets: int,
) -> list[tuple[str, torch.Tensor]]:
    """Starts from perfect stack, packet and slice estimates (labels end with the level's name).

    A group's perfect rigid estimate is the robust mean of ``T_i o S_i^-1`` over its slices (``T``
    the true canonical poses, ``S`` the scanner poses): the one transform that best places the
    group as acquired.
    """
    out = []
    for level in ("stack", "packet"):
        poses = torch.empty_like(truth)
        key = ids * packets + (slice_k % packets if level == "packet" else 0)
        for value in torch.unique(key).tolist():
            members = key == value
            frame = robust_mean_pose(se3_compose(truth[members], se3_inverse(scanner[members])))
            poses[members] = se3_compose(frame[None], scanner[members])
        out.append((f"SVR from perfect {level}", poses))
    out.append(("SVR from perfect slice", truth.clone()))
    return out


def perturbed(truth: torch.Tensor, deg: float, seed: int) -> torch.Tensor:
    """The true poses each moved by ``deg`` degrees (random axis) and ``0.4 deg`` mm."""
    gen = torch.Generator().manual_seed(seed)
    n = truth.shape[0]
    axis = torch.nn.functional.normalize(
        torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=1
    )
    shift = torch.nn.functional.normalize(
        torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=1
    )
    move = vector_to_se3(torch.cat([axis * math.radians(deg), shift * 0.4 * deg], dim=1))
    return se3_compose(truth, move)


def describe(rot: np.ndarray, cen: np.ndarray) -> str:
    return (
        f"median {np.median(rot):.1f} deg (p90 {np.percentile(rot, 90):.1f}), "
        f"centre median {np.median(cen):.1f} mm"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--cases", nargs="*", default=["sb24-large"])
    parser.add_argument("--simulated", nargs="*", default=[])
    parser.add_argument("--cases-dir", type=Path, default=ROOT / "runs" / "simulated-cases")
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument("--scorer", type=Path, default=SHARED / "tools" / "score_recon.py")
    parser.add_argument("--packets", type=int, default=2)
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench-packets")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--results", type=Path, default=None)
    parser.add_argument(
        "--oracle", action="store_true", help="also start from perfect stack/packet/slice poses"
    )
    parser.add_argument(
        "--oracle-deg",
        type=float,
        nargs="*",
        default=[],
        help="with --oracle, also from the true slice poses each moved by this rotation (random "
        "axis) and 0.4 mm per degree (random direction)",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    model = load_stack_pose_model(args.model)
    folders = [args.data / c for c in args.cases] + [args.cases_dir / c for c in args.simulated]
    lines = []
    for case in folders:
        stacks = load_case_stacks(case)
        slices = extract_slices(stacks)
        truth = true_canonical(case, slices)
        atlas = load_canonical_volume(*neighbour_atlas(case_age(case)))
        scanner = slices.poses.double().cpu()
        ids = slices.stack_ids.cpu()
        start = torch.empty_like(scanner)
        learned = torch.empty_like(scanner)
        began = time.perf_counter()
        for sid, stack in enumerate(stacks):
            mask = stack.mask.data > 0.5
            estimate = estimate_stack_pose(model, stack.image, mask, atlas=atlas, restart_deg=10.0)
            members = ids == sid
            start[members] = se3_compose(estimate.to_canonical[None], scanner[members])
            image, fractions = coarsen_stack(stack.image, mask, model.config.in_plane_mm)
            file_k = stack.k_indices.cpu()
            slice_k = slices.slice_indices.cpu()
            for j in range(args.packets):
                present = file_k % args.packets == j
                frames, _ = refine_transforms(
                    model, image, fractions, estimate.to_canonical[None], args.iterations, present
                )
                chosen = members & (slice_k % args.packets == j)
                learned[chosen] = se3_compose(frames[0][None], scanner[chosen])
        packet_s = time.perf_counter() - began
        row = [f"### {case.name}", ""]
        for label, poses in (("stack poses (start)", start), ("learned packets", learned)):
            rot, cen = relative_errors(truth, poses)
            row.append(f"- {label}: {describe(rot, cen)}")
        row.append(f"- stack poses and packet refinement took {packet_s:.1f} s")
        starts = [("classical SVR from the stack poses", start),
                  ("SVR from the learned packets", learned)]  # fmt: skip
        if args.oracle:
            oracles = oracle_starts(truth, scanner, ids, slices.slice_indices.cpu(), args.packets)
            oracles += [
                (f"SVR from slices-{deg:g}deg perturbed", perturbed(truth, deg, seed=i))
                for i, deg in enumerate(args.oracle_deg)
            ]
            for label, poses in oracles:
                rot, cen = relative_errors(truth, poses)
                row.append(f"- start of {label}: {describe(rot, cen)}")
            starts += oracles
        for label, poses in starts:
            began = time.perf_counter()
            result = reconstruct_from_poses(
                stacks, poses, "canonical", ReconstructionConfig(), progress=False
            )
            seconds = time.perf_counter() - began
            path = args.out / f"{case.name}-{'-'.join(label.split()[-2:])}.nii.gz"
            save_nifti(result.volume, path, overwrite=True)
            score = run_scorer(args.scorer, path, case)
            rot, cen = relative_errors(truth, result.slices.poses)
            row.append(
                f"- {label}: PSNR {score['psnr']:.2f} dB, SSIM {score['ssim']:.4f}; final poses "
                f"{describe(rot, cen)}; {seconds:.0f} s"
            )
        row.append("")
        print("\n".join(row), flush=True)
        lines += row
    if args.results is not None:
        command = "python benchmarks/bench_packet_refinement.py " + " ".join(sys.argv[1:])
        args.results.write_text(
            "# Packets follow their stack: learned refinement vs classical SVR\n\n"
            f"Command: `{command}`\n\n" + "\n".join(lines) + "\n",
            encoding="utf-8",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
