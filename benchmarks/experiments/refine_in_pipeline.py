"""The slice refiner in the pipeline's place, measured per slice: after the learned start.

For each case: the slices start where ``--registration cnn`` starts them
(:func:`svr.reconstruction.initialisation.initialise`, shipped stack-pose network, no slice
refinement); then every slice is refined against a reference by refiner stages and kept where the
other stacks agree better (:func:`svr.reconstruction.initialisation.slice_refinement.place_slices`,
what ``learned_start`` does with an atlas). Printed: the slices' pose errors against the truth (up
to one global rigid transform) at the start, after the stages (every slice), and kept; with
``--reconstruct``, the reconstruction (adaptive schedule) from the start and from the kept poses,
scored by ``../shared/tools/score_recon.py``.

The reference is ``--atlas`` (an age folder with ``srr.nii.gz`` and ``mask.nii.gz``), or with
``--oracle-reference`` the case's true volume (the slices first moved into the truth's frame by
one rigid transform: what the refiner does given a perfect reference). The stages are the shipped
ones (``--steps`` each), or saved ones (``--stage NAME=PATH ... --schedule NAME ...``).
``--subject-pass`` then refines the kept poses once more (the shipped ``fine`` stage, 3 steps)
against the subject's own volume: the scattered-data volume of the brain-masked slices at their
kept poses, each stack against the other stacks' only, on the refiner's reference grid.
``--subject-start`` refines the *start* that way instead, keeps a move where the other stacks at
their start agree better (the rule of a start that agrees), and keeps the atlas-refined pose only
where the subject-refined one lies within each ``--agree-deg`` of it.

    python benchmarks/experiments/refine_in_pipeline.py --cases ../shared/data/bench/sb32-severe
        --atlas ../shared/data/atlas/sb-fidon2021/GA33_operated --reconstruct
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_common import SHARED, load_case_stacks, run_scorer
from bench_packet_refinement import describe, relative_errors, true_canonical

from svr.geometry import rotation_angle, se3_compose, se3_inverse
from svr.geometry.averaging import robust_mean_pose
from svr.image import Image, save_nifti
from svr.models.pretrained import stack_pose_model_path
from svr.models.slice_refiner import load_slice_refiner, shipped_slice_refiners
from svr.models.stack_pose import load_stack_pose_model
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation import initialise
from svr.reconstruction.initialisation.case_evaluation import load_case
from svr.reconstruction.initialisation.slice_refinement import (
    KEEP_MARGIN,
    REFERENCE_VOXEL_MM,
    _normalised,
    atlas_reference,
    place_slices,
    refine_poses,
)
from svr.reconstruction.pipeline import reconstruct_from_poses
from svr.reconstruction.registration import _sda, slice_agreement
from svr.reconstruction.slices import SliceSet, extract_slices
from svr.reconstruction.superres import output_grid
from svr.sampling.volume import load_canonical_volume


def _stages(args: argparse.Namespace) -> list:
    if not args.stage:
        return list(zip(shipped_slice_refiners(), args.steps, strict=True))
    saved = {}
    for item in args.stage:
        name, _, path = item.partition("=")
        saved[name] = load_slice_refiner(Path(path))
    return [(saved[name], 1) for name in args.schedule]


def subject_pass(slices: SliceSet) -> torch.Tensor:
    """(N, 4, 4) each stack's slices refined by ``fine`` x 3 against the other stacks' volume."""
    fine = shipped_slice_refiners()[-1]
    masked = dataclasses.replace(slices, images=slices.images * slices.masks)
    poses = slices.poses.to(torch.float64).clone()
    for sid in range(len(slices.stack_names)):
        mine = slices.stack_ids == sid
        others = masked.subset(~mine)
        grid = output_grid(others, REFERENCE_VOXEL_MM)
        data = _sda(others, grid).float()
        reference = Image(_normalised(data, data > 0), grid.affine)  # as atlas_reference
        poses[mine] = refine_poses([(fine, 3)], slices.subset(mine), reference)
    return poses


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=Path, nargs="+", required=True)
    parser.add_argument("--atlas", type=Path, default=None, help="the reference's age folder")
    parser.add_argument("--oracle-reference", action="store_true")
    parser.add_argument("--steps", type=int, nargs=2, default=[4, 3], help="shipped stages' steps")
    parser.add_argument("--stage", action="append", default=[], help="NAME=PATH, saved stages")
    parser.add_argument("--schedule", nargs="*", default=[], help="saved stage names, in order")
    parser.add_argument("--resolution-mm", type=float, default=2.0)
    parser.add_argument(
        "--subject-pass",
        action="store_true",
        help="then refine the kept poses against the other stacks' own volume",
    )
    parser.add_argument(
        "--subject-start",
        action="store_true",
        help="also refine the start (fine x 3) against the other stacks' own volume, kept as "
        "the trusted branch keeps moves",
    )
    parser.add_argument("--agree-deg", type=float, nargs="*", default=[2.0, 4.0])
    parser.add_argument("--reconstruct", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("runs/refine-in-pipeline"))
    parser.add_argument("--scorer", type=Path, default=SHARED / "tools" / "score_recon.py")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    if (args.atlas is None) == (not args.oracle_reference):
        parser.error("give one of --atlas and --oracle-reference")
    torch.set_num_threads(args.threads)
    stages = _stages(args)
    model = load_stack_pose_model(stack_pose_model_path())
    config = ReconstructionConfig.preset("learned")
    args.out.mkdir(parents=True, exist_ok=True)
    atlas = None
    if args.atlas is not None:
        atlas = load_canonical_volume(args.atlas / "srr.nii.gz", args.atlas / "mask.nii.gz")
    for case in args.cases:
        stacks = load_case_stacks(case)
        slices = extract_slices(stacks)
        truth = true_canonical(case, slices)
        start = initialise(slices, stacks, config, model)
        placed_in = start.slices
        reference = atlas
        if args.oracle_reference:
            frame = robust_mean_pose(se3_compose(truth, se3_inverse(placed_in.poses)))
            placed_in = placed_in.with_poses(se3_compose(frame[None], placed_in.poses))
            reference = load_case(case).volume
        print(f"## {case.name}: kept {start.choice}", flush=True)
        began = time.perf_counter()
        placed = place_slices(placed_in, reference, stages, args.resolution_mm)
        seconds = time.perf_counter() - began
        kept = placed.kept
        for label, poses in (
            ("start", placed_in.poses),
            (f"kept ({int(kept.sum())}/{len(kept)})", placed.poses),
        ):
            rot, cen = relative_errors(truth, poses)
            print(f"- {label}: {describe(rot, cen)}", flush=True)
        print(f"- placement {seconds:.1f} s ({1000 * seconds / len(kept):.1f} ms per slice)")
        if args.subject_pass:
            again = subject_pass(placed_in.with_poses(placed.poses.to(placed_in.poses)))
            rot, cen = relative_errors(truth, again)
            print(
                f"- then against the other stacks' own volume (every slice): {describe(rot, cen)}"
            )
        if args.subject_start:
            mine = subject_pass(placed_in)
            rot, cen = relative_errors(truth, mine)
            print(f"- from the start against the other stacks' own volume: {describe(rot, cen)}")
            grid_mm = config.initialisation_grid_mm
            before = slice_agreement(placed_in, grid_mm, leave_out=True)
            at_start = slice_agreement(placed_in, grid_mm, True, at=mine.to(placed_in.poses))
            keep = (at_start > before + KEEP_MARGIN).cpu()
            kept_poses = torch.where(keep[:, None, None], mine, placed_in.poses.double().cpu())
            rot, cen = relative_errors(truth, kept_poses)
            print(
                f"- the same, kept where the others at their start agree better "
                f"({int(keep.sum())}/{len(keep)}; start median NCC {float(before.median()):.2f}): "
                f"{describe(rot, cen)}",
                flush=True,
            )
            # Both references: the atlas-refined pose, kept where the subject-refined one
            # lands near it and the others at their start agree better.
            refined = refine_poses(stages, placed_in, atlas_reference(reference)).cpu()
            apart = torch.rad2deg(rotation_angle(refined.double(), mine.double()))
            agree = slice_agreement(placed_in, grid_mm, True, at=refined.to(placed_in.poses))
            for limit in args.agree_deg:
                keep = ((apart < limit) & (agree > before + KEEP_MARGIN).cpu()).cpu()
                both = torch.where(keep[:, None, None], refined, placed_in.poses.double().cpu())
                rot, cen = relative_errors(truth, both)
                print(
                    f"- atlas-refined, kept where the subject-refined pose is within {limit:g} deg "
                    f"and the others agree ({int(keep.sum())}/{len(keep)}): {describe(rot, cen)}",
                    flush=True,
                )
        if not args.reconstruct:
            continue
        for label, poses in (("start", placed_in.poses), ("kept", placed.poses)):
            began = time.perf_counter()
            result = reconstruct_from_poses(stacks, poses, "canonical", config, progress=False)
            path = args.out / f"{case.name}-{label}.nii.gz"
            save_nifti(result.volume, path, overwrite=True)
            score = run_scorer(args.scorer, path, case)
            rot, cen = relative_errors(truth, result.slices.poses)
            print(
                f"- SVR from {label}: PSNR {score['psnr']:.2f} dB, SSIM {score['ssim']:.4f};"
                f" final {describe(rot, cen)}; {time.perf_counter() - began:.0f} s",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
