"""``svr sample``: slices cut from a brain volume at training or evaluation poses."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from svr.cli.common import (
    CliError,
    HelpFormatter,
    add_common_options,
    add_volume_options,
    load_input_volume,
    option_errors,
    positive_float,
    positive_int,
    resolve_device,
)
from svr.files import atomic_directory, check_output_path

if TYPE_CHECKING:
    import torch

    from svr.sampling.poses import PoseDraw

DESCRIPTION = """\
Cut 2D slices from a brain volume (or the built-in phantom) in canonical space, at the paper's
random validation poses (Euler angles in ±90°, offsets in ±40 mm), rotations uniform on SO(3),
or a random subset of the Euler grid (18° and 2 mm steps). Slices with less than
--min-brain-fraction of their pixels in the brain mask are skipped. Writes a preview grid (PNG)
and/or a dataset folder: slices.nii.gz (H x W x N), poses.csv (one row per slice, canonical
frame) and config.json.

examples:
  svr sample --output-preview slices.png
  svr sample --input-volume srr.nii.gz --input-mask mask.nii.gz --num-slices 1000 \\
      --thickness 3 --output-dataset train_slices
"""


SAMPLE_CHUNK = 256  # slices sampled at once (bounds the memory of the sampling grid)


_POSE_DRAWS: dict[str, PoseDraw] = {
    "random": "euler",
    "uniform": "uniform",
    "euler-grid": "euler-grid",
}
"""``--poses`` choices and the :data:`svr.sampling.poses.PoseDraw` kinds they stand for."""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr sample``."""
    p = subparsers.add_parser(
        "sample",
        help="cut slices at training/evaluation poses",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    add_volume_options(p)
    p.add_argument(
        "--poses",
        choices=list(_POSE_DRAWS),
        default="random",
        help="pose distribution",
    )
    p.add_argument("--num-slices", type=positive_int, default=64, help="number of slices")
    p.add_argument("--size", type=positive_int, default=128, help="slice size in pixels (square)")
    p.add_argument("--spacing", type=positive_float, default=1.0, help="in-plane spacing in mm")
    p.add_argument(
        "--thickness",
        type=positive_float,
        default=None,
        help="slice thickness in mm (Gaussian PSF); default: thin slices",
    )
    p.add_argument(
        "--min-brain-fraction",
        type=float,
        default=0.1,
        help="skip slices with a smaller fraction of pixels in the brain mask",
    )
    p.add_argument("--output-preview", help="write a grid of up to 64 slices to this PNG")
    p.add_argument("--output-dataset", help="write the slices and poses to this new folder")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_common_options(p)


def _preview_png(slices: torch.Tensor, path: str, overwrite: bool) -> None:
    import imageio.v3 as iio
    import numpy as np

    from svr.files import atomic_write_bytes

    tiles = slices[:64].numpy()
    cols = int(np.ceil(np.sqrt(len(tiles))))
    rows = int(np.ceil(len(tiles) / cols))
    h, w = tiles.shape[1:]
    mosaic = np.zeros((rows * h, cols * w), dtype=np.float32)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, cols)
        mosaic[r * h : (r + 1) * h, c * w : (c + 1) * w] = tile.T[::-1]  # u rightwards, v upwards
    top = float(np.percentile(mosaic[mosaic > 0], 99.5)) if (mosaic > 0).any() else 1.0
    image = (np.clip(mosaic / top, 0, 1) * 255).astype(np.uint8)
    atomic_write_bytes(path, iio.imwrite("<bytes>", image, extension=".png"), overwrite)


_OPTIONS = {"size": "--size", "spacing_mm": "--spacing", "thickness_mm": "--thickness"}
"""The option behind each SliceConfig field (:func:`~svr.cli.common.option_errors`)."""


def run(args: argparse.Namespace) -> int:
    """Run ``svr sample``."""
    import torch
    from tqdm import tqdm

    from svr.image import Image, save_nifti
    from svr.pose_io import PoseTable, write_pose_table
    from svr.sampling.poses import draw_validation_poses
    from svr.sampling.slicer import SliceConfig, sample_slices

    if args.output_preview is None and args.output_dataset is None:
        raise CliError("nothing to write: give --output-preview and/or --output-dataset")
    if not 0 <= args.min_brain_fraction < 1:
        raise CliError(f"--min-brain-fraction must be in [0, 1), got {args.min_brain_fraction}")
    for out in (args.output_preview, args.output_dataset):
        if out is not None:
            check_output_path(out, args.overwrite)
    device = resolve_device(args.device)
    volume, source = load_input_volume(args)
    volume = volume.to(device)
    with option_errors(_OPTIONS):
        config = SliceConfig(
            size=(args.size, args.size), spacing_mm=args.spacing, thickness_mm=args.thickness
        )
    generator = torch.Generator().manual_seed(args.seed)
    kind = _POSE_DRAWS[args.poses]
    try:
        poses = draw_validation_poses(
            volume, args.num_slices, config, generator, kind, args.min_brain_fraction
        ).cpu()
    except ValueError as err:
        raise CliError(f"--min-brain-fraction {args.min_brain_fraction:g}: {err}") from err
    chunks = torch.split(poses, SAMPLE_CHUNK)
    slices = torch.cat(
        [
            sample_slices(volume.image, chunk.to(device), config).cpu()
            for chunk in tqdm(
                chunks, desc="slices", unit="chunk", disable=args.quiet or len(chunks) < 2
            )
        ]
    )
    if args.output_preview is not None:
        _preview_png(slices, args.output_preview, args.overwrite)
        print(f"wrote {args.output_preview}")
    if args.output_dataset is not None:
        with atomic_directory(args.output_dataset, args.overwrite) as tmp:
            affine = torch.diag(
                torch.tensor([args.spacing, args.spacing, 1.0, 1.0], dtype=torch.float64)
            )
            save_nifti(Image(slices.permute(1, 2, 0).contiguous(), affine), tmp / "slices.nii.gz")
            table = PoseTable(
                ["slices.nii.gz"] * len(poses), torch.arange(len(poses)), poses, "canonical"
            )
            write_pose_table(table, tmp / "poses.csv")
            info = {
                "source": source,
                "poses": args.poses,
                "size": args.size,
                "spacing_mm": args.spacing,
                "thickness_mm": args.thickness,
                "min_brain_fraction": args.min_brain_fraction,
                "seed": args.seed,
                "centre_mm": volume.centre_mm.tolist(),
            }
            (tmp / "config.json").write_text(json.dumps(info, indent=1) + "\n")
        print(f"wrote {args.output_dataset}: {len(poses)} slices from {source}")
    return 0
