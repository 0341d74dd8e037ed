"""``svr demo``: the whole toolkit on built-in data, scored against the truth; or the loss demo."""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import asdict
from typing import TYPE_CHECKING

from svr.cli.common import (
    MODEL_HELP,
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
from svr.files import atomic_write_text, check_output_path

if TYPE_CHECKING:
    from svr.apps.demo_scores import DemoResult
    from svr.apps.loss_demo import LossDemoResult

DEFAULT_OUTPUT_DIR = "svr-demo"

DESCRIPTION = f"""\
Run the toolkit end to end on a case whose truth is known, and score it:
  1. a pose model (--registration cnn): the shipped stack-pose model (--model stack-pose, the
     default: each stack placed in canonical space from its own data), a given one, or a
     slice-pose model trained for a few minutes on the brain volume (--model train;
     in-distribution: it sees the anatomy it is tested on);
  2. three 3 mm stacks simulated from the volume (the built-in phantom unless --input-volume),
     planned along the brain's axes, with random-walk fetal motion and noise;
  3. reconstruction with stack registration (scanner frame) and, with --registration cnn, with
     the model's canonical-space initialisation;
  4. CC, PSNR and SSIM of the initial and the reconstructed volumes against the ground truth
     (after removing the reconstruction frame's rigid offset, which the simulated slice poses
     give, and a linear intensity fit inside the brain mask).
Prints a table and writes DIR/metrics.json, DIR/figure.png (orthogonal views of the truth and of
every volume), the volumes, slice poses and the simulated case. The full run is meant to take
under 10 minutes on 2 CPU cores; --quick runs a small version (a smoke test).

--loss-only runs the older loss demo instead: random slice poses (Euler angles in ±90°,
offsets in ±40 mm) recovered by gradient descent on each pose loss (SE(3) geodesic, PoseNet,
Anchor Points, 6D) from the same start; it prints a table and optionally writes it as JSON.

examples:
  svr demo
  svr demo --output-dir demo-stack --registration stack
  svr demo --output-dir demo-atlas --input-volume GA28/srr.nii.gz --input-mask GA28/mask.nii.gz
  svr demo --output-dir demo-train --model train --device cuda
  svr demo --loss-only --num-poses 512 --steps 200 --output losses.json

default output folder: {DEFAULT_OUTPUT_DIR}
"""

LOSS_DEMO_DEFAULTS = {"num_poses": 512, "steps": 200, "learning_rate": 0.05}
"""The defaults of :class:`svr.apps.loss_demo.LossDemoConfig` that the help shows (a test checks
them against the library), so that building the parser imports no torch."""

# Options of one mode only; their defaults are None so that a stray one can be reported.
RECONSTRUCTION_OPTIONS = ("output_dir", "model", "registration", "train_steps")
LOSS_OPTIONS = ("num_poses", "steps", "learning_rate", "output")

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr demo``."""
    parser = subparsers.add_parser(
        "demo",
        help="simulate, reconstruct and score on built-in data (or --loss-only: the loss demo)",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "--output-dir",
        metavar="DIR",
        help=f"folder to create for the outputs (default: {DEFAULT_OUTPUT_DIR})",
    )
    parser.add_argument(
        "--model",
        metavar="stack-pose|train|default|CHECKPOINT_DIR",
        help="pose model for --registration cnn: 'stack-pose' (the shipped stack-pose model, "
        f"the default), 'train' a slice-pose model on the volume, or {MODEL_HELP}",
    )
    parser.add_argument(
        "--registration",
        choices=("cnn", "stack"),
        help="cnn: reconstruct with stack registration and with the model (default); "
        "stack: stack registration only, no model",
    )
    parser.add_argument(
        "--train-steps",
        type=positive_int,
        metavar="N",
        help="training steps of --model train (default: 2000; 10 with --quick)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a small version for tests: phantom at 2 mm, tiny model, few iterations",
    )
    add_volume_options(parser)
    losses = parser.add_argument_group("loss demo")
    losses.add_argument(
        "--loss-only",
        action="store_true",
        help="run the loss demo (pose recovery by gradient descent on each loss) instead",
    )
    defaults = LOSS_DEMO_DEFAULTS
    losses.add_argument(
        "--num-poses",
        type=positive_int,
        help=f"number of random target poses (default: {defaults['num_poses']})",
    )
    losses.add_argument(
        "--steps",
        type=positive_int,
        help=f"optimisation steps per loss (default: {defaults['steps']})",
    )
    losses.add_argument(
        "--learning-rate",
        type=positive_float,
        help=f"Adam learning rate (default: {defaults['learning_rate']})",
    )
    losses.add_argument("--output", metavar="FILE", help="write the loss table to this JSON file")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an existing --output-dir (or --output)"
    )
    add_common_options(parser)


def _check_mode(args: argparse.Namespace) -> None:
    """Reject the options of the mode not chosen."""
    if args.loss_only:
        stray = [name for name in RECONSTRUCTION_OPTIONS if getattr(args, name) is not None]
        stray += ["quick"] if args.quick else []
        stray += ["input_volume"] if args.input_volume is not None else []
        stray += ["input_mask"] if args.input_mask is not None else []
        mode = "without --loss-only"
    else:
        stray = [name for name in LOSS_OPTIONS if getattr(args, name) is not None]
        mode = "with --loss-only"
    if stray:
        option = "--" + stray[0].replace("_", "-")
        raise CliError(f"{option}: applies only {mode}")


def format_table(results: list[LossDemoResult]) -> str:
    """Loss-demo results as a fixed-width text table."""
    lines = [
        f"{'loss':<8} {'median rot (deg)':>16} {'median trans (mm)':>17} "
        f"{'recovered':>9} {'time (s)':>8}"
    ]
    lines += [
        f"{r.method:<8} {r.median_rotation_deg:>16.4f} {r.median_translation_mm:>17.4f} "
        f"{r.recovered_fraction:>9.1%} {r.seconds:>8.2f}"
        for r in results
    ]
    return "\n".join(lines)


def format_scores(result: DemoResult) -> str:
    """Demo scores as a fixed-width text table, then the frame offsets and pose errors."""
    lines = [
        f"{'registration':<12} {'frame':<9} {'volume':<13} {'CC':>6} {'PSNR (dB)':>9} {'SSIM':>6}"
    ]
    for m in result.methods:
        for kind, score in (("initial", m.initial), ("reconstructed", m.reconstructed)):
            lines.append(
                f"{m.registration:<12} {m.frame:<9} {kind:<13} {score.cc:>6.3f} "
                f"{score.psnr_db:>9.2f} {score.ssim:>6.3f}"
            )
    lines.append("")
    for m in result.methods:
        lines.append(
            f"{m.registration}: frame offset {m.frame_offset_deg:.1f} deg, "
            f"{m.frame_offset_mm:.1f} mm; median slice pose error after alignment "
            f"{m.slice_rotation_error_deg:.2f} deg, {m.slice_translation_error_mm:.2f} mm; "
            f"initialisation {', '.join(m.initialisation)}; {m.rounds} rounds"
            + {True: " (converged)", False: " (not converged)", None: ""}[m.converged]
            + f"; {m.seconds:.0f} s"
        )
    timings = ", ".join(f"{name} {s:.0f} s" for name, s in result.timings_s.items())
    lines.append(f"time: {timings}; total {sum(result.timings_s.values()):.0f} s")
    return "\n".join(lines)


_OPTIONS = {
    "seed": "--seed",
    "registrations": "--registration",
    "TrainConfig.steps": "--train-steps",
    "OptimConfig.warmup_steps": "--train-steps",
    "TrainConfig.checkpoint_every": "--train-steps",
    "num_poses": "--num-poses",
    "LossDemoConfig.steps": "--steps",
    "learning_rate": "--learning-rate",
    "device": "--device",
}
"""The option behind each configuration field the demo sets, in either mode
(:func:`~svr.cli.common.option_errors`)."""


def _run_loss_demo(args: argparse.Namespace) -> int:
    import torch

    from svr.apps.loss_demo import LossDemoConfig, run_loss_demo

    if args.output is not None:
        check_output_path(args.output, args.overwrite)
    defaults = LossDemoConfig()
    with option_errors(_OPTIONS):
        config = LossDemoConfig(
            num_poses=args.num_poses or defaults.num_poses,
            steps=args.steps or defaults.steps,
            learning_rate=args.learning_rate or defaults.learning_rate,
            seed=args.seed,
            device=resolve_device(args.device),
            progress=not args.quiet,
        )
    from svr.sampling.poses import random_slice_poses

    targets = random_slice_poses(config.num_poses, torch.Generator().manual_seed(config.seed))
    results = run_loss_demo(config, targets)
    print(format_table(results))
    print("recovered: rotation error < 1 deg and translation error < 1 mm")
    if args.output is not None:
        payload = {"config": asdict(config), "results": [asdict(r) for r in results]}
        path = atomic_write_text(
            args.output, json.dumps(payload, indent=2) + "\n", overwrite=args.overwrite
        )
        print(f"wrote {path}")
    return 0


def run(args: argparse.Namespace) -> int:
    """Run ``svr demo``."""
    _check_mode(args)
    if args.loss_only:
        return _run_loss_demo(args)
    from svr.apps.demo import TRAIN_MODEL, demo_config, quick_phantom, run_demo
    from svr.models.stack_pose import STACK_POSE_MODEL

    output_dir = args.output_dir or DEFAULT_OUTPUT_DIR
    check_output_path(output_dir, args.overwrite)
    device = resolve_device(args.device)
    registration = args.registration or "cnn"
    model = args.model or STACK_POSE_MODEL
    if registration == "stack" and args.model is not None:
        log.warning("--model is used only with --registration cnn; ignoring %s", args.model)
    if model != TRAIN_MODEL and args.train_steps is not None:
        log.warning("--train-steps is used only with --model train; ignoring it")
    with option_errors(_OPTIONS):
        config = demo_config(
            quick=args.quick,
            seed=args.seed,
            train_steps=args.train_steps,
            registrations=("stack", "cnn") if registration == "cnn" else ("stack",),
        )
    if args.quick and args.input_volume is None and args.input_mask is None:
        volume, source = quick_phantom(args.phantom_ga)
    else:
        volume, source = load_input_volume(args)
    result = run_demo(
        volume,
        config,
        output_dir,
        model=model,
        source=source,
        device=device,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    print(format_scores(result))
    print(
        f"wrote {result.output_dir}: metrics.json, figure.png, ground_truth.nii.gz, "
        f"{', '.join(m.registration + '/' for m in result.methods)} and case/"
    )
    return 0
