"""``svr train-stack-pose``: train the stack-pose network on stacks simulated from atlas volumes."""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
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
from svr.cli.defaults import STACK_POSE_MODEL, STACK_POSE_TRAINING

if TYPE_CHECKING:
    from torch import Tensor

    from svr.models.stack_pose import StackPoseConfig
    from svr.sampling.volume import CanonicalVolume

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
cerebellum, re-drawn contrast) for scans of fetuses unlike the spina bifida atlas's. Use the
result with `svr reconstruct --registration cnn --model OUTPUT_DIR`, and check its output frame
on a real scan before trusting it.

Atlases: the Fidon 2021 spina bifida atlas (zenodo.org/record/5524312: GA21..GA34 folders with
srr.nii.gz and mask.nii.gz) or any folder laid out alike. Motion: the fetal head-motion
trajectories that SVoRT published (svort_fetal_motion_trajectories.npz).

--loss picks the pose output and its loss (the SE(3) geodesic loss, or the PoseNet, Anchor
Points and 6D baselines, for comparisons). --init-from starts a new run from trained weights
(fine-tuning with a new schedule, e.g. a lower --learning-rate); the network's settings are then
the checkpoint's.

examples:
  svr train-stack-pose --atlas-dir atlas/ --hold-out 24 28 32 \\
      --motion-path svort_fetal_motion_trajectories.npz --output-dir runs/stack-pose
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
        "--atlas-dir", required=True, help="folder of GA*/srr.nii.gz + GA*/mask.nii.gz volumes"
    )
    p.add_argument(
        "--hold-out",
        type=float,
        nargs="*",
        default=[],
        help="gestational ages (weeks) to leave out",
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
}
"""The option behind each StackPoseConfig and StackPoseTrainingConfig field it sets
(:func:`~svr.cli.common.option_errors`)."""


def phantom_sources(count: int) -> list[tuple[float, int]]:
    """The (gestational age in weeks, seed) of ``--phantoms``' training phantoms.

    Seeds 1..count (seed 0 is the benchmarks' test phantom); ages spread evenly over 22-36 weeks.

    Args:
        count: How many, >= 0.

    Returns:
        ``count`` pairs.
    """
    if count == 1:
        return [(29.0, 1)]
    return [(22.0 + 14.0 * i / (count - 1), i + 1) for i in range(count)]


def _anatomy_variants(
    pairs: list[tuple[Path, Path]], count: int, downsample: int
) -> list[CanonicalVolume]:
    """``count`` label-edited variants of each (volume, mask) atlas pair, canonical and coarsened.

    Variant ``n`` of the ``i``-th pair has seed ``1000 i + n``. Raises :class:`CliError` naming
    a missing or unusable ``parcellation.nii.gz``.
    """
    from svr.image import Image, load_nifti
    from svr.sampling.anatomy import anatomy_variant
    from svr.sampling.volume import canonicalize, downsample_volume

    variants = []
    for index, (volume_path, mask_path) in enumerate(pairs):
        labels_path = volume_path.parent / "parcellation.nii.gz"
        if not labels_path.exists():
            raise CliError(f"--anatomy-variants: {labels_path} is missing (the tissue labels)")
        source, labels = load_nifti(volume_path), load_nifti(labels_path).data.round()
        brain = load_nifti(mask_path).data > 0.5
        for number in range(count):
            try:
                image = anatomy_variant(source, brain, labels, seed=index * 1000 + number)
            except ValueError as err:
                raise CliError(f"--anatomy-variants: {labels_path}: {err}") from err
            mask = Image(brain.float(), source.affine)
            variants.append(
                downsample_volume(canonicalize(image, mask, name=str(volume_path)), downsample)
            )
    return variants


@dataclass
class _TrainingBrains:
    """The brains the command trains on, as :func:`train_stack_pose` takes them.

    Attributes:
        pairs: The training atlas ages' (volume, mask) files.
        first: The brains of every step (atlas ages, and variants with --variants-phase all).
        second: The brains that join for the second phase (variants with --variants-phase
            second, then the phantoms).
        first_weights: A draw weight per brain of ``first``.
        second_weights: A draw weight per brain of ``second``.
        phantoms: The phantoms' (weeks, seed).
        alike: Whether every brain is drawn alike (no weights given).
    """

    pairs: list[tuple[Path, Path]]
    first: list[CanonicalVolume]
    second: list[CanonicalVolume]
    first_weights: list[float]
    second_weights: list[float]
    phantoms: list[tuple[float, int]]
    alike: bool


def _training_brains(args: argparse.Namespace) -> _TrainingBrains:
    """Load the atlas ages, make the anatomy variants and phantoms, and weigh them."""
    from svr.sampling.phantom import gestational_age_config, make_phantom
    from svr.sampling.volume import (
        VolumeSourceError,
        atlas_volume_paths,
        canonicalize,
        downsample_volume,
        load_canonical_volume,
    )

    try:
        pairs = atlas_volume_paths(args.atlas_dir, hold_out=args.hold_out)
    except VolumeSourceError as err:
        raise CliError(f"--atlas-dir: {err}") from err
    volumes = [
        downsample_volume(load_canonical_volume(v, m), args.volume_downsample) for v, m in pairs
    ]
    variants = (
        _anatomy_variants(pairs, args.anatomy_variants, args.volume_downsample)
        if args.anatomy_variants
        else []
    )
    if args.variants_phase == "all":
        volumes += variants
    phantoms = phantom_sources(args.phantoms)
    # The second phase's brains (every step's with --fine-tune-steps 0): the phantoms, and the
    # variants where --variants-phase second.
    second_phase = list(variants) if args.variants_phase == "second" else []
    volume_weights = [1.0] * len(volumes)
    if args.variants_phase == "all":
        volume_weights[len(volumes) - len(variants) :] = [args.variants_weight] * len(variants)
    second_weights = [args.variants_weight] * len(second_phase) + [args.phantoms_weight] * len(
        phantoms
    )
    for age, seed in phantoms:
        image, mask = make_phantom(gestational_age_config(age, seed=seed))
        second_phase.append(downsample_volume(canonicalize(image, mask), args.volume_downsample))
    alike = args.variants_weight == 1.0 and args.phantoms_weight == 1.0
    return _TrainingBrains(
        pairs, volumes, second_phase, volume_weights, second_weights, phantoms, alike
    )


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


def _run_config(args: argparse.Namespace, brains: _TrainingBrains) -> dict[str, Any]:
    """What the checkpoints record about the run beyond the network and the training."""
    return {
        "data": {
            "volumes": [str(v) for v, _ in brains.pairs],
            "hold_out_weeks": list(args.hold_out),
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

    from svr.models.stack_pose_train import StackPoseTrainingConfig, train_stack_pose
    from svr.sampling.motion import load_trajectories

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
        )
    device = resolve_device(args.device)
    brains = _training_brains(args)
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
