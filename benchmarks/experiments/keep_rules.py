"""Which of the slice refiner's moves to keep: the shipped rule against rules that also look back.

For each case (a folder with ``truth_slices.json``) and its atlas: the slices start where
``--registration cnn`` starts them (:func:`svr.reconstruction.initialisation.initialise`, the
shipped stack-pose network), every slice is refined once by the shipped stages
(:func:`~svr.reconstruction.initialisation.slice_refinement.refine_poses`, 4 + 3 steps), and each
rule decides which refined poses to keep. Scores are leave-one-stack-out NCCs on the
initialisation grid: ``before`` (the slice at its start, the other stacks at theirs), ``after``
(refined, the others refined: the shipped rule keeps ``after > before + 0.01``) and ``mixed``
(refined, the others at their start). Printed per rule: slices kept, how many of them improved,
and the per-slice rotation error median and 90th percentile against the truth (up to one global
rigid transform); "improved" keeps exactly the slices whose error fell (the best any rule can do).

    python benchmarks/experiments/keep_rules.py CASE ATLAS_AGE_FOLDER [CASE ATLAS ...]
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
from svr.reconstruction.initialisation.slice_refinement import atlas_reference, refine_poses
from svr.reconstruction.operators import SliceProjector
from svr.reconstruction.registration import SVR_PSF_SAMPLES, slice_agreement, slice_ncc
from svr.reconstruction.slices import SliceSet, extract_slices
from svr.reconstruction.superres import coverage, output_grid, sda_ratio
from svr.sampling.volume import load_canonical_volume

MARGIN = 0.01


def mixed_agreement(start: SliceSet, moved: SliceSet, grid_mm: float) -> torch.Tensor:
    """(N,) each moved slice's NCC with the volume of the *other* stacks at their start poses."""
    grid = output_grid(start, grid_mm)
    parts = {}
    for sid in range(len(start.stack_names)):
        chosen = start.stack_ids == sid
        mine = start.subset(chosen)
        projector = SliceProjector(grid, mine, psf_samples=SVR_PSF_SAMPLES)
        observed = projector.gather(mine.images)
        points = projector.grid_points(mine.poses)
        covered = coverage(projector, points, torch.ones_like(observed))
        numerator = projector.adjoint(observed, points)
        parts[sid] = (projector, observed, numerator, covered, chosen)
    total_numerator = torch.stack([p[2] for p in parts.values()]).sum(0)
    total_coverage = torch.stack([p[3] for p in parts.values()]).sum(0)
    out = torch.zeros(len(start), dtype=torch.float64)
    for projector, observed, numerator, covered, chosen in parts.values():
        volume = sda_ratio(total_numerator - numerator, total_coverage - covered)
        points = projector.grid_points(moved.subset(chosen).poses)
        out[chosen] = slice_ncc(projector, projector.forward(volume, points), observed).double()
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", type=Path, nargs="+", help="CASE ATLAS_AGE_FOLDER, repeated")
    parser.add_argument("--threads", type=int, default=1)
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
        mixed = mixed_agreement(start, moved, grid_mm).cpu()
        start_error, _ = relative_errors(truth, start.poses)
        refined_error, _ = relative_errors(truth, refined)
        better = torch.from_numpy(refined_error < start_error)
        rules = {
            "shipped (after)": after > before + MARGIN,
            "mixed only": mixed > before + MARGIN,
            "both": (after > before + MARGIN) & (mixed > before + MARGIN),
            "improved": better,
        }
        print(
            f"## {case.name} ({folder.name}): start median {np.median(start_error):.1f} deg, "
            f"every slice refined {np.median(refined_error):.1f}",
            flush=True,
        )
        for name, kept in rules.items():
            poses = torch.where(kept[:, None, None], refined.cpu(), start.poses.double().cpu())
            error, _ = relative_errors(truth, poses)
            print(
                f"  {name}: kept {int(kept.sum())}/{len(kept)} ({int((kept & better).sum())} "
                f"improved), median {np.median(error):.1f} deg, p90 "
                f"{np.percentile(error, 90):.1f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
