"""Which of the slice refiner's moves to keep: the shipped rule against rules that also look back.

For each case (a folder with ``truth_slices.json``) and its atlas: the slices start where
``--registration cnn`` starts them (:func:`svr.reconstruction.initialisation.initialise`, the
shipped stack-pose network), every slice is refined once by the shipped stages
(:func:`~svr.reconstruction.initialisation.slice_refinement.refine_poses`, 4 + 3 steps), and each
rule decides which refined poses to keep. Scores are leave-one-stack-out NCCs on the
initialisation grid: ``before`` (the slice at its start, the other stacks at theirs), ``after``
(refined, the others refined) and ``mixed`` (refined, the others at their start); the shipped
rule keeps ``mixed > before + 0.01`` where the start's median ``before`` exceeds
:data:`~svr.reconstruction.initialisation.slice_refinement.TRUSTED_START_NCC`, else
``after > before + 0.01``. Printed per rule: slices kept, how many of them improved,
and the per-slice rotation error median and 90th percentile against the truth (up to one global
rigid transform); "improved" keeps exactly the slices whose error fell (the best any rule can do).
Then the packets' motion trajectories of the kept poses (``slice-refiner.md`` section 10): at
each ``--smoothness`` and each value of :data:`~svr.reconstruction.trajectory.SMOOTHNESS_GRID`
(with its leave-one-out error), the value leave-one-out chooses per packet and per case, and the
packet choice by agreement with the other stacks; ``--save`` keeps each case's poses (.npz).

    python benchmarks/experiments/keep_rules.py [--save DIR] CASE ATLAS_AGE_FOLDER [CASE ATLAS ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_common import load_case_stacks
from bench_packet_refinement import relative_errors, true_canonical

from svr.models.pretrained import stack_pose_model_path
from svr.models.slice_refiner import shipped_slice_refiners
from svr.models.stack_pose import load_stack_pose_model
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation import initialise
from svr.reconstruction.initialisation.slice_refinement import (
    TRUSTED_START_NCC,
    atlas_reference,
    refine_poses,
)
from svr.reconstruction.registration import slice_agreement
from svr.reconstruction.slices import SliceSet, extract_slices
from svr.reconstruction.trajectory import (
    SMOOTHNESS_GRID,
    TrajectoryConfig,
    cross_validated_trajectory,
    fit_slice_trajectory,
    leave_one_out_deg,
    packet_times,
)
from svr.sampling.volume import load_canonical_volume

MARGIN = 0.01


def per_packet_smoothness(
    slices: SliceSet, poses: torch.Tensor, packets: int
) -> tuple[torch.Tensor, list[float]]:
    """Each packet on its trajectory at the smoothness its own leave-one-out error favours."""
    moved = slices.with_poses(poses.to(slices.poses))
    packet = packet_times(moved, packets)[0].cpu()
    errors = leave_one_out_deg(moved, packets).cpu()
    fits = torch.stack(
        [
            fit_slice_trajectory(moved, packets, TrajectoryConfig(smoothness=value)).poses.cpu()
            for value in SMOOTHNESS_GRID
        ]
    )
    chosen = torch.zeros(len(slices), dtype=torch.long)
    for key in packet.unique():
        mine = packet == key
        chosen[mine] = int(errors[:, mine].mean(1).argmin())
    return fits[chosen, torch.arange(len(slices))], [SMOOTHNESS_GRID[int(c)] for c in chosen]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", type=Path, nargs="+", help="CASE ATLAS_AGE_FOLDER, repeated")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--save", type=Path, help="folder for each case's poses (.npz)")
    parser.add_argument(
        "--smoothness",
        type=float,
        nargs="*",
        default=[0.05, 0.5],
        help="trajectory smoothness of the rules that fit the refined poses' packet trajectories",
    )
    args = parser.parse_args()
    if len(args.pairs) % 2:
        parser.error("give a case folder and an atlas age folder for each case")
    torch.set_num_threads(args.threads)
    model = load_stack_pose_model(stack_pose_model_path())
    config = ReconstructionConfig.preset("learned")
    grid_mm = config.initialisation_grid_mm
    stages = list(zip(shipped_slice_refiners(), (4, 3), strict=True))
    for case, folder in zip(args.pairs[::2], args.pairs[1::2], strict=True):
        stacks = load_case_stacks(case)
        slices = extract_slices(stacks)
        truth = true_canonical(case, slices)
        start = initialise(slices, stacks, config, model).slices
        atlas = load_canonical_volume(folder / "srr.nii.gz", folder / "mask.nii.gz")
        refined = refine_poses(stages, start, atlas_reference(atlas))
        moved = start.with_poses(refined.to(start.poses))
        before = slice_agreement(start, grid_mm, leave_out=True).double().cpu()
        after = slice_agreement(moved, grid_mm, leave_out=True).double().cpu()
        mixed = slice_agreement(start, grid_mm, True, at=refined).double().cpu()
        start_error, _ = relative_errors(truth, start.poses)
        refined_error, _ = relative_errors(truth, refined)
        better = torch.from_numpy(refined_error < start_error)
        trusted = float(before.median()) > TRUSTED_START_NCC
        rules = {
            "shipped (mixed where the start agrees, else after)": (
                (mixed if trusted else after) > before + MARGIN
            ),
            "after only": after > before + MARGIN,
            "mixed only": mixed > before + MARGIN,
            "both": (after > before + MARGIN) & (mixed > before + MARGIN),
            "improved": better,
        }
        shipped = torch.where(
            rules["shipped (mixed where the start agrees, else after)"][:, None, None],
            refined.cpu(),
            start.poses.double().cpu(),
        )
        candidates = {name: (kept, None) for name, kept in rules.items()}
        for smoothness in args.smoothness:
            trajectory = TrajectoryConfig(smoothness=smoothness)
            for label, poses in (("every slice refined", refined.cpu()), ("shipped", shipped)):
                fit = fit_slice_trajectory(start.with_poses(poses), config.packets, trajectory)
                candidates[f"{label}, then trajectory {smoothness:g}"] = (None, fit.poses)
                smooth = start.with_poses(fit.poses.to(start.poses))
                agree = slice_agreement(smooth, grid_mm, leave_out=True).double().cpu()
                kept = agree > before + MARGIN
                mixed_poses = torch.where(kept[:, None, None], fit.poses, start.poses.double())
                candidates[f"{label}, trajectory {smoothness:g}, then kept if after"] = (
                    kept,
                    mixed_poses,
                )
        print(
            f"## {case.name} ({folder.name}): start median {np.median(start_error):.1f} deg, "
            f"every slice refined {np.median(refined_error):.1f}",
            flush=True,
        )
        # Per packet, the candidate whose slices agree best with the other stacks (mean NCC of
        # the packet's slices, each candidate's poses for every slice).
        options = {"shipped": shipped}
        options.update(
            {
                name: poses
                for name, (_, poses) in candidates.items()
                if name.startswith("shipped, then trajectory")
            }
        )
        scores = torch.stack(
            [
                slice_agreement(start.with_poses(poses.to(start.poses)), grid_mm, leave_out=True)
                .double()
                .cpu()
                for poses in options.values()
            ]
        )
        packet, _ = packet_times(start, config.packets)
        packet = packet.cpu()
        chosen = torch.zeros(len(start), dtype=torch.long)
        for key in packet.unique():
            mine = packet == key
            chosen[mine] = int(scores[:, mine].mean(1).argmax())
        stacked = torch.stack([poses.cpu() for poses in options.values()])
        per_packet = stacked[chosen, torch.arange(len(start))]
        counts = ", ".join(f"{name} {int((chosen == i).sum())}" for i, name in enumerate(options))
        print(f"  per-packet choice (slices): {counts}", flush=True)
        candidates["per packet, the best agreeing of shipped and its trajectories"] = (
            None,
            per_packet,
        )
        grid = SMOOTHNESS_GRID
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savez(
                args.save / f"{case.name}.npz",
                truth=truth.numpy(),
                start=start.poses.double().cpu().numpy(),
                refined=refined.cpu().numpy(),
                shipped=shipped.numpy(),
                scanner=start.scanner_poses.double().cpu().numpy(),
                stack_ids=start.stack_ids.cpu().numpy(),
                slice_indices=start.slice_indices.cpu().numpy(),
            )
        _, _, loo = cross_validated_trajectory(
            start.with_poses(shipped.to(start.poses)), config.packets, grid
        )
        for value, error in zip(grid, loo.tolist(), strict=True):
            fit = fit_slice_trajectory(
                start.with_poses(shipped.to(start.poses)),
                config.packets,
                TrajectoryConfig(smoothness=value),
            )
            angle, _ = relative_errors(truth, fit.poses.cpu())
            print(
                f"  smoothness {value:g}: leave-one-out {error:.2f} deg, median "
                f"{np.median(angle):.1f}, p90 {np.percentile(angle, 90):.1f}",
                flush=True,
            )
        moved = start.with_poses(shipped.to(start.poses))
        fit, value, _ = cross_validated_trajectory(moved, config.packets)
        print(f"  leave-one-out smoothness, per case: {value:g}", flush=True)
        candidates["shipped, then trajectory by leave-one-out, per case"] = (None, fit.poses.cpu())
        smoothed, chosen = per_packet_smoothness(start, shipped, config.packets)
        values = ", ".join(f"{g:g}: {chosen.count(g)}" for g in grid if chosen.count(g))
        print(f"  leave-one-out smoothness, per packet (slices): {values}", flush=True)
        candidates["shipped, then trajectory by leave-one-out, per packet"] = (None, smoothed)
        for name, (kept, poses) in candidates.items():
            if poses is None:
                poses = torch.where(kept[:, None, None], refined.cpu(), start.poses.double().cpu())
            error, _ = relative_errors(truth, poses.cpu())
            count = "all" if kept is None else f"{int(kept.sum())}/{len(kept)}"
            print(
                f"  {name}: kept {count}, median {np.median(error):.1f} deg, p90 "
                f"{np.percentile(error, 90):.1f}, within 5 deg {np.mean(error <= 5):.0%}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
