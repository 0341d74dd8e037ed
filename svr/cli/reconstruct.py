"""``svr reconstruct``: a volume from motion-corrupted thick-slice stacks (SVR + super-resolution).

The options, their checks and the run are shared with ``svr register`` (:mod:`svr.cli.register`),
which is the same pipeline with fewer rounds and the volume optional.
"""

from __future__ import annotations

import argparse
import io
import logging
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict
from typing import TYPE_CHECKING, NamedTuple

from svr.cli.common import (
    MASK_MODEL_HELP,
    CliError,
    HelpFormatter,
    add_common_options,
    check_fusion_count,
    check_outputs,
    check_thickness_count,
    non_negative_float,
    option_errors,
    positive_float,
    positive_int,
    resolve_device,
)
from svr.files import atomic_write_text

if TYPE_CHECKING:
    from svr.masking import MaskingConfig
    from svr.reconstruction.config import ReconstructionConfig, ReconstructionResult
    from svr.reconstruction.stacks import Stack, StackConfig

DESCRIPTION = """\
Reconstruct a 3D volume from thick-slice stacks acquired while the fetus moved. Every slice is
its own rigid body: its pose is initialised (--registration: `cnn` places every stack in
canonical atlas space from its own data with the stack-pose model (the brain mask's principal
axes give candidate frames, a 3D CNN refines and scores them; with --atlas-volume the finished
volume is brought into the atlas's frame) and each interleaved packet (--packets) on its own,
refines how the stacks sit together by stack registration, and keeps, per stack, whichever of
these starts and plain stack registration agrees best with the other stacks (a slice-pose model
given with --model predicts every slice instead); `stack` registers every
stack rigidly to the template stack; `none` keeps the scanner's poses), then outer rounds
alternate slice-to-volume registration (skipped in the first round), EM outlier weighting,
exclusion of slices whose NCC with their simulation is below --ncc-threshold, and
edge-preserving super-resolution.

Stacks are cropped to their brain masks and normalised; without --stack-masks each stack's brain
is found automatically (--auto-masks network, as `svr segment-stack` does; the log and the QA
figure say so; accurate on stacks cropped around the brain, looser than manual masks on
whole-uterus scans; a stack without a found brain stops the command with an error; with
--fuse-masks the masks of 3 or more stacks are made to agree in 3D, as `svr segment-stack
--fuse-masks` does). The output
volume is in canonical atlas space with --registration cnn and in the scanner's world frame
otherwise. --output-transforms writes one row per slice (stack file, k index, pose of the file's
k-plane as 6-vector and matrix, frame, NCC, EM weight, excluded); --output-slices a NeSVoR-style
folder (n.nii.gz, mask_n.nii.gz; n = row of the transforms table) of the slices kept, each posed
by its affine; --output-qa a one-page figure (orthogonal views, per-slice NCC, timings).
All output paths are checked before the computation starts.

examples:
  svr reconstruct --input-stacks ax.nii.gz cor.nii.gz sag.nii.gz \\
      --stack-masks ax_mask.nii.gz cor_mask.nii.gz sag_mask.nii.gz --thicknesses 3 \\
      --output-volume srr.nii.gz --output-qa srr_qa.png
  svr reconstruct --input-stacks case1/stacks/stack*.nii.gz --stack-masks case1/masks/*.nii.gz \\
      --registration cnn --atlas-volume atlas/GA28/srr.nii.gz --atlas-mask atlas/GA28/mask.nii.gz \\
      --output-volume srr_atlas.nii.gz \\
      --output-transforms slices.csv --output-slices slices/ --output-log srr.log --device cuda
  svr reconstruct --input-stacks ax.nii.gz cor.nii.gz sag.nii.gz --thicknesses 3 \\
      --registration cnn --atlas-dir atlas/ --gestational-age 27.5 --output-volume srr_atlas.nii.gz
"""

TABLE_SUFFIXES = (".csv", ".json")
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr reconstruct``."""
    p = subparsers.add_parser(
        "reconstruct",
        help="reconstruct a volume from motion-corrupted stacks (SVR + super-resolution)",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    add_options(p, volume_required=True, iterations=None)


def add_options(
    parser: argparse.ArgumentParser, volume_required: bool, iterations: int | None
) -> None:
    """Add the inputs, outputs and settings of ``svr reconstruct`` and ``svr register``.

    Args:
        parser: The subcommand's parser.
        volume_required: Whether ``--output-volume`` is required.
        iterations: Default of ``--iterations``; ``None`` for the library's default.
    """
    inputs = parser.add_argument_group("inputs")
    inputs.add_argument(
        "--input-stacks", nargs="+", required=True, metavar="STACK", help="stacks (NIfTI)"
    )
    inputs.add_argument(
        "--stack-masks",
        nargs="+",
        metavar="MASK",
        help="brain masks (NIfTI, any grid that overlaps the stack), one per stack in order "
        "(default: automatic masks, see --auto-masks)",
    )
    add_mask_options(inputs)
    inputs.add_argument(
        "--thicknesses",
        nargs="+",
        type=positive_float,
        metavar="MM",
        help="slice thickness in mm: one for all stacks or one per stack (default: each stack's "
        "slice spacing, with a warning)",
    )
    inputs.add_argument(
        "--bias-correction",
        action="store_true",
        help="correct each stack's bias field with N4 before reconstruction",
    )
    outputs = parser.add_argument_group("outputs")
    outputs.add_argument(
        "--output-volume",
        required=volume_required,
        metavar="FILE",
        help="reconstructed volume (.nii or .nii.gz, float32)",
    )
    outputs.add_argument(
        "--output-slices", metavar="FOLDER", help="folder of posed slices (NeSVoR format)"
    )
    outputs.add_argument(
        "--output-transforms", metavar="FILE", help="slice poses and quality (.csv or .json)"
    )
    outputs.add_argument("--output-qa", metavar="FILE", help="quality figure (.png or .pdf)")
    outputs.add_argument(
        "--output-log", metavar="FILE", help="text log: messages, settings, timings per phase"
    )
    outputs.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_settings_options(parser, iterations)
    add_common_options(parser)


def add_mask_options(group: argparse._ArgumentGroup) -> None:
    """Add the automatic brain-mask options (``svr reconstruct``, ``svr register``, ``svr bids``).

    Args:
        group: The argument group to add them to.
    """
    group.add_argument(
        "--auto-masks",
        choices=["network", "otsu"],
        default="network",
        help="masks of stacks given without --stack-masks: network (the shipped brain-mask "
        "networks of svr segment-stack; reliable on cropped stacks, looser than manual masks on "
        "whole-uterus ones) or otsu (the largest bright region all stacks see; stacks cropped "
        "around the brain only)",
    )
    group.add_argument(
        "--mask-model",
        default="default",
        metavar="CHECKPOINT_DIR",
        help=f"{MASK_MODEL_HELP} (for --auto-masks network)",
    )
    group.add_argument(
        "--fuse-masks",
        action="store_true",
        help="make the automatic masks (--auto-masks network, 3 or more stacks) agree in 3D: "
        "the stacks are registered rigidly on their own masks and each stack's mask becomes the "
        "vote of all of them, as `svr segment-stack --fuse-masks` does (with large motion between "
        "the stacks the rigid registration misaligns the vote: measured up to 3.2 dB worse on "
        "simulated cases, benchmarks/results/reconstruction-masks.md)",
    )


def add_settings_options(parser: argparse.ArgumentParser, iterations: int | None) -> None:
    """Add the reconstruction settings (``svr reconstruct``, ``svr register``, ``svr bids``).

    Args:
        parser: The subcommand's parser.
        iterations: Default of ``--iterations``; ``None`` for the library's default.
    """
    from svr.reconstruction.config import (
        ADAPTIVE_MAX_ROUNDS,
        CONVERGED_DEFAULTS,
        FIXED_ROUNDS,
        REGISTRATIONS,
        SCHEDULES,
        ReconstructionConfig,
    )

    d = ReconstructionConfig()
    settings = parser.add_argument_group("reconstruction")
    settings.add_argument(
        "--output-resolution",
        type=positive_float,
        default=d.output_resolution_mm,
        metavar="MM",
        help="isotropic voxel size of the volume",
    )
    settings.add_argument(
        "--registration",
        choices=REGISTRATIONS,
        default=d.registration,
        help="pose initialisation: cnn places every stack (and, with a stack-pose model, every "
        "interleaved packet: --packets) in the atlas's canonical space with --model and keeps, "
        "per stack, whichever start agrees best with the other stacks, stack registration "
        "included; stack registers every stack rigidly to a template stack; none keeps the "
        "scanner's poses",
    )
    settings.add_argument(
        "--model",
        default="stack-pose",
        metavar="CHECKPOINT_DIR",
        help="pose model for --registration cnn: 'stack-pose' (the shipped stack-pose model: "
        "every stack placed in atlas space from its own data), 'default' (the shipped "
        "slice-pose model: every slice predicted, made rigid per stack), 'none' (no model: the "
        "classical chain, needs --atlas-volume), or a checkpoint or training-run folder of either "
        "kind (svr train-stack-pose, svr train)",
    )
    settings.add_argument(
        "--atlas-volume",
        metavar="NIFTI",
        nargs="+",
        help="--registration cnn: a brain atlas volume of about the fetus's gestational age (for "
        "example GA28/srr.nii.gz of the Fidon 2021 spina bifida atlas, zenodo.org/record/5524312, "
        "or the CRL fetal atlas), with --atlas-mask. The output is brought into its frame: rigid "
        "registration from 12 starts (the volume's frame, its 180-degree flips and its brain "
        "mask's principal axes); another frame replaces the one the stacks' learned poses give "
        "only if it fits the atlas clearly better (NCC higher by 0.05). Several volumes (for "
        "example the ages either side of an uncertain or missing one, the preferred first): the "
        "first's frame, unless another fits the output better by the same margin. Without a "
        "model (--model none) each stack's pose is also chosen by agreement with the atlas and "
        "fitted to it",
    )
    settings.add_argument(
        "--atlas-mask",
        metavar="NIFTI",
        nargs="+",
        help="the brain mask of each --atlas-volume, in the same order",
    )
    settings.add_argument(
        "--atlas-dir",
        metavar="DIR",
        help="instead of --atlas-volume: an atlas folder of GA<weeks>*/srr.nii.gz and mask.nii.gz "
        "(the Fidon 2021 layout); with --gestational-age, every age within --atlas-age-window "
        "weeks of it is used (the nearest where none is), nearest first, as several "
        "--atlas-volume",
    )
    settings.add_argument(
        "--gestational-age",
        type=positive_float,
        metavar="WEEKS",
        help="the fetus's gestational age, for --atlas-dir",
    )
    settings.add_argument(
        "--atlas-age-window",
        type=non_negative_float,
        default=1.0,
        metavar="WEEKS",
        help="with --atlas-dir: how far (weeks) an atlas's age may be from the fetus's",
    )
    settings.add_argument(
        "--template",
        type=int,
        metavar="INDEX",
        help="template stack (0-based index) of the stack registration (default: the stack with "
        "the most brain voxels)",
    )
    settings.add_argument(
        "--schedule",
        choices=SCHEDULES,
        default=d.schedule,
        help="adaptive: slice-to-volume registration rounds continue while the slices still move "
        "(--converged-deg, --converged-mm) up to --iterations, then the volume is reconstructed "
        "anew at the final poses; fixed: exactly --iterations rounds, as fetal-svr 0.1.0 ran them "
        "(reproduces its outputs)",
    )
    settings.add_argument(
        "--iterations",
        type=positive_int,
        default=iterations,
        metavar="N",
        help="rounds of (slice-to-volume registration, super-resolution), no slice-to-volume "
        f"registration in the first: the most rounds of the adaptive schedule (default "
        f"{ADAPTIVE_MAX_ROUNDS['stack']}; {ADAPTIVE_MAX_ROUNDS['cnn']} with --registration cnn), "
        f"the number of rounds of the fixed one (default {FIXED_ROUNDS})",
    )
    settings.add_argument(
        "--converged-deg",
        type=non_negative_float,
        default=d.converged_deg,
        metavar="DEG",
        help="adaptive schedule: a slice whose rotation changes by more than this in a round is "
        "still moving; the rounds stop once at most 10%% of the slices are (default: "
        f"{CONVERGED_DEFAULTS['stack'][0]:g}; {CONVERGED_DEFAULTS['cnn'][0]:g} with --registration "
        "cnn, whose slices start near their place)",
    )
    settings.add_argument(
        "--converged-mm",
        type=non_negative_float,
        default=d.converged_mm,
        metavar="MM",
        help="adaptive schedule: likewise for the displacement of a slice's centre (default: "
        f"{CONVERGED_DEFAULTS['stack'][1]:g}; {CONVERGED_DEFAULTS['cnn'][1]:g} with --registration "
        "cnn)",
    )
    settings.add_argument(
        "--sr-iterations",
        nargs="+",
        type=positive_int,
        default=list(d.sr_iterations),
        metavar="N",
        help="super-resolution (conjugate-gradient) iterations per round; the last value repeats",
    )
    settings.add_argument(
        "--svr-iterations",
        type=positive_int,
        default=d.svr_iterations,
        metavar="N",
        help="optimiser steps per resolution level of slice-to-volume registration",
    )
    settings.add_argument(
        "--packets",
        type=positive_int,
        default=d.packets,
        metavar="N",
        help="interleaved packets per stack: slices k = 0, N, 2N, ... were acquired in one "
        "sweep, then k = 1, N + 1, ..., and so on (1 for sequential acquisition). Slices are "
        "registered in groups of neighbours within a packet, and --registration cnn also places "
        "each packet on its own",
    )
    settings.add_argument(
        "--no-robust", action="store_true", help="no EM outlier weights (voxel and slice level)"
    )
    settings.add_argument(
        "--ncc-threshold",
        type=float,
        default=d.ncc_threshold,
        metavar="NCC",
        help="slices whose NCC with their simulation is below this are excluded",
    )


def run(args: argparse.Namespace) -> int:
    """Run ``svr reconstruct`` (and ``svr register``): check, reconstruct, write the outputs.

    Raises:
        CliError: For inconsistent options or output paths.
        ValueError, OSError: From the library (bad or missing files, checkpoints), naming the file.
    """
    count = len(args.input_stacks)
    if args.stack_masks is not None and len(args.stack_masks) != count:
        raise CliError(
            f"--stack-masks: got {len(args.stack_masks)} masks for {count} stacks; give none or "
            "one per stack"
        )
    check_thickness_count(args.thicknesses, count)
    settings = build_configs(args, count)
    _check_outputs(args)
    device = resolve_device(args.device)
    with _captured_log() as captured:
        stacks, result = load_and_reconstruct(
            args,
            args.input_stacks,
            args.stack_masks,
            args.thicknesses,
            settings,
            device,
        )
        _log_result(result)
        written = _write_outputs(args, result)
    if args.output_log is not None:
        text = captured.getvalue() + _summary(args, settings, result, device)
        atomic_write_text(args.output_log, text, args.overwrite)
        written.append(args.output_log)
    excluded = int(result.excluded.sum())
    print(
        f"wrote {', '.join(written)}: {len(result.slices)} slices from {len(stacks)} stacks, "
        f"{excluded} excluded, {result.slices.frame} frame"
    )
    return 0


def check_atlas_options(
    args: argparse.Namespace, registration: str, weeks: float | None = None
) -> list[tuple[str, str]]:
    """The ``(volume, mask)`` pairs of the atlas options, checked.

    Either ``--atlas-volume`` with ``--atlas-mask`` (one mask per volume), or ``--atlas-dir``
    with a gestational age (``--gestational-age``, or ``weeks`` from elsewhere, e.g. a BIDS
    dataset's participants table): the folder's atlases within ``--atlas-age-window`` weeks of it
    (:func:`svr.sampling.volume.atlas_paths_near`).

    Args:
        args: The parsed settings (``--atlas-volume``, ``--atlas-mask``, ``--atlas-dir``,
            ``--gestational-age``, ``--atlas-age-window`` (default 1 week where the command has
            none), ``--model``).
        registration: The ``--registration`` in use.
        weeks: The fetus's gestational age where it does not come from ``--gestational-age``.

    Returns:
        One pair per atlas; empty without an atlas option.

    Raises:
        CliError: If only one of ``--atlas-volume`` and ``--atlas-mask`` is given, their counts
            differ, ``--atlas-dir`` comes with ``--atlas-volume`` or without an age,
            ``--gestational-age`` without ``--atlas-dir``, the folder holds no atlas, or
            ``--registration cnn --model none`` comes without an atlas.
    """
    from svr.sampling.volume import VolumeSourceError, atlas_paths_near

    volumes, masks = args.atlas_volume, args.atlas_mask
    # One path where the command takes one atlas (svr predict), a list where it takes several.
    volumes = [volumes] if isinstance(volumes, str) else volumes
    masks = [masks] if isinstance(masks, str) else masks
    folder = getattr(args, "atlas_dir", None)
    if (volumes is None) != (masks is None):
        raise CliError("--atlas-volume and --atlas-mask go together")
    if volumes is not None and len(volumes) != len(masks):
        raise CliError(
            f"--atlas-mask needs one mask per --atlas-volume: got {len(volumes)} volumes and "
            f"{len(masks)} masks"
        )
    if volumes is not None and folder is not None:
        raise CliError("give --atlas-volume or --atlas-dir, not both")
    if getattr(args, "gestational_age", None) is not None and folder is None:
        raise CliError("--gestational-age chooses atlases from --atlas-dir; give --atlas-dir too")
    if registration == "cnn" and args.model == "none" and volumes is None and folder is None:
        raise CliError(
            "--registration cnn --model none needs --atlas-volume and --atlas-mask (or --atlas-dir)"
        )
    if volumes is not None:
        return list(zip(volumes, masks, strict=True))
    if folder is None:
        return []
    weeks = getattr(args, "gestational_age", None) if weeks is None else weeks
    if weeks is None:
        raise CliError("--atlas-dir needs the fetus's --gestational-age (weeks)")
    try:
        pairs = atlas_paths_near(folder, weeks, getattr(args, "atlas_age_window", 1.0))
    except VolumeSourceError as error:
        raise CliError(f"--atlas-dir {error}") from None
    return [(str(volume), str(mask)) for volume, mask in pairs]


def load_and_reconstruct(
    args: argparse.Namespace,
    stack_paths: Sequence[str],
    mask_paths: Sequence[str] | None,
    thicknesses: Sequence[float] | None,
    settings: Settings,
    device: str,
    weeks: float | None = None,
) -> tuple[list[Stack], ReconstructionResult]:
    """Load the model, atlas and stacks that the options name, and reconstruct.

    The one path from options to a result, shared by ``svr reconstruct``, ``svr register`` and
    each participant of ``svr bids``, so that they give identical volumes for the same stacks.

    Args:
        args: The parsed settings (``--model``, the atlas options, ``--mask-model``,
            ``--quiet``).
        stack_paths: The stacks (NIfTI).
        mask_paths: One brain mask per stack, or ``None`` for automatic masks.
        thicknesses: Slice thickness (mm): one for all stacks, one per stack, or ``None``.
        settings: The masking, stack preparation and reconstruction (:func:`build_configs`).
        device: Torch device.
        weeks: The fetus's gestational age for ``--atlas-dir`` where it does not come from
            ``--gestational-age`` (:func:`check_atlas_options`).

    Returns:
        The prepared stacks and the reconstruction.

    Raises:
        CliError: For inconsistent model and atlas options.
    """
    from svr.image import load_nifti
    from svr.masking import auto_masks
    from svr.models.predict import load_any_pose_model
    from svr.reconstruction.pipeline import reconstruct
    from svr.reconstruction.stacks import load_stacks, prepare_stacks, slice_thicknesses
    from svr.sampling.volume import load_canonical_volume

    config = settings.reconstruction

    if config.registration != "cnn" and args.model != "stack-pose":
        log.warning("--model is used only with --registration cnn; ignoring %s", args.model)
    atlas_paths = check_atlas_options(args, config.registration, weeks)
    model = None
    if config.registration == "cnn" and args.model != "none":
        model = load_any_pose_model(args.model, device)
    atlas = None
    if config.registration == "cnn" and atlas_paths:
        atlas = [load_canonical_volume(volume, mask) for volume, mask in atlas_paths]
    widths = None if thicknesses is None else list(thicknesses)
    if mask_paths is not None:
        stacks = load_stacks(list(stack_paths), list(mask_paths), widths, settings.stacks)
    else:
        # The masking stage, then preparation with its masks.
        names = [str(path) for path in stack_paths]
        images = [load_nifti(path) for path in stack_paths]
        masking = settings.masking
        if masking.fuse:
            widths = slice_thicknesses(widths, images, names)  # warned about once, here
        masks = auto_masks(images, masking, names, widths, args.mask_model, device)
        stacks = prepare_stacks(images, masks, widths, settings.stacks, names=names)
    result = reconstruct(
        stacks, config, model=model, device=device, progress=not args.quiet, atlas=atlas
    )
    return stacks, result


_OPTIONS = {
    "output_resolution_mm": "--output-resolution",
    "registration": "--registration",
    "template": "--template",
    "schedule": "--schedule",
    "outer_iterations": "--iterations",
    "converged_deg": "--converged-deg",
    "converged_mm": "--converged-mm",
    "sr_iterations": "--sr-iterations",
    "svr_iterations": "--svr-iterations",
    "packets": "--packets",
    "robust": "--no-robust",
    "ncc_threshold": "--ncc-threshold",
    "seed": "--seed",
    "bias_correction": "--bias-correction",
    "MaskingConfig.method": "--auto-masks",
    "MaskingConfig.fuse": "--fuse-masks",
}
"""The option behind each field of the StackConfig and ReconstructionConfig that the command sets
(:func:`~svr.cli.common.option_errors`)."""


class Settings(NamedTuple):
    """The dataclass configs that one run's options describe (:func:`build_configs`)."""

    masking: MaskingConfig
    """How stacks given without masks get them (used only then)."""
    stacks: StackConfig
    """How stacks are prepared."""
    reconstruction: ReconstructionConfig
    """The reconstruction."""


def build_configs(args: argparse.Namespace, count: int) -> Settings:
    """The dataclass configs the settings describe, after the checks argparse cannot do.

    Args:
        args: The parsed settings.
        count: The number of stacks they apply to (``--template`` and ``--fuse-masks`` checks).

    Returns:
        The masking, stack preparation and reconstruction configs.

    Raises:
        CliError: Naming the option, for a value out of range.
    """
    from svr.masking import MaskingConfig
    from svr.reconstruction.config import ReconstructionConfig
    from svr.reconstruction.stacks import StackConfig

    if args.template is not None and not 0 <= args.template < count:
        raise CliError(f"--template {args.template}: must be a stack index in [0, {count})")
    if args.fuse_masks and getattr(args, "stack_masks", None) is not None:
        raise CliError("--fuse-masks: only for automatic masks (give no --stack-masks)")
    if args.fuse_masks and args.auto_masks != "network":
        raise CliError("--fuse-masks: needs --auto-masks network")
    if args.fuse_masks:
        check_fusion_count(count)
    with option_errors(_OPTIONS):
        masking = MaskingConfig(method=args.auto_masks, fuse=args.fuse_masks)
        stack_config = StackConfig(bias_correction=args.bias_correction)
        config = ReconstructionConfig(
            output_resolution_mm=args.output_resolution,
            registration=args.registration,
            template=args.template,
            schedule=args.schedule,
            outer_iterations=args.iterations,
            converged_deg=args.converged_deg,
            converged_mm=args.converged_mm,
            sr_iterations=tuple(args.sr_iterations),
            svr_iterations=args.svr_iterations,
            packets=args.packets,
            robust=not args.no_robust,
            ncc_threshold=args.ncc_threshold,
            seed=args.seed,
        )
    return Settings(masking, stack_config, config)


def _check_outputs(args: argparse.Namespace) -> None:
    """Check every output path before the computation: suffix, existence, folder, no repeats."""
    from svr.image import NIFTI_SUFFIXES
    from svr.reconstruction.qa import FIGURE_SUFFIXES

    outputs = [
        ("--output-volume", args.output_volume, NIFTI_SUFFIXES),
        ("--output-slices", args.output_slices, None),
        ("--output-transforms", args.output_transforms, TABLE_SUFFIXES),
        ("--output-qa", args.output_qa, FIGURE_SUFFIXES),
        ("--output-log", args.output_log, None),
    ]
    check_outputs(outputs, args.overwrite)


@contextmanager
def _captured_log() -> Iterator[io.StringIO]:
    """Collect the log messages emitted meanwhile (at the chosen verbosity) for --output-log."""
    buffer = io.StringIO()
    handler = logging.StreamHandler(buffer)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield buffer
    finally:
        root.removeHandler(handler)


def excluded_by_stack(result: ReconstructionResult) -> dict[str, list[int]]:
    """Stack name -> k indices (in its file) of the excluded slices, for stacks that have some."""
    slices = result.slices
    out: dict[str, list[int]] = {}
    for row in result.excluded.nonzero().flatten().tolist():
        name = slices.stack_names[int(slices.stack_ids[row])]
        out.setdefault(name, []).append(int(slices.slice_indices[row]))
    return out


def _log_result(result: ReconstructionResult) -> None:
    frame = result.slices.frame
    where = (
        "the slice-pose model's atlas space"
        if frame == "canonical"
        else "the stacks' world coordinates"
    )
    log.info("the output volume and poses are in the %s frame (%s)", frame, where)
    for name, ks in excluded_by_stack(result).items():
        log.info("%s: excluded slices k = %s", name, ", ".join(map(str, ks)))


def _write_outputs(args: argparse.Namespace, result: ReconstructionResult) -> list[str]:
    """Write the requested outputs (the log aside); returns their paths."""
    from svr.reconstruction.outputs import write_slices_folder, write_transforms, write_volume
    from svr.reconstruction.qa import qa_figure

    written = []
    if args.output_volume is not None:
        written.append(str(write_volume(result.volume, args.output_volume, args.overwrite)))
    if args.output_transforms is not None:
        written.append(str(write_transforms(result, args.output_transforms, args.overwrite)))
    if args.output_slices is not None:
        keep = ~result.excluded
        written.append(
            str(write_slices_folder(result.slices, args.output_slices, args.overwrite, keep))
        )
    if args.output_qa is not None:
        notes = [f"masks: {_mask_source(args)}"]
        written.append(
            str(qa_figure(result, args.output_qa, overwrite=args.overwrite, notes=notes))
        )
    return written


def _mask_source(args: argparse.Namespace) -> str:
    """Where the brain masks came from, for the log and the QA figure."""
    if args.stack_masks is not None:
        return "given (--stack-masks)"
    if args.auto_masks == "network":
        fused = ", fused across stacks" if args.fuse_masks else ""
        return f"automatic (network, --mask-model {args.mask_model}{fused})"
    return "automatic (otsu)"


def _rounds_line(config: ReconstructionConfig, result: ReconstructionResult) -> str:
    """How many rounds ran and whether the slices converged, for the log summary."""
    from svr.reconstruction.convergence import verdict

    ending = verdict(result.converged)
    return f"{len(result.rounds)} ({config.schedule} schedule{', ' + ending if ending else ''})"


def _summary(
    args: argparse.Namespace, settings: Settings, result: ReconstructionResult, device: str
) -> str:
    """The settings, timings, initialisation and exclusions, as text for --output-log."""
    config = settings.reconstruction
    lines = [f"# svr {args.command} summary", "inputs:"]
    masks = args.stack_masks or [_mask_source(args)] * len(args.input_stacks)
    lines += [
        f"  {stack} (mask {mask})" for stack, mask in zip(args.input_stacks, masks, strict=True)
    ]
    if config.registration == "cnn":
        lines.append(f"model: {args.model}")
    if args.stack_masks is None:
        lines.append("masking:")
        lines += [f"  {key}: {value}" for key, value in asdict(settings.masking).items()]
    lines.append("stack preparation:")
    lines += [f"  {key}: {value}" for key, value in asdict(settings.stacks).items()]
    lines.append("reconstruction:")
    lines += [f"  {key}: {value}" for key, value in config.settings().items()]
    lines.append(f"  device: {device}")
    lines.append("time per phase (s):")
    lines += [f"  {name}: {seconds:.2f}" for name, seconds in result.timings_s.items()]
    lines.append(f"  total: {sum(result.timings_s.values()):.2f}")
    lines.append("initialisation per stack:")
    lines += [
        f"  {name}: {init}"
        for name, init in zip(result.slices.stack_names, result.initialisation, strict=True)
    ]
    lines.append(f"frame: {result.slices.frame}")
    if result.atlas_chosen is not None:
        volumes = [volume for volume, _ in check_atlas_options(args, config.registration)]
        lines.append(f"atlas frame: {volumes[result.atlas_chosen]}")
        lines += [
            f"  {path}: NCC {ncc:.3f}" for path, ncc in zip(volumes, result.atlas_ncc, strict=True)
        ]
    lines.append(f"rounds: {_rounds_line(config, result)}")
    lines += [f"  {record.line()}" for record in result.rounds]
    excluded = excluded_by_stack(result)
    lines.append(f"excluded slices: {int(result.excluded.sum())} of {len(result.slices)}")
    lines += [f"  {name}: k = {', '.join(map(str, ks))}" for name, ks in excluded.items()]
    return "\n".join(lines) + "\n"
