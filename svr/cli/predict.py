"""``svr predict``: canonical slice poses of acquired stacks from a trained slice-pose CNN."""

from __future__ import annotations

import argparse
import logging

from svr.cli.common import (
    MODEL_HELP,
    CliError,
    HelpFormatter,
    add_common_options,
    non_negative_float,
    positive_float,
    positive_int,
    resolve_device,
)
from svr.cli.recon_options import atlas_paths as checked_atlas_paths
from svr.files import check_output_path

DESCRIPTION = """\
Predict the pose of every slice of thick-slice stacks in canonical (atlas) space with a model
trained by `svr train`. Each slice (a k-plane of its stack) is resampled in-plane to the model's
spacing, cropped to its input size around the brain mask (or the slice centre without masks),
masked and divided by the stack's in-mask 99th intensity percentile, as in training. Slices whose
mask is empty are skipped. The poses are written as a pose table (.csv or .json): one row per
slice with the stack file, the slice index, the 6-vector (rad, mm), the 3x4 matrix and the frame
"canonical"; each pose maps the slice's own plane (origin at its centre, mm) to canonical space.
A slices.nii.gz written by `svr sample` is a stack; --input-slices reads NeSVoR-style slice
folders (0.nii.gz, 1.nii.gz, ... and optional mask_0.nii.gz, ...).

examples:
  svr predict --model default --input-stacks ax.nii.gz --stack-masks ax_mask.nii.gz \\
      --output-poses poses.csv
  svr predict --model runs/se3/checkpoints/step_000020000 \\
      --input-stacks ax.nii.gz cor.nii.gz sag.nii.gz \\
      --stack-masks ax_mask.nii.gz cor_mask.nii.gz sag_mask.nii.gz --output-poses poses.csv
  svr predict --model runs/se3/checkpoints/step_000020000 --input-stacks slices.nii.gz \\
      --output-poses poses.json --device cpu
"""

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr predict``."""
    p = subparsers.add_parser(
        "predict",
        help="predict slice poses in canonical space with a trained model",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "--model",
        required=True,
        metavar="CHECKPOINT_DIR",
        help=f"pose model: {MODEL_HELP}; with a stack-pose model (svr train-stack-pose, or "
        "'stack-pose' for the shipped one) every stack is posed as a whole from its own data "
        "and each slice takes its stack's pose, or its own from --atlas-volume (needs "
        "--stack-masks)",
    )
    p.add_argument("--input-stacks", nargs="+", default=[], metavar="STACK", help="stacks (NIfTI)")
    p.add_argument(
        "--stack-masks",
        nargs="+",
        default=[],
        metavar="MASK",
        help="brain masks (NIfTI), one per stack in order",
    )
    p.add_argument(
        "--input-slices",
        nargs="+",
        default=[],
        metavar="FOLDER",
        help="NeSVoR-style slice folders (0.nii.gz, 1.nii.gz, ...)",
    )
    p.add_argument(
        "--output-poses", required=True, metavar="FILE", help="pose table to write (.csv or .json)"
    )
    p.add_argument(
        "--output-stack-poses",
        metavar="FILE.json",
        help="with a stack-pose model: also write each stack's pose (stack frame -> canonical: "
        "origin at the stack's centre voxel, axes along its array axes i, j and the slice "
        "normal; 6-vector in rad and mm, and the 4x4 matrix) and how it was found",
    )
    p.add_argument(
        "--atlas-volume",
        metavar="NIFTI",
        help="with a stack-pose model: an atlas of about the fetus's age (with --atlas-mask); "
        "each slice of each stack is then registered to it from the model's stack pose, and the "
        "stack's pose becomes the robust mean of its slices', kept where the slices match the "
        "atlas (mean NCC >= 0.6; else the model's pose stays). The slice thickness is taken to "
        "be the slice spacing",
    )
    p.add_argument("--atlas-mask", metavar="NIFTI", help="the atlas's brain mask")
    p.add_argument(
        "--atlas-dir",
        metavar="DIR",
        help="instead of --atlas-volume: an atlas folder of GA<weeks>*/srr.nii.gz and "
        "mask.nii.gz (the Fidon 2021 layout); the atlas of the age nearest --gestational-age is "
        "used",
    )
    p.add_argument(
        "--gestational-age",
        type=positive_float,
        metavar="WEEKS",
        help="the fetus's gestational age, for --atlas-dir",
    )
    p.add_argument(
        "--restart-deg",
        type=non_negative_float,
        default=10.0,
        metavar="DEG",
        help="with a stack-pose model: the turn of six restarts of the network about each "
        "stack's chosen pose, averaged (0: none). Restarts put more simulated held-out stacks "
        "within 10 degrees; svr reconstruct does without by default (--restart-deg 0 there), "
        "because the reconstructions they started were lower",
    )
    p.add_argument("--batch-size", type=positive_int, default=64, help="slices per forward pass")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_common_options(p)


def run(args: argparse.Namespace) -> int:
    """Run ``svr predict``."""
    import torch
    from tqdm import tqdm

    from svr.image import ImageError, load_nifti
    from svr.models.predict import load_any_pose_model, predict_plane_poses, predict_slice_folder
    from svr.models.stack_pose import StackPoseNet
    from svr.pose_io import PoseTable, write_pose_table

    if not args.input_stacks and not args.input_slices:
        raise CliError("nothing to predict: give --input-stacks and/or --input-slices")
    if args.stack_masks and len(args.stack_masks) != len(args.input_stacks):
        raise CliError(
            f"--stack-masks: got {len(args.stack_masks)} masks for {len(args.input_stacks)} "
            "stacks; give none or one per stack"
        )
    if not args.output_poses.endswith((".csv", ".json")):
        raise CliError(f"--output-poses {args.output_poses}: must end in .csv or .json")
    check_output_path(args.output_poses, args.overwrite)
    if args.output_stack_poses is not None:
        if not args.output_stack_poses.endswith(".json"):
            raise CliError(f"--output-stack-poses {args.output_stack_poses}: must end in .json")
        check_output_path(args.output_stack_poses, args.overwrite)
    # One atlas: --atlas-volume, or the age nearest --gestational-age in --atlas-dir (first).
    atlas_paths = checked_atlas_paths(args, None)[:1]
    device = resolve_device(args.device)
    model = load_any_pose_model(args.model, device)
    if isinstance(model, StackPoseNet):
        return _predict_stacks(args, model, atlas_paths[0] if atlas_paths else None)
    if args.output_stack_poses is not None or atlas_paths:
        raise CliError(
            "--output-stack-poses and --atlas-volume need a stack-pose model "
            f"(--model {args.model} is a slice-pose model)"
        )
    masks = args.stack_masks or [None] * len(args.input_stacks)
    inputs = [
        *((path, mask, False) for path, mask in zip(args.input_stacks, masks, strict=True)),
        *((folder, None, True) for folder in args.input_slices),
    ]
    tables = []
    for path, mask, is_folder in tqdm(inputs, desc="stacks", unit="stack", disable=args.quiet):
        if is_folder:
            table = predict_slice_folder(model, path, args.batch_size)
        else:
            stack = load_nifti(path)
            mask_image = None if mask is None else load_nifti(mask)
            if mask_image is not None and not bool((mask_image.data > 0.5).any()):
                raise ImageError(f"{mask}: the mask is empty")
            table = predict_plane_poses(
                model,
                stack,
                mask_image,
                args.batch_size,
                name=str(path),
                mask_name=None if mask is None else str(mask),
            ).table(str(path))
        log.debug("%s: %d slices posed", path, len(table.poses))
        tables.append(table)
    result = PoseTable(
        [f for t in tables for f in t.files],
        torch.cat([t.slice_indices for t in tables]),
        torch.cat([t.poses for t in tables]),
        "canonical",
    )
    write_pose_table(result, args.output_poses, args.overwrite)
    print(f"wrote {args.output_poses}: {len(result.poses)} slices from {len(inputs)} inputs")
    return 0


def _predict_stacks(
    args: argparse.Namespace, model, atlas_path: tuple[str, str] | None = None
) -> int:
    """``svr predict`` with a stack-pose model: one pose per stack, its slices follow it.

    ``atlas_path``: the ``(volume, mask)`` of the atlas each stack's slices are fitted to, or
    ``None``.
    """
    import json

    import torch
    from tqdm import tqdm

    from svr.files import atomic_write_text
    from svr.geometry import se3_compose, se3_to_vector
    from svr.image import ImageError, load_nifti, stack_slice_poses
    from svr.pose_io import PoseTable, write_pose_table
    from svr.reconstruction.initialisation.atlas_slices import (
        ATLAS_SLICES_MIN_NCC,
        fit_slices_to_atlas,
    )
    from svr.reconstruction.initialisation.stack_pose import estimate_stack_pose
    from svr.sampling.volume import load_canonical_volume

    if args.input_slices:
        raise CliError("--input-slices: a stack-pose model poses whole stacks; give --input-stacks")
    if not args.stack_masks:
        raise CliError("a stack-pose model needs --stack-masks (one brain mask per stack)")
    atlas = None if atlas_path is None else load_canonical_volume(*atlas_path)
    files, indices, poses, records = [], [], [], []
    for path, mask_path in tqdm(
        list(zip(args.input_stacks, args.stack_masks, strict=True)),
        desc="stacks",
        unit="stack",
        disable=args.quiet,
    ):
        stack, mask = load_nifti(path), load_nifti(mask_path)
        if mask.shape != stack.shape:
            raise ImageError(
                f"{mask_path}: shape {mask.shape} differs from the stack's {stack.shape}"
            )
        inside = mask.data > 0.5
        if int(inside.sum()) < 4:
            raise ImageError(f"{mask_path}: the mask is empty")
        estimate = estimate_stack_pose(model, stack, inside, restart_deg=args.restart_deg)
        pose, method = estimate.pose, estimate.method
        planes = se3_compose(estimate.to_canonical[None], stack_slice_poses(stack))
        if atlas is not None:
            fit = fit_slices_to_atlas(stack, inside, estimate.to_canonical, atlas)
            if fit.kept:
                pose, planes = fit.pose, fit.plane_poses
                method += f"+atlas slices (NCC {fit.ncc:.2f})"
            else:
                method += f" (atlas slices not kept: NCC {fit.ncc:.2f} < {ATLAS_SLICES_MIN_NCC:g})"
            log.info("%s: %s", path, method)
        keep = inside.flatten(0, 1).any(0)
        for k in torch.nonzero(keep).flatten().tolist():
            files.append(str(path))
            indices.append(k)
            poses.append(se3_to_vector(planes[k]))
        records.append(
            {
                "file": str(path),
                "pose": se3_to_vector(pose).tolist(),
                "matrix": pose.tolist(),
                "frame": "canonical",
                "method": method,
                "score": estimate.score,
            }
        )
    table = PoseTable(
        files, torch.tensor(indices, dtype=torch.long), torch.stack(poses), "canonical"
    )
    write_pose_table(table, args.output_poses, args.overwrite)
    written = [args.output_poses]
    if args.output_stack_poses is not None:
        text = json.dumps({"stacks": records}, indent=1)
        atomic_write_text(args.output_stack_poses, text + "\n", args.overwrite)
        written.append(args.output_stack_poses)
    print(f"wrote {', '.join(written)}: {len(files)} slices of {len(records)} stacks")
    return 0
