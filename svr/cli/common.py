"""Options and checks shared by the ``svr`` subcommands."""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from svr.errors import ConfigFieldError

if TYPE_CHECKING:
    from svr.sampling.volume import CanonicalVolume


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 1."""


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Show defaults (except ``None``, which the help text explains) and keep line breaks."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default == []:
            return action.help
        return super()._get_help_string(action)


MODEL_HELP = (
    "'default' (the model shipped with the package), a checkpoint folder, or a training run "
    "folder from svr train (its newest checkpoint); write ./default for a folder of that name"
)
"""A model argument's one meaning (:func:`svr.models.checkpoint.resolve_model_path`)."""


MASK_MODEL_HELP = (
    "brain-mask model: 'default' (shipped with the package) or a model folder written by "
    "svr train-brain-mask"
)
"""The meaning of ``--mask-model`` (:func:`svr.masking.load_brain_masker`)."""


def check_outputs(
    outputs: Sequence[tuple[str, str | None, tuple[str, ...] | None]],
    overwrite: bool,
    inputs: Sequence[tuple[str, str]] = (),
) -> None:
    """Check output paths before any computation: suffix, existence, folder, no repeats.

    Args:
        outputs: ``(option, path, suffixes)`` per output; a ``None`` path (not given) is
            skipped, ``None`` suffixes accept any name.
        overwrite: Whether existing outputs may be replaced.
        inputs: ``(option, path)`` of input files that no output may be.

    Raises:
        CliError: For a wrong suffix, or a path given twice (naming the other option).
        OutputExistsError, FileNotFoundError, PermissionError: From
            :func:`svr.files.check_output_path`.
    """
    from svr.files import check_output_path

    seen = {Path(path).resolve(): option for option, path in inputs}
    for option, path, suffixes in outputs:
        if path is None:
            continue
        if suffixes is not None and not path.endswith(suffixes):
            raise CliError(f"{option} {path}: must end in {' or '.join(suffixes)}")
        resolved = Path(path).resolve()
        if resolved in seen:
            raise CliError(f"{option} {path}: the same path as {seen[resolved]}")
        seen[resolved] = option
        check_output_path(path, overwrite)


def add_common_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--device``, ``--seed``, ``--verbose`` and ``--quiet``."""
    parser.add_argument(
        "--device",
        default="auto",
        help="torch device: auto (cuda if available, else cpu), cpu, cuda, cuda:N",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    add_verbosity_options(parser)


def add_verbosity_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--verbose`` and ``--quiet`` (one or the other)."""
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging and tracebacks on errors"
    )
    verbosity.add_argument(
        "-q", "--quiet", action="store_true", help="warnings and errors only, no progress bars"
    )


def add_rotation_option(group: argparse._ActionsContainer) -> None:
    """Add ``--rotation euler|uniform``: the rotations that slice poses are drawn from."""
    group.add_argument(
        "--rotation",
        choices=["euler", "uniform"],
        default="euler",
        help="euler: angles in ±90° (the paper); uniform: all of SO(3)",
    )


def resolve_device(name: str) -> str:
    """Turn ``--device`` into a usable torch device string.

    Raises:
        CliError: If the device is unknown or CUDA is requested but not available.
    """
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise CliError(
            f"--device: unknown device {name!r} (use auto, cpu, cuda or cuda:N)"
        ) from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise CliError(f"--device {name}: CUDA is not available on this machine (use cpu)")
    if device.type not in ("cpu", "cuda"):
        raise CliError(f"--device: unsupported device type {device.type!r} (use cpu or cuda)")
    return str(device)


def positive_int(text: str) -> int:
    """Argparse type: an integer > 0."""
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return value


def non_negative_int(text: str) -> int:
    """Argparse type: an integer >= 0."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def positive_float(text: str) -> float:
    """Argparse type: a finite float > 0."""
    value = float(text)
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def non_negative_float(text: str) -> float:
    """Argparse type: a finite float >= 0."""
    value = float(text)
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def check_thickness_count(thicknesses: list[float] | None, count: int) -> None:
    """Refuse a ``--thicknesses`` list that is neither one value nor one per stack.

    Raises:
        CliError: Naming ``--thicknesses``.
    """
    if thicknesses is not None and len(thicknesses) not in (1, count):
        raise CliError(
            f"--thicknesses: got {len(thicknesses)} values for {count} stacks; give one for "
            "all stacks or one per stack"
        )


def check_fusion_count(count: int) -> None:
    """Refuse ``--fuse-masks`` with fewer stacks than a vote needs.

    Raises:
        CliError: Naming ``--fuse-masks``.
    """
    from svr.masking import MIN_FUSED_STACKS

    if count < MIN_FUSED_STACKS:
        raise CliError(
            f"--fuse-masks: needs at least {MIN_FUSED_STACKS} stacks of one fetus, got {count}"
        )


@contextmanager
def option_errors(options: Mapping[str, str]) -> Iterator[None]:
    """Report a bad configuration value as the command-line option that set it.

    Wrap the construction of a command's configurations: a
    :class:`~svr.errors.ConfigFieldError` raised meanwhile becomes a :class:`CliError` that
    names the option, e.g. ``--steps must be an integer >= 1, got 0``.

    Args:
        options: Configuration field -> the option that sets it (``{"steps": "--steps"}``). A
            key ``"Owner.field"`` (``"OptimConfig.name"``) applies to that configuration class
            only and comes first. A field that no option sets keeps the library's message, which
            names the configuration and the field.

    Raises:
        CliError: In place of a :class:`~svr.errors.ConfigFieldError`.
    """
    try:
        yield
    except ConfigFieldError as err:
        option = options.get(f"{err.owner}.{err.field}", options.get(err.field))
        if option is None:
            raise CliError(str(err)) from err
        value, expected = err.value, err.expected
        if value is not None:  # an option given has a value: "None or ..." is for the library
            expected = expected.removeprefix("None or ")
        shown = str(value)
        if isinstance(value, tuple | list) and value:
            shown = " ".join(map(str, value))  # as the values are typed on the command line
        raise CliError(f"{option} must be {expected}, got {shown}") from err


def check_run_folder(path: str, option: str = "--output-dir") -> Path:
    """Check that a run folder can be created or added to: a folder, or creatable and writable.

    Args:
        path: The folder (it may exist, e.g. to resume a run).
        option: The option (or argument) that names it, for the messages.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        CliError: If the path exists and is not a folder.
        PermissionError: If the folder, or the nearest existing folder above it, is not writable.
    """
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise CliError(f"{option} {out}: exists and is not a folder")
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise CliError(f"{option} {out}: {existing} is not a folder")
    if not os.access(existing, os.W_OK):
        raise PermissionError(f"{out}: output folder {existing} is not writable")
    return out


def add_volume_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--input-volume``, ``--input-mask`` and ``--phantom-ga`` (the built-in brain)."""
    group = parser.add_argument_group("input volume (default: the built-in phantom)")
    group.add_argument("--input-volume", help="brain volume (NIfTI), e.g. an atlas srr.nii.gz")
    group.add_argument("--input-mask", help="its brain mask (NIfTI, same grid)")
    group.add_argument(
        "--phantom-ga",
        type=positive_float,
        default=28.0,
        help="gestational age (weeks) of the built-in phantom, without --input-volume",
    )


def load_input_volume(args: argparse.Namespace) -> tuple[CanonicalVolume, str]:
    """The canonical volume named by the options, and a name for it.

    Raises:
        CliError: If only one of ``--input-volume`` and ``--input-mask`` is given.
        ImageError: For unusable files (the message names the file).
    """
    from svr.sampling.volume import load_volumes

    if (args.input_volume is None) != (args.input_mask is None):
        raise CliError("--input-volume and --input-mask go together")
    pairs = [] if args.input_volume is None else [(args.input_volume, args.input_mask)]
    volumes, names = load_volumes(pairs, phantom_ages=(args.phantom_ga,))
    if args.input_volume is None:
        return volumes[0], f"phantom (GA {args.phantom_ga:g} weeks)"
    return volumes[0], names[0]


def registered_loss(text: str) -> str:
    """Argparse type of ``--loss``: a registered representation's command-line name.

    The registry (:func:`svr.representation_registry.representations_by_cli_name`) is read when
    the option is parsed, not when the parser is built, so that ``svr --help`` imports no torch
    and a representation registered by a plug-in is a loss on the command line.

    Raises:
        argparse.ArgumentTypeError: Listing the registered names.
    """
    from svr.representation_registry import representations_by_cli_name

    names = representations_by_cli_name()
    if text not in names:
        raise argparse.ArgumentTypeError(
            f"invalid choice: {text!r} (choose from {', '.join(map(repr, sorted(names)))})"
        )
    return text


LOSS_HELP = (
    "pose output and loss, a registered representation's name: se3 (the SE(3) geodesic loss, "
    "default), or the baselines posenet (quaternion and translation), anchor (anchor points) "
    "and rot6d (6D rotation and translation)"
)
"""The meaning of ``--loss`` (``svr train``, ``svr train-stack-pose``)."""
