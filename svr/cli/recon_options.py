"""The options of the commands that reconstruct (``svr reconstruct``, ``register``, ``bids``).

``--registration`` (the NeSVoR-compatible values ``stack`` and ``none``, ``cnn`` for the learned
start and ``atlas`` for the classical one), ``--model``, the atlas options and the mask options
are written here; every other setting is an option declared on its configuration field
(:mod:`svr.cli.config_options`). They are resolved once, here, into a
:class:`~svr.apps.reconstruct.ReconstructionJob` (:func:`build_job`): below the command line only
the start's kind (:data:`svr.reconstruction.config.INITIALISATIONS`) decides which start runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING

from svr.cli.common import (
    MASK_MODEL_HELP,
    CliError,
    check_fusion_count,
    non_negative_float,
    option_errors,
    positive_float,
)
from svr.cli.config_options import add_config_options, config_from_options, option_names

if TYPE_CHECKING:
    from svr.apps.reconstruct import ReconstructionJob

__all__ = [
    "REGISTRATIONS",
    "add_mask_options",
    "add_pose_options",
    "add_reconstruction_options",
    "atlas_paths",
    "build_job",
    "initialisation_kind",
]

log = logging.getLogger(__name__)

REGISTRATIONS = ("stack", "cnn", "atlas", "none")
"""The values of ``--registration``."""

ATLAS_EXAMPLE = (
    "for example GA28_operated/srr.nii.gz of the Fidon 2021 atlas (zenodo.org/record/5524312), "
    "or a CRL or Wu 2021 atlas volume of that age"
)


def add_pose_options(group: argparse._ArgumentGroup) -> None:
    """Add ``--registration``, ``--model`` and the atlas options to a help section.

    Args:
        group: The section ("initialisation").
    """
    group.add_argument(
        "--registration",
        choices=REGISTRATIONS,
        default="stack",
        help="how slice poses start. stack: every stack registered rigidly to a template stack "
        "(scanner frame); cnn: every stack, and each interleaved packet (--packets), placed in "
        "the atlas's canonical space by --model, each placement kept per stack only where it "
        "agrees with the other stacks better than stack registration (canonical frame); atlas: "
        "the same with each stack placed by agreement with --atlas-volume, no network; none: "
        "the scanner's poses",
    )
    group.add_argument(
        "--model",
        default="stack-pose",
        metavar="NAME|CHECKPOINT_DIR",
        help="pose model of --registration cnn: 'stack-pose' (the shipped stack-pose model: each "
        "stack placed from its own data), 'slice-pose' (the shipped slice-pose model: every "
        "slice predicted, made rigid per stack), or a checkpoint or training-run folder of "
        "either kind (svr train-stack-pose, svr train)",
    )
    group.add_argument(
        "--atlas-volume",
        metavar="NIFTI",
        nargs="+",
        help="--registration cnn or atlas: a brain atlas volume of about the fetus's gestational "
        f"age ({ATLAS_EXAMPLE}), with --atlas-mask. The output is brought into its frame (rigid "
        "registration from 12 starts; another frame replaces the one the stacks' poses give only "
        "if it fits the atlas clearly better). Several volumes (the ages either side of an "
        "uncertain one, the preferred first): the first's frame unless another fits clearly "
        "better",
    )
    group.add_argument(
        "--atlas-mask",
        metavar="NIFTI",
        nargs="+",
        help="the brain mask of each --atlas-volume, in the same order",
    )
    group.add_argument(
        "--atlas-dir",
        metavar="DIR",
        help="instead of --atlas-volume: an atlas folder of GA<weeks>*/srr.nii.gz and mask.nii.gz "
        "(the Fidon 2021 layout); every age within --atlas-age-window weeks of --gestational-age "
        "is used (the nearest where none is), nearest first",
    )
    group.add_argument(
        "--gestational-age",
        type=positive_float,
        metavar="WEEKS",
        help="the fetus's gestational age, for --atlas-dir",
    )
    group.add_argument(
        "--atlas-age-window",
        type=non_negative_float,
        default=1.0,
        metavar="WEEKS",
        help="with --atlas-dir: how far (weeks) an atlas's age may be from the fetus's",
    )


def add_mask_options(group: argparse._ArgumentGroup) -> None:
    """Add the automatic brain-mask options (``svr reconstruct``, ``svr register``, ``svr bids``).

    Args:
        group: The section to add them to.
    """
    group.add_argument(
        "--auto-masks",
        choices=["network", "otsu"],
        default="network",
        help="masks of stacks given without masks: network (the shipped brain-mask networks of "
        "svr segment-stack; reliable on cropped stacks, looser than manual masks on whole-uterus "
        "ones) or otsu (the largest bright region all stacks see; stacks cropped around the brain "
        "only)",
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
        help="make the automatic masks (--auto-masks network, 3 or more stacks) agree in 3D: the "
        "stacks are registered rigidly on their own masks and each stack's mask becomes the vote "
        "of all of them, as svr segment-stack --fuse-masks does (with large motion between the "
        "stacks the rigid registration can misalign the vote)",
    )


def initialisation_kind(registration: str, model: str) -> str:
    """The start that ``--registration`` and ``--model`` name (the one place that decides it).

    ``cnn`` is the learned start of the model's kind (a stack-pose or a slice-pose network, read
    from the checkpoint's configuration, nothing executed). Old spellings still work, with a
    deprecation message: ``--registration cnn --model none`` is ``--registration atlas``, and
    ``--model default`` the shipped slice-pose model (``--model slice-pose``).

    Args:
        registration: The ``--registration`` value.
        model: The ``--model`` value.

    Returns:
        One of :data:`svr.reconstruction.config.INITIALISATIONS`.

    Raises:
        CliError: If ``--registration`` is unknown.
        CheckpointError: If the model cannot be read.
    """
    from svr.models.predict import pose_model_kind

    if registration == "none":
        return "scanner"
    if registration in ("stack", "atlas"):
        return registration
    if registration != "cnn":
        raise CliError(f"--registration {registration}: must be one of {', '.join(REGISTRATIONS)}")
    if model == "none":
        log.warning(
            "--registration cnn --model none is deprecated and will be removed: it runs no "
            "network; write --registration atlas"
        )
        return "atlas"
    if model == "default":
        log.warning(
            "--model default is deprecated in svr reconstruct (it is the shipped slice-pose "
            "model, not the default stack-pose one): write --model slice-pose"
        )
    kind = pose_model_kind(model)
    return "learned" if kind == "stack-pose" else "learned-slices"


def atlas_paths(
    args: argparse.Namespace, kind: str | None, weeks: float | None = None
) -> list[tuple[str, str]]:
    """The ``(volume, mask)`` pairs of the atlas options, checked.

    Either ``--atlas-volume`` with ``--atlas-mask`` (one mask per volume), or ``--atlas-dir``
    with a gestational age (``--gestational-age``, or ``weeks`` from elsewhere, e.g. a BIDS
    dataset's participants table): the folder's atlases within ``--atlas-age-window`` weeks of it
    (:func:`svr.sampling.volume.atlas_paths_near`).

    Args:
        args: The parsed options (``--atlas-volume``, ``--atlas-mask``, ``--atlas-dir``,
            ``--gestational-age``, ``--atlas-age-window`` where the command has them).
        kind: The start (:func:`initialisation_kind`): ``"atlas"`` needs an atlas; starts in
            the scanner frame use none (a warning says they are ignored); ``None`` checks only.
        weeks: The fetus's gestational age where it does not come from ``--gestational-age``.

    Returns:
        One pair per atlas; empty without an atlas option, or for a start that uses none.

    Raises:
        CliError: If only one of ``--atlas-volume`` and ``--atlas-mask`` is given, their counts
            differ, ``--atlas-dir`` comes with ``--atlas-volume`` or without an age,
            ``--gestational-age`` without ``--atlas-dir``, the folder holds no atlas, or the
            ``atlas`` start comes without an atlas.
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
    if kind == "atlas" and volumes is None and folder is None:
        raise CliError(
            "--registration atlas needs --atlas-volume with --atlas-mask, or --atlas-dir"
        )
    if kind in ("scanner", "stack") and (volumes is not None or folder is not None):
        log.warning("the atlas options are used only with --registration cnn or atlas; ignored")
        return []
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


SECTIONS = {
    "": "acquisition",
    "grid": "output grid",
    "initialisation": "initialisation",
    "schedule": "rounds",
    "superres": "super-resolution",
    "outliers": "outliers",
}
"""The help section of each group of :class:`~svr.reconstruction.config.ReconstructionConfig`."""


def add_reconstruction_options(
    parser: argparse.ArgumentParser, masks: argparse._ArgumentGroup | None = None
) -> None:
    """Add the initialisation options and every option of the reconstruction's configuration.

    Args:
        parser: The command's parser.
        masks: The section for the automatic-mask options (``None``: a section of their own).
    """
    from svr.reconstruction.config import ReconstructionConfig

    add_mask_options(masks or parser.add_argument_group("automatic brain masks"))
    initialisation = parser.add_argument_group(SECTIONS["initialisation"])
    add_pose_options(initialisation)
    add_config_options(
        parser, ReconstructionConfig, SECTIONS, {SECTIONS["initialisation"]: initialisation}
    )


def build_job(
    args: argparse.Namespace,
    stacks: Sequence[str],
    masks: Sequence[str] | None,
    thicknesses: Sequence[float] | None,
    device: str,
    weeks: float | None = None,
) -> ReconstructionJob:
    """The job that the options describe for these stacks, after the checks argparse cannot do.

    The start's kind comes from ``--registration`` and ``--model``
    (:func:`initialisation_kind`), its defaults from
    :meth:`~svr.reconstruction.config.ReconstructionConfig.preset`, and every option given on
    the command line is set over them.

    Args:
        args: The parsed options.
        stacks: The stacks (NIfTI paths).
        masks: One mask per stack, or ``None`` for automatic masks.
        thicknesses: Slice thickness (mm): one for all stacks, one per stack, or ``None``.
        device: Torch device.
        weeks: The fetus's gestational age for ``--atlas-dir`` where it does not come from
            ``--gestational-age``.

    Returns:
        The job.

    Raises:
        CliError: Naming the option, for a value out of range or inconsistent options.
    """
    from svr.apps.reconstruct import ReconstructionJob
    from svr.masking import MaskingConfig
    from svr.reconstruction.config import ReconstructionConfig
    from svr.reconstruction.stacks import StackConfig

    count = len(stacks)
    if args.fuse_masks and masks is not None:
        raise CliError("--fuse-masks: only for automatic masks, and these stacks have masks given")
    if args.fuse_masks and args.auto_masks != "network":
        raise CliError("--fuse-masks: needs --auto-masks network")
    if args.fuse_masks:
        check_fusion_count(count)
    kind = initialisation_kind(args.registration, args.model)
    base = ReconstructionConfig.preset(kind, args.schedule or "adaptive")
    names = {
        **option_names(ReconstructionConfig),
        "MaskingConfig.method": "--auto-masks",
        "MaskingConfig.fuse": "--fuse-masks",
        "bias_correction": "--bias-correction",
        "ReconstructionConfig.seed": "--seed",
    }
    with option_errors(names):
        config = dataclasses.replace(config_from_options(args, base), seed=args.seed)
        masking = MaskingConfig(method=args.auto_masks, fuse=args.fuse_masks)
        preparation = StackConfig(bias_correction=args.bias_correction)
    template = config.initialisation.template
    if template is not None and not 0 <= template < count:
        raise CliError(f"--template {template}: must be a stack index in [0, {count})")
    return ReconstructionJob(
        stacks=tuple(map(str, stacks)),
        masks=None if masks is None else tuple(map(str, masks)),
        thicknesses=None if thicknesses is None else tuple(thicknesses),
        config=config,
        model=args.model if kind in ("learned", "learned-slices") else None,
        atlases=tuple(atlas_paths(args, kind, weeks)),
        masking=masking,
        preparation=preparation,
        mask_model=args.mask_model,
        device=device,
        progress=not args.quiet,
    )
