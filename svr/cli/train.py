"""``svr train``: train a slice-pose CNN with the SE(3) geodesic loss or a baseline."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from svr.cli.common import (
    LOSS_HELP,
    CliError,
    HelpFormatter,
    add_common_options,
    add_rotation_option,
    check_run_folder,
    option_errors,
    positive_float,
    positive_int,
    registered_loss,
    resolve_device,
)
from svr.cli.defaults import SE3_ROTATIONS, SYMMETRY_MODES, SYMMETRY_THRESHOLD

DESCRIPTION = """\
Train a CNN that predicts each 2D slice's pose in canonical (atlas) space, on slices cut on the
fly from brain volumes (an atlas folder, volume/mask pairs, or the built-in phantom) at random
poses or at the paper's Euler grid (--pose-sampling grid), with scanner-like augmentation.
Checkpoints (safetensors + JSON) are written every --checkpoint-every steps; rerunning the same
command resumes from the newest one.

Atlases: the Fidon 2021 spina bifida atlas (zenodo.org/record/5524312: GA21..GA34 folders with
srr.nii.gz and mask.nii.gz, downloaded to a folder such as atlas/) or any folder laid out alike.

examples:
  svr train --output-dir runs/phantom --steps 200
  svr train --output-dir runs/se3 --atlas-dir atlas/ \\
      --hold-out 24 28 32 --loss se3 --steps 20000 --thickness-range 1 4 --augment
  svr train --output-dir runs/grid --atlas-dir atlas/ \\
      --hold-out 24 28 32 --pose-sampling grid --steps 60000 --device cuda
  torchrun --nproc_per_node 2 -m svr train --output-dir runs/ddp --steps 1000
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr train``."""
    p = subparsers.add_parser(
        "train",
        help="train a slice-pose CNN",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument("--output-dir", required=True, help="folder for checkpoints and logs")
    _add_volume_options(p)
    _add_model_options(p)
    _add_slice_options(p)
    _add_optimisation_options(p)
    _add_run_options(p)
    add_common_options(p)


def _add_volume_options(p: argparse.ArgumentParser) -> None:
    """The training volumes: an atlas folder, volume/mask pairs or the built-in phantoms."""
    data = p.add_argument_group("training volumes (default: the built-in phantom)")
    data.add_argument("--atlas-dir", help="folder of GA*/srr.nii.gz + GA*/mask.nii.gz volumes")
    data.add_argument(
        "--hold-out",
        type=float,
        nargs="*",
        default=[],
        help="gestational ages (weeks) of --atlas-dir to leave out",
    )
    data.add_argument("--input-volumes", nargs="*", default=[], help="volume files")
    data.add_argument("--input-masks", nargs="*", default=[], help="their masks, in order")
    data.add_argument(
        "--phantom-ga",
        type=positive_float,
        nargs="*",
        default=[24.0, 28.0, 32.0],
        help="gestational ages of built-in phantoms, without other volumes",
    )


def _add_model_options(p: argparse.ArgumentParser) -> None:
    """The network, its output representation and loss, and the loss's mirror symmetry."""
    model = p.add_argument_group("model")
    model.add_argument(
        "--loss",
        type=registered_loss,
        default="se3",
        metavar="NAME",
        help=LOSS_HELP,
    )
    model.add_argument("--backbone", choices=["resnet", "inception"], default="resnet")
    model.add_argument("--width", type=positive_int, default=32, help="channels of the first stage")
    model.add_argument("--depth", type=positive_int, default=4, help="downsampling stages")
    model.add_argument(
        "--metric-weights",
        type=float,
        nargs="+",
        default=None,
        help="SE(3) loss Z: 6 diagonal or 36 row-major numbers (rad, mm units)",
    )
    model.add_argument(
        "--se3-rotation",
        choices=SE3_ROTATIONS,
        default="rotvec",
        help="se3 head: regress the rotation vector, or 6D columns turned into it (continuous "
        "over all of SO(3); the loss is the same SE(3) geodesic loss)",
    )
    model.add_argument(
        "--symmetry",
        choices=SYMMETRY_MODES,
        default="auto",
        help="mirror symmetry of the training anatomy: the loss goes to the nearer of a slice's "
        "pose and its mirror twin. auto: measure each volume's reflection plane and use it when "
        f"every volume is symmetric (brain r >= {SYMMETRY_THRESHOLD}); sagittal: the canonical "
        "plane x = 0; none: the plain loss",
    )


def _add_slice_options(p: argparse.ArgumentParser) -> None:
    """The training slices: grid, thickness, poses and augmentation."""
    slices = p.add_argument_group("slices")
    slices.add_argument("--size", type=positive_int, default=128, help="slice size in pixels")
    slices.add_argument("--spacing", type=positive_float, default=1.0, help="in-plane spacing mm")
    slices.add_argument(
        "--thickness-range",
        type=positive_float,
        nargs=2,
        default=None,
        metavar=("LOW", "HIGH"),
        help="slice thickness range in mm (PSF)",
    )
    slices.add_argument(
        "--spacing-range",
        type=positive_float,
        nargs=2,
        default=None,
        metavar=("LOW", "HIGH"),
        help="jitter of the in-plane spacing in mm",
    )
    add_rotation_option(slices)
    slices.add_argument(
        "--pose-sampling",
        choices=["random", "grid"],
        default="random",
        help="random: new random poses every batch (--rotation); grid: the paper's Euler grid "
        "(Rx, Ry, Rz in 18° steps over ±90°, Tz in 2 mm steps over ±40 mm) of every volume, "
        "shuffled (needs --rotation euler; the sweep at the start takes a while on a CPU)",
    )
    slices.add_argument("--shift-mm", type=float, default=0.0, help="in-plane shift range")
    slices.add_argument(
        "--augment",
        action="store_true",
        help="intensity scaling, gamma, bias field and Rician noise",
    )
    slices.add_argument(
        "--scale-range",
        type=positive_float,
        nargs=2,
        default=None,
        metavar=("LOW", "HIGH"),
        help="scale each batch's brain by per-axis factors in this range (other sizes and shapes)",
    )
    slices.add_argument(
        "--deform-mm",
        type=float,
        default=0.0,
        metavar="MM",
        help="random smooth non-rigid deformation of each batch's brain: standard deviation of "
        "the control displacements (about 30 mm apart), mm; 0 (default) for none",
    )


def _add_optimisation_options(p: argparse.ArgumentParser) -> None:
    """Steps, batch size, optimiser and schedule."""
    opt = p.add_argument_group("optimisation")
    opt.add_argument("--steps", type=positive_int, default=1000)
    opt.add_argument("--batch-size", type=positive_int, default=32)
    opt.add_argument("--optimizer", choices=["adamw", "sgd"], default="adamw")
    opt.add_argument("--lr", type=positive_float, default=1e-3)
    opt.add_argument("--weight-decay", type=float, default=1e-4)
    opt.add_argument("--schedule", choices=["cosine", "constant"], default="cosine")
    opt.add_argument("--warmup-steps", type=int, default=100)
    opt.add_argument("--amp", action="store_true", help="mixed precision (CUDA)")
    opt.add_argument("--workers", type=int, default=0, help="data-loading processes")


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """Checkpoints, logs and resuming."""
    run = p.add_argument_group("checkpoints and logs")
    run.add_argument("--checkpoint-every", type=positive_int, default=500)
    run.add_argument("--keep-checkpoints", type=positive_int, default=3)
    run.add_argument("--log-every", type=positive_int, default=10)
    run.add_argument("--no-resume", action="store_true", help="do not resume (needs --overwrite)")
    run.add_argument(
        "--overwrite",
        action="store_true",
        help="start afresh in an --output-dir that holds checkpoints",
    )


_OPTIONS = {
    "output_dir": "--output-dir",
    "BackboneConfig.name": "--backbone",
    "width": "--width",
    "depth": "--depth",
    "representation": "--loss",
    "data.representation": "--loss",
    "input_size": "--size",
    "size": "--size",
    "spacing_mm": "--spacing",
    "se3_rotation": "--se3-rotation",
    "symmetry_planes": "--symmetry",
    "thickness_range_mm": "--thickness-range",
    "spacing_range_mm": "--spacing-range",
    "rotation": "--rotation",
    "data.rotation": "--rotation",
    "shift_mm": "--shift-mm",
    "scale_range": "--scale-range",
    "deform_mm": "--deform-mm",
    "batch_size": "--batch-size",
    "OptimConfig.name": "--optimizer",
    "lr": "--lr",
    "weight_decay": "--weight-decay",
    "schedule": "--schedule",
    "warmup_steps": "--warmup-steps",
    "steps": "--steps",
    "metric_weights": "--metric-weights",
    "checkpoint_every": "--checkpoint-every",
    "keep_checkpoints": "--keep-checkpoints",
    "log_every": "--log-every",
    "workers": "--workers",
    "device": "--device",
    "amp": "--amp",
    "seed": "--seed",
    "pose_sampling": "--pose-sampling",
}
"""The option behind each configuration field that ``svr train`` sets
(:func:`~svr.cli.common.option_errors`)."""


def _volumes(args: argparse.Namespace) -> tuple[list, list[str]]:
    """The training volumes named by the options, and a name for each."""
    from svr.sampling.volume import VolumeSourceError, atlas_volume_paths, load_volumes

    if len(args.input_volumes) != len(args.input_masks):
        raise CliError(
            f"--input-volumes ({len(args.input_volumes)}) and --input-masks "
            f"({len(args.input_masks)}) must pair up"
        )
    pairs = [(Path(v), Path(m)) for v, m in zip(args.input_volumes, args.input_masks, strict=True)]
    if args.atlas_dir:
        try:
            pairs += atlas_volume_paths(args.atlas_dir, hold_out=args.hold_out)
        except VolumeSourceError as err:
            raise CliError(f"--atlas-dir: {err}") from err
    return load_volumes(pairs, phantom_ages=args.phantom_ga)


def _symmetry_summary(report: dict) -> str:
    """One line per measured volume and the planes the loss uses."""
    lines = []
    for name, fit in report.get("volumes", {}).items():
        lines.append(
            f"symmetry: {name}: r = {fit['correlation']:.4f} about a plane "
            f"{fit['tilt_deg']:.2f}° from x = 0, offset {fit['offset_mm']:.2f} mm"
        )
    planes = report["planes"]
    if planes:
        used = "; ".join(
            f"normal ({', '.join(f'{v:.4f}' for v in p['normal'])}), offset {p['offset_mm']:.2f} mm"
            for p in planes
        )
        lines.append(f"symmetry ({report['mode']}): loss up to the mirror twin about {used}")
    else:
        lines.append(f"symmetry ({report['mode']}): plain loss (no mirror plane)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run ``svr train``."""
    from svr.files import OutputExistsError
    from svr.models.backbones import BackboneConfig
    from svr.models.network import ModelConfig, loss_function
    from svr.models.train import OptimConfig, TrainConfig, train
    from svr.representation_registry import representations_by_cli_name
    from svr.sampling.augment import SliceAugmentConfig
    from svr.sampling.dataset import SliceDatasetConfig
    from svr.sampling.mirror_planes import resolve_symmetry
    from svr.sampling.slicer import SliceConfig

    check_run_folder(args.output_dir)
    representation = representations_by_cli_name()[args.loss].name
    size = (args.size, args.size)
    with option_errors(_OPTIONS):
        config = TrainConfig(
            output_dir=args.output_dir,
            model=ModelConfig(
                backbone=BackboneConfig(name=args.backbone, width=args.width, depth=args.depth),
                representation=representation,
                input_size=size,
                spacing_mm=args.spacing,
                se3_rotation=args.se3_rotation if representation == "se3" else "rotvec",
            ),
            data=SliceDatasetConfig(
                slice=SliceConfig(size=size, spacing_mm=args.spacing),
                thickness_range_mm=tuple(args.thickness_range) if args.thickness_range else None,
                spacing_range_mm=tuple(args.spacing_range) if args.spacing_range else None,
                rotation=args.rotation,
                shift_mm=args.shift_mm,
                representation=representation,
                augment=SliceAugmentConfig() if args.augment else None,
                scale_range=tuple(args.scale_range) if args.scale_range else None,
                deform_mm=args.deform_mm,
                batch_size=args.batch_size,
                seed=args.seed,
            ),
            optim=OptimConfig(
                name=args.optimizer,
                lr=args.lr,
                weight_decay=args.weight_decay,
                schedule=args.schedule,
                warmup_steps=args.warmup_steps,
            ),
            steps=args.steps,
            metric_weights=tuple(args.metric_weights) if args.metric_weights else None,
            checkpoint_every=args.checkpoint_every,
            keep_checkpoints=args.keep_checkpoints,
            log_every=args.log_every,
            workers=args.workers,
            device=resolve_device(args.device),
            amp=args.amp,
            seed=args.seed,
            pose_sampling=args.pose_sampling,
        )
    if config.metric_weights is not None:
        try:
            loss_function(representation, config.weights_tensor())
        except ValueError as err:
            raise CliError(f"--metric-weights: {err}") from err
    volumes, sources = _volumes(args)
    planes, report = resolve_symmetry(args.symmetry, volumes, sources)
    if not args.quiet:
        print(_symmetry_summary(report), file=sys.stderr)
    with option_errors(_OPTIONS):
        config = dataclasses.replace(
            config,
            model=dataclasses.replace(config.model, symmetry_planes=planes),
            data_sources=tuple(sources),
            symmetry_report=report,
        )
    try:
        result = train(
            config,
            volumes,
            resume=not args.no_resume,
            overwrite=args.overwrite,
            progress=not args.quiet,
        )
    except OutputExistsError as err:
        if not args.no_resume or args.overwrite:
            raise  # another output in the way: worded by svr.cli as any other
        raise CliError(
            f"--output-dir {args.output_dir}: holds checkpoints; resume, or pass --overwrite "
            "to start afresh (to resume, drop --no-resume)"
        ) from err
    summary = {
        "checkpoint": str(result.checkpoint),
        "symmetry_planes": report["planes"],
        "steps": result.steps_done,
        "last_loss": result.last_loss,
    }
    print(json.dumps(summary))
    return 0
