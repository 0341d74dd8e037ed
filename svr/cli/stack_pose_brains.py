"""The brains that ``svr train-stack-pose`` trains on.

The atlas ages of one or more atlas folders (with their tissue labels for ``--synthesis``),
anatomy variants and procedural phantoms.

Library modules are imported where they are used, so that building the parser stays light.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from svr.cli.common import CliError

if TYPE_CHECKING:
    from svr.sampling.volume import CanonicalVolume

__all__ = ["TrainingBrains", "phantom_sources", "training_brains"]


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
    from svr.sampling.volume import (
        VolumeSourceError,
        atlas_labels_path,
        canonicalize,
        downsample_volume,
    )

    variants = []
    for index, (volume_path, mask_path) in enumerate(pairs):
        try:
            labels_path = atlas_labels_path(volume_path)
        except VolumeSourceError as err:
            raise CliError(f"--anatomy-variants: {err}") from err
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
class TrainingBrains:
    """The brains the command trains on, as ``train_stack_pose`` takes them.

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


def _atlas_pairs(folders: list[str], hold_out: list[float]) -> list[tuple[Path, Path]]:
    """The (volume, mask) files of every folder's ages but the held-out ones, folder by folder."""
    from svr.sampling.volume import VolumeSourceError, atlas_volume_paths

    pairs = []
    for folder in folders:
        try:
            pairs += atlas_volume_paths(folder, hold_out=hold_out)
        except VolumeSourceError as err:
            raise CliError(f"--atlas-dir: {err}") from err
    return pairs


def _atlas_brains(
    pairs: list[tuple[Path, Path]], labels: bool, downsample: int
) -> list[CanonicalVolume]:
    """The atlas brains, canonical and coarsened, with their tissue labels if ``labels``."""
    from svr.sampling.volume import (
        VolumeSourceError,
        atlas_labels_path,
        downsample_volume,
        load_canonical_volume,
    )

    volumes = []
    for volume, mask in pairs:
        try:
            tissue = atlas_labels_path(volume) if labels else None
        except VolumeSourceError as err:
            raise CliError(f"--synthesis: {err}") from err
        brain = load_canonical_volume(volume, mask, labels_path=tissue)
        volumes.append(downsample_volume(brain, downsample))
    return volumes


def training_brains(args: argparse.Namespace) -> TrainingBrains:
    """Load the atlas ages, make the anatomy variants and phantoms, and weigh them."""
    from svr.sampling.phantom import gestational_age_config, make_phantom
    from svr.sampling.volume import canonicalize, downsample_volume

    pairs = _atlas_pairs(args.atlas_dir, args.hold_out)
    volumes = _atlas_brains(pairs, args.synthesis != "none", args.volume_downsample)
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
    return TrainingBrains(
        pairs, volumes, second_phase, volume_weights, second_weights, phantoms, alike
    )
