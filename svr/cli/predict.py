"""``svr predict``: canonical slice poses of acquired stacks from a trained slice-pose CNN."""

from __future__ import annotations

import argparse
import logging

import torch
from tqdm import tqdm

from svr.cli.common import (
    MODEL_HELP,
    CliError,
    HelpFormatter,
    add_common_options,
    positive_int,
    resolve_device,
)
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
        help=f"slice-pose model: {MODEL_HELP}",
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
    p.add_argument("--batch-size", type=positive_int, default=64, help="slices per forward pass")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_common_options(p)


def run(args: argparse.Namespace) -> int:
    """Run ``svr predict``."""
    from svr.image import ImageError, load_nifti
    from svr.models.predict import load_pose_model, predict_plane_poses, predict_slice_folder
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
    device = resolve_device(args.device)
    model = load_pose_model(args.model, device)
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
