"""``svr train-stack-pose``: train the stack-pose network on stacks simulated from atlas volumes."""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from typing import TYPE_CHECKING, Any

from svr.cli.common import (
    LOSS_HELP,
    CliError,
    HelpFormatter,
    add_common_options,
    check_run_folder,
    non_negative_int,
    option_errors,
    positive_float,
    positive_int,
    registered_loss,
    resolve_device,
)
from svr.cli.defaults import STACK_POSE_MODEL, STACK_POSE_TRAINING, SYNTHESIS_MODES

if TYPE_CHECKING:
    from torch import Tensor

    from svr.cli.stack_pose_brains import TrainingBrains
    from svr.models.stack_pose import StackPoseConfig

DESCRIPTION = """\
Train the stack-pose network (svr.models.stack_pose): each step simulates stacks from the
training brains at uniformly random orientations, with real fetal motion, thickness 2-5 mm, gaps
and overlaps, bias field, noise, signal voids and grown or shrunk masks, and teaches a small 3D
CNN to bring a stack seen in a nearly right canonical frame (within 40 degrees, as the brain
mask's principal axes give) to the right one, with the SE(3) geodesic loss on the stack's pose,
and to tell right frames from wrong ones. The run has two phases: for the last
--fine-tune-steps steps the learning rate restarts lower and --phantoms procedural brains join
the atlas ones (anatomy unlike the atlas's). Checkpoints go to --output-dir every
--checkpoint-every steps; running the same command again resumes from the newest. --minutes
stops a run after a checkpoint once that much time has passed (the default recipe fits in 2
hours on one CPU core; on a GPU, simulation is the bottleneck: add --device cuda --workers N, N
about the number of free cores). --fine-tune-seed runs the second phase as a separate
fine-tuning run of the first phase's weights would be: the shipped model's two runs as one
command (see docs/training.md).
--anatomy-variants adds label-edited variants of each atlas brain (smaller ventricles, a larger
cerebellum, re-drawn contrast) for scans of fetuses unlike the spina bifida atlas's.
--synthesis labels (or mixed) simulates a share of the stacks (--synthesis-fraction) from a
synthetic copy of their brain: its tissue labels (parcellation.nii.gz) painted with a random
contrast, texture, bias field, blur and noise (or, mixed, its own image remapped per label), so
that the network learns the brain's shape rather than one atlas family's contrast. Use the
result with `svr reconstruct --registration cnn --model OUTPUT_DIR`, and check its output frame
on a real scan before trusting it.

Atlases: the Fidon 2021 spina bifida atlas (zenodo.org/record/5524312: GA21..GA34 folders with
srr.nii.gz and mask.nii.gz) or any folder laid out alike; give several folders to --atlas-dir to
train on several atlas families at once (their volumes must be aligned in one canonical frame;
--hold-out leaves those ages out of each). Motion: the fetal head-motion trajectories that SVoRT
published (svort_fetal_motion_trajectories.npz).

--loss picks the pose output and its loss (the SE(3) geodesic loss, or the PoseNet, Anchor
Points and 6D baselines, for comparisons). --init-from starts a new run from trained weights
(fine-tuning with a new schedule, e.g. a lower --learning-rate); the network's settings are then
the checkpoint's.

examples:
  svr train-stack-pose --atlas-dir atlas/ --hold-out 24 28 32 \\
      --motion-path svort_fetal_motion_trajectories.npz --output-dir runs/stack-pose
  svr train-stack-pose --atlas-dir atlas/ crl/ --hold-out 24 28 32 --synthesis labels \\
      --motion-path svort_fetal_motion_trajectories.npz --output-dir runs/stack-pose-synth
  svr train-stack-pose --atlas-dir atlas/ --hold-out 24 28 32 \\
      --motion-path svort_fetal_motion_trajectories.npz --output-dir runs/stack-pose-ft \\
      --init-from runs/stack-pose --steps 10000 --fine-tune-steps 0 --learning-rate 3e-4 \\
      --seed 1
"""

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr train-stack-pose``."""
    p = subparsers.add_parser(
        "train-stack-pose",
        help="train the stack-pose CNN (canonical pose of a whole stack)",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument("--output-dir", required=True, help="folder for the run's checkpoints")
    _add_brain_options(p)
    _add_network_options(p)
    _add_schedule_options(p)
    _add_run_options(p)
    add_common_options(p)


def _add_brain_options(p: argparse.ArgumentParser) -> None:
    """The training brains: atlas ages, phantoms, anatomy variants, motion."""
    p.add_argument(
        "--atlas-dir",
        required=True,
        nargs="+",
        metavar="DIR",
        help="folder(s) of GA*/srr.nii.gz + GA*/mask.nii.gz volumes (several: atlas families "
        "aligned in one canonical frame)",
    )
    p.add_argument(
        "--hold-out",
        type=float,
        nargs="*",
        default=[],
        help="gestational ages (weeks) to leave out (of every --atlas-dir)",
    )
    p.add_argument(
        "--motion-path",
        help="fetal motion trajectories (.npz); without it, random walks of a few degrees",
    )
    p.add_argument(
        "--phantoms",
        type=non_negative_int,
        default=4,
        help="also train on N procedural phantom brains (svr.sampling.phantom; seeds 1..N, ages "
        "spread over 22-36 weeks): anatomy unlike the atlas's, from the second phase on (from "
        "the first step with --fine-tune-steps 0). Seed 0, the benchmarks' phantom, is never used",
    )
    p.add_argument(
        "--anatomy-variants",
        type=non_negative_int,
        default=0,
        help="also train on N variants of each training atlas brain with shrunk ventricles, a "
        "grown cerebellum and re-drawn contrast per tissue label (svr.sampling.anatomy; needs "
        "each GA folder's parcellation.nii.gz): anatomy and contrast unlike the spina bifida "
        "atlas's, from the phase that --variants-phase names",
    )
    p.add_argument(
        "--variants-phase",
        choices=("all", "second"),
        default="all",
        help="when the anatomy variants join: all (from the first step) or second (with the "
        "phantoms, for the last --fine-tune-steps steps; from the first step with "
        "--fine-tune-steps 0)",
    )
    p.add_argument(
        "--variants-weight",
        type=positive_float,
        default=1.0,
        help="how often each anatomy variant is drawn for a training stack, relative to an atlas "
        "brain (default: %(default)s, every brain alike; 0.25 with 4 variants: the variants of a "
        "brain together as often as the brain)",
    )
    p.add_argument(
        "--phantoms-weight",
        type=positive_float,
        default=1.0,
        help="how often each phantom is drawn for a training stack, relative to an atlas brain "
        "(default: %(default)s, every brain alike)",
    )
    p.add_argument(
        "--synthesis",
        choices=("none", *SYNTHESIS_MODES),
        default="none",
        help="synthetic copies of the atlas brains (svr.sampling.synthesis; needs each GA "
        "folder's parcellation.nii.gz): labels (the tissue labels painted with a random "
        "contrast, texture, bias, blur and noise) or mixed (the brain's own image remapped by a "
        "random curve per label); none for the atlas images only",
    )
    p.add_argument(
        "--synthesis-fraction",
        type=float,
        default=STACK_POSE_TRAINING["synthesis_fraction"],
        help="with --synthesis, the chance that a training stack's atlas brain is a synthetic "
        "copy (the phantoms never are)",
    )
    p.add_argument(
        "--loose-masks",
        type=float,
        default=0.0,
        metavar="MM",
        help="also move each training stack's mask edge in and out by a smooth random field up "
        "to MM and fill the tissue it takes in, as automatic masks of whole-uterus scans do "
        "(svr.sampling.artefacts.loose_mask; 0: off)",
    )
    p.add_argument(
        "--volume-downsample",
        type=positive_int,
        default=2,
        help="average the training volumes over blocks of this many voxels per side (faster "
        "simulation; the blocks are 4 mm)",
    )


def _add_network_options(p: argparse.ArgumentParser) -> None:
    """The network and its loss, or the weights to start from."""
    p.add_argument(
        "--head",
        choices=("regress", "coords"),
        help=f"pose head (default: {STACK_POSE_MODEL['head']})",
    )
    p.add_argument(
        "--width",
        type=positive_int,
        help=f"first-stage channels (default: {STACK_POSE_MODEL['width']})",
    )
    p.add_argument(
        "--hidden-norm",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="batch normalisation in the hidden layer (default: on; --no-hidden-norm is the "
        "network of the models trained before it, the shipped one included)",
    )
    p.add_argument(
        "--loss",
        type=registered_loss,
        metavar="NAME",
        help=f"{LOSS_HELP} (the baselines: regress head only)",
    )
    p.add_argument(
        "--init-from",
        metavar="MODEL",
        help="start from these weights: 'stack-pose' (the shipped model), a checkpoint or a run "
        "folder (used when --output-dir holds no checkpoint yet)",
    )


def _add_schedule_options(p: argparse.ArgumentParser) -> None:
    """Steps, learning rates and the second phase."""
    p.add_argument(
        "--steps", type=positive_int, default=STACK_POSE_TRAINING["steps"], help="optimiser steps"
    )
    p.add_argument(
        "--learning-rate",
        type=positive_float,
        default=STACK_POSE_TRAINING["learning_rate"],
        help="Adam's initial rate (cosine decay to 5 %% of it)",
    )
    p.add_argument(
        "--fine-tune-steps",
        type=non_negative_int,
        default=STACK_POSE_TRAINING["fine_tune_steps"],
        help="the last steps of --steps, a second phase: the learning rate restarts at "
        "--fine-tune-learning-rate and the phantoms join the atlas brains (0: one phase)",
    )
    p.add_argument(
        "--fine-tune-learning-rate",
        type=positive_float,
        default=STACK_POSE_TRAINING["fine_tune_learning_rate"],
        help="Adam's rate at the start of the second phase (cosine decay to 5 %% of it)",
    )
    p.add_argument(
        "--fine-tune-seed",
        type=int,
        default=STACK_POSE_TRAINING["fine_tune_seed"],
        help="run the second phase as the separate fine-tuning run of the first phase's weights "
        "with this --seed would be (a fresh Adam at --fine-tune-learning-rate, the random stream "
        "reseeded): the shipped model's recipe (default: %(default)s; --no-fine-tune-seed: the "
        "second phase continues the first's stream and Adam's moments)",
    )
    p.add_argument(
        "--no-fine-tune-seed",
        dest="fine_tune_seed",
        action="store_const",
        const=None,
        help="continue the first phase's random stream and Adam's moments in the second",
    )


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """Checkpoints, simulation processes and the time limit."""
    p.add_argument(
        "--checkpoint-every",
        type=positive_int,
        default=STACK_POSE_TRAINING["checkpoint_every"],
        help="steps",
    )
    p.add_argument(
        "--workers",
        type=non_negative_int,
        default=0,
        help="processes that simulate the training stacks: 0 simulates them in the training "
        "process (the shipped recipe); N >= 1 seeds each step's simulation by the step, so a run "
        "is the same for any N (worth it on a GPU or with spare cores)",
    )
    p.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="stop after a checkpoint once this much time passed",
    )


_OPTIONS = {
    "head": "--head",
    "width": "--width",
    "hidden_norm": "--hidden-norm",
    "representation": "--loss",
    "steps": "--steps",
    "learning_rate": "--learning-rate",
    "fine_tune_steps": "--fine-tune-steps",
    "fine_tune_learning_rate": "--fine-tune-learning-rate",
    "fine_tune_seed": "--fine-tune-seed",
    "checkpoint_every": "--checkpoint-every",
    "seed": "--seed",
    "synthesis_fraction": "--synthesis-fraction",
    "loose_mask_mm": "--loose-masks",
}
"""The option behind each StackPoseConfig and StackPoseTrainingConfig field it sets
(:func:`~svr.cli.common.option_errors`)."""


def _network(args: argparse.Namespace) -> tuple[StackPoseConfig, dict[str, Tensor] | None]:
    """The network asked for, or --init-from's with its weights.

    Raises:
        CliError: If --init-from cannot be loaded, or a network option contradicts its network.
    """
    from svr.models.checkpoint import CheckpointError
    from svr.models.stack_pose import StackPoseConfig, load_stack_pose_model
    from svr.representation_registry import representations_by_cli_name

    asked = {
        "head": args.head,
        "width": args.width,
        "hidden_norm": args.hidden_norm,
        "representation": None
        if args.loss is None
        else representations_by_cli_name()[args.loss].name,
    }
    asked = {key: value for key, value in asked.items() if value is not None}
    if args.init_from is None:
        with option_errors(_OPTIONS):
            return StackPoseConfig(**asked), None
    try:
        start = load_stack_pose_model(args.init_from)
    except (CheckpointError, OSError) as err:
        raise CliError(f"--init-from {args.init_from}: {err}") from err
    model = start.config
    for key, value in asked.items():
        if getattr(model, key) == value:
            continue
        if isinstance(value, bool):  # --hidden-norm / --no-hidden-norm
            flag = _OPTIONS[key].replace("--", "--" if value else "--no-", 1)
            raise CliError(f"{flag} differs from the --init-from model's network; leave it out")
        raise CliError(
            f"{_OPTIONS[key]} {value} differs from the --init-from model's "
            f"{getattr(model, key)}; leave it out"
        )
    return model, start.state_dict()


def _run_config(args: argparse.Namespace, brains: TrainingBrains) -> dict[str, Any]:
    """What the checkpoints record about the run beyond the network and the training."""
    return {
        "data": {
            "atlas_dirs": list(args.atlas_dir),
            "volumes": [str(v) for v, _ in brains.pairs],
            "hold_out_weeks": list(args.hold_out),
            "synthesis": args.synthesis,
            "phantoms": [{"weeks": age, "seed": seed} for age, seed in brains.phantoms],
            "anatomy_variants": args.anatomy_variants,
            "variants_phase": args.variants_phase,
            "variants_weight": args.variants_weight,
            "phantoms_weight": args.phantoms_weight,
            "motion": args.motion_path,
            "volume_downsample": args.volume_downsample,
        },
        "command": shlex.join(["svr", *sys.argv[1:]]),
        "init_from": args.init_from,
        "workers": args.workers,
    }


def run(args: argparse.Namespace) -> int:
    """Run ``svr train-stack-pose``."""
    import torch

    from svr.cli.stack_pose_brains import training_brains
    from svr.models.stack_pose_train import StackPoseTrainingConfig, train_stack_pose
    from svr.sampling.blocks import TrainingStackConfig
    from svr.sampling.motion import load_trajectories
    from svr.sampling.synthesis import SynthesisConfig

    if args.minutes is not None and not args.minutes > 0:
        raise CliError(f"--minutes must be > 0, got {args.minutes:g}")
    check_run_folder(args.output_dir)
    with option_errors(_OPTIONS):
        training = StackPoseTrainingConfig(
            steps=args.steps,
            learning_rate=args.learning_rate,
            fine_tune_steps=args.fine_tune_steps,
            fine_tune_learning_rate=args.fine_tune_learning_rate,
            fine_tune_seed=args.fine_tune_seed,
            checkpoint_every=args.checkpoint_every,
            seed=args.seed,
            synthesis=None if args.synthesis == "none" else SynthesisConfig(mode=args.synthesis),
            synthesis_fraction=args.synthesis_fraction,
            stacks=TrainingStackConfig(loose_mask_mm=args.loose_masks),
        )
    device = resolve_device(args.device)
    brains = training_brains(args)
    trajectories = load_trajectories(args.motion_path) if args.motion_path else None
    model, init = _network(args)
    threads = torch.get_num_threads()  # restored after, for a caller in this process
    if torch.device(device).type == "cpu":
        torch.set_num_threads(1)  # one process per core trains fastest (measured)
    began = time.time()
    try:
        train_stack_pose(
            brains.first,
            trajectories,
            model,
            training,
            folder=args.output_dir,
            progress=not args.quiet,
            time_limit_s=None if args.minutes is None else args.minutes * 60,
            extra_config=_run_config(args, brains),
            device=device,
            init=init,
            workers=args.workers,
            fine_tune_volumes=brains.second,
            # Alike (None) unless asked: the same draws as before these options existed.
            volume_weights=None if brains.alike else brains.first_weights,
            fine_tune_weights=None if brains.alike else brains.second_weights,
        )
    finally:
        torch.set_num_threads(threads)
    print(f"trained in {time.time() - began:.0f} s; checkpoints in {args.output_dir}")
    return 0
