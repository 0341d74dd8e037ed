"""``svr train-brain-mask``: train the brain-mask networks on simulated scenes, write the model."""

from __future__ import annotations

import argparse
import shlex
import sys
from typing import TYPE_CHECKING

from svr.cli.common import (
    CliError,
    HelpFormatter,
    add_common_options,
    check_outputs,
    check_run_folder,
    non_negative_int,
    option_errors,
    positive_int,
    resolve_device,
)
from svr.cli.defaults import BRAIN_MASK_TRAINING, MASKER_RECIPE

if TYPE_CHECKING:
    from svr.masking.recipe import MaskerRecipe

DESCRIPTION = """\
Train the two networks of a brain-mask model (svr segment-stack --mask-model): a localiser that
finds the brain on each slice and a segmenter that outlines it, small 2D U-Nets trained on
simulated stacks only. Each training case is an atlas brain at a random scale inside a random
whole-uterus scene (or alone), cut into motion-corrupted thick-slice stacks; no real scan is read.
--output-dir holds one folder per network with its settings, its simulated examples and its
checkpoints: running the same command again resumes, and a run folder started with other
settings is refused. --stage all (the default) trains the localiser, then the segmenter, then
writes --output-model; the two networks can also be trained side by side, one process each
(--stage localiser, --stage segmenter), then put together (--stage assemble). The model folder
holds float16 weights, a config with the provenance and a README.md model card.

Atlases: the Fidon 2021 spina bifida atlas (zenodo.org/record/5524312: GA21..GA34 folders with
srr.nii.gz, mask.nii.gz and, for --label-intensities, parcellation.nii.gz) or any folder laid out
alike.

examples:
  svr train-brain-mask --atlas-dir atlas/ --output-dir runs/mask --output-model my-mask
  OMP_NUM_THREADS=1 svr train-brain-mask --stage localiser --atlas-dir atlas/ \\
      --output-dir runs/mask --tiles --label-intensities --intensity-curves 0.5 \\
      --cases 80 --steps 3000 &
  OMP_NUM_THREADS=1 svr train-brain-mask --stage segmenter --atlas-dir atlas/ \\
      --output-dir runs/mask --tiles --label-intensities --intensity-curves 0.5 \\
      --cases 100 --steps 5000 --segmenter-width 12 &
  wait
  svr train-brain-mask --stage assemble --output-dir runs/mask --tiles --segmenter-width 12 \\
      --output-model my-mask
"""

STAGE_CHOICES = ("all", "localiser", "segmenter", "assemble")
"""``--stage``: both networks and the model, one network, or the model from trained networks."""

_VARIANTS = {
    "segment_all_slices": "segmenter: canvases from every slice, not only the brain's",
    "tight_heads": "scenes with narrower CSF and fainter, thinner skulls and scalps",
    "faces": "scenes whose heads have a face and eyes and whose bodies hang from a neck",
    "partial_volume_masks": "slice masks wherever a fifth of the slice's profile is brain",
    "grazing_only": "with --partial-volume-masks: only on the slices grazing the head's ends",
    "thick_skulls": "scenes with 2-5 mm grey skulls (inside the masks) and thin scalps",
    "spinal_cord": "heads end at the skull base; the brainstem below is the spinal cord",
}
"""The simulation variants (:class:`svr.masking.recipe.MaskerRecipe` switches) and their help."""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr train-brain-mask``."""
    p = subparsers.add_parser(
        "train-brain-mask",
        help="train the brain-mask networks on simulated scenes",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "--output-dir", required=True, help="run folder: one folder per network (resumed)"
    )
    p.add_argument(
        "--stage",
        choices=STAGE_CHOICES,
        default="all",
        help="all: both networks, then the model; localiser or segmenter: that network only; "
        "assemble: the model from the trained networks",
    )
    p.add_argument(
        "--atlas-dir", help="folder of GA*/srr.nii.gz + GA*/mask.nii.gz volumes (to train)"
    )
    p.add_argument(
        "--output-model",
        metavar="MODEL_DIR",
        help="the model folder to write (--stage all or assemble; required with assemble)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output-model")
    _add_training_options(p)
    _add_variant_options(p)
    add_common_options(p)


def _add_training_options(p: argparse.ArgumentParser) -> None:
    """The networks' shape and training."""
    group = p.add_argument_group("networks and training")
    group.add_argument(
        "--tiles",
        action="store_true",
        help="the shipped model's recipe: the localiser on 1.5 mm tiles over the field of view, "
        "every slice segmented, masks up to the skull's outer edge",
    )
    group.add_argument(
        "--segmenter-width",
        type=positive_int,
        default=MASKER_RECIPE["segmenter_width"],
        help="channels of the segmenter's first level",
    )
    group.add_argument(
        "--segmenter-context",
        type=non_negative_int,
        default=MASKER_RECIPE["segmenter_context"],
        help="neighbouring slices on either side the segmenter sees (0: 2D)",
    )
    group.add_argument(
        "--cases",
        type=positive_int,
        default=BRAIN_MASK_TRAINING["cases"],
        help="simulated cases per network (2 or 3 stacks each)",
    )
    group.add_argument(
        "--steps", type=positive_int, default=BRAIN_MASK_TRAINING["steps"], help="optimiser steps"
    )
    group.add_argument(
        "--intensity-curves",
        type=float,
        default=BRAIN_MASK_TRAINING["intensity_curves"],
        help="fraction of the training canvases given a random increasing intensity map",
    )
    group.add_argument(
        "--label-intensities",
        action="store_true",
        help="give half of the scenes' brains a random intensity per parcellation label",
    )


def _add_variant_options(p: argparse.ArgumentParser) -> None:
    """The simulation variants (none of them in the shipped model)."""
    group = p.add_argument_group("simulation variants")
    for name, text in _VARIANTS.items():
        group.add_argument(f"--{name.replace('_', '-')}", action="store_true", help=text)


_OPTIONS = {
    "cases": "--cases",
    "steps": "--steps",
    "seed": "--seed",
    "intensity_curves": "--intensity-curves",
    "segmenter_width": "--segmenter-width",
    "segmenter_context": "--segmenter-context",
    "grazing_only": "--grazing-only",
    "thick_skulls": "--thick-skulls",
}
"""The option behind each MaskerRecipe and BrainMaskTrainingConfig field it sets
(:func:`~svr.cli.common.option_errors`)."""


def _recipe_options(recipe: MaskerRecipe, stage: str) -> list[str]:
    """The options that give ``recipe`` for ``stage`` (those the stage depends on, if not default).

    ``"assemble"`` depends on the networks' shapes only.
    """
    from svr.masking.recipe import MaskerRecipe

    default = MaskerRecipe()
    options = ["--tiles"] if recipe.tiles else []
    if stage != "localiser":
        for name in ("segmenter_width", "segmenter_context"):
            if getattr(recipe, name) != getattr(default, name):
                options += [_OPTIONS[name], str(getattr(recipe, name))]
    if stage == "assemble":
        return options
    for name in ("cases", "steps", "seed", "intensity_curves"):
        value = getattr(recipe.training, name)
        if value != getattr(default.training, name):
            options += [_OPTIONS[name], f"{value:g}"]
    if recipe.label_intensities:
        options.append("--label-intensities")
    return options + [f"--{name.replace('_', '-')}" for name in _VARIANTS if getattr(recipe, name)]


def _commands(args: argparse.Namespace, recipe: MaskerRecipe) -> list[str]:
    """The commands that reproduce the model: each network as recorded, then the assembly."""
    from svr.masking.recipe import STAGES, recorded_recipe

    atlas = args.atlas_dir or "ATLAS"
    lines = []
    for stage in STAGES:
        trained = recorded_recipe(args.output_dir, stage) or recipe
        words = ["svr", "train-brain-mask", "--stage", stage, "--output-dir", args.output_dir]
        words += ["--atlas-dir", atlas, *_recipe_options(trained, stage)]
        lines.append(f"OMP_NUM_THREADS=1 {shlex.join(words)} &")
    words = ["svr", "train-brain-mask", "--stage", "assemble", "--output-dir", args.output_dir]
    words += [*_recipe_options(recipe, "assemble"), "--output-model", args.output_model]
    return [*lines, "wait", shlex.join(words)]


def _check_arguments(args: argparse.Namespace) -> None:
    """Refuse a combination of options the stage cannot use, and outputs in the way."""
    if args.stage == "assemble" and args.output_model is None:
        raise CliError("--output-model: required with --stage assemble")
    if args.stage in ("localiser", "segmenter") and args.output_model is not None:
        raise CliError(f"--output-model: written by --stage all or assemble, not {args.stage}")
    if args.stage != "assemble" and args.atlas_dir is None:
        raise CliError(f"--atlas-dir: required to train (--stage {args.stage})")
    check_run_folder(args.output_dir)
    check_outputs([("--output-model", args.output_model, None)], args.overwrite)


def run(args: argparse.Namespace) -> int:
    """Run ``svr train-brain-mask``."""
    from svr.masking.recipe import STAGES, MaskerRecipe, assemble_masker, train_stage
    from svr.masking.train import BrainMaskTrainingConfig
    from svr.sampling.volume import VolumeSourceError, atlas_volume_paths

    _check_arguments(args)
    with option_errors(_OPTIONS):
        recipe = MaskerRecipe(
            training=BrainMaskTrainingConfig(
                cases=args.cases,
                steps=args.steps,
                seed=args.seed,
                intensity_curves=args.intensity_curves,
            ),
            tiles=args.tiles,
            segmenter_width=args.segmenter_width,
            segmenter_context=args.segmenter_context,
            label_intensities=args.label_intensities,
            **{name: getattr(args, name) for name in _VARIANTS},
        )
    device = resolve_device(args.device)
    stages = {"all": STAGES, "assemble": ()}.get(args.stage, (args.stage,))
    if stages:
        try:
            atlas_volume_paths(args.atlas_dir)
        except VolumeSourceError as err:
            raise CliError(f"--atlas-dir: {err}") from err
    for stage in stages:
        train_stage(
            recipe, stage, args.output_dir, args.atlas_dir, progress=not args.quiet, device=device
        )
    if args.output_model is None:
        print(f"trained the {' and the '.join(stages)} in {args.output_dir}")
        return 0
    out = assemble_masker(
        recipe,
        args.output_dir,
        args.output_model,
        command=shlex.join(["svr", *sys.argv[1:]]),
        commands=_commands(args, recipe),
        overwrite=args.overwrite,
    )
    print(f"wrote {out}")
    return 0
