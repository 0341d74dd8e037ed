"""The ``svr`` command line: one entry point, explicit subcommand dispatch.

Each subcommand module defines ``add_parser(subparsers)`` and ``run(args) -> int``; ``run`` turns
the parsed options into a dataclass config and calls library code. Errors that users can cause
(bad files, bad values) are reported as one line on stderr with a non-zero exit; tracebacks only
with ``--verbose``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import traceback
from collections.abc import Sequence
from typing import NoReturn

from svr import __version__
from svr.cli import (
    bids,
    demo,
    evaluate,
    export_model,
    predict,
    reconstruct,
    register,
    sample,
    segment_stack,
    segment_volume,
    simulate,
    train,
    train_brain_mask,
    train_stack_pose,
)
from svr.cli.common import CliError
from svr.files import OutputExistsError

SUBCOMMANDS = {
    "reconstruct": reconstruct,
    "bids": bids,
    "segment-stack": segment_stack,
    "segment-volume": segment_volume,
    "register": register,
    "predict": predict,
    "demo": demo,
    "simulate": simulate,
    "train-stack-pose": train_stack_pose,
    "train": train,
    "evaluate": evaluate,
    "sample": sample,
    "train-brain-mask": train_brain_mask,
    "export-model": export_model,
}
"""The commands, in the order ``svr --help`` lists them: what most users run first."""


class UsageError(Exception):
    """A command line that argparse refuses (an unknown option, a value of the wrong type).

    Attributes:
        prog: The (sub)command's name, e.g. ``"svr reconstruct"``.
        message: What argparse says is wrong.
    """

    def __init__(self, prog: str, message: str) -> None:
        super().__init__(message)
        self.prog, self.message = prog, message


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line and exit status 1, as every other error."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(self.prog, message)


def build_parser() -> argparse.ArgumentParser:
    """The ``svr`` argument parser with all subcommands."""
    parser = _Parser(
        prog="svr",
        description="Fetal MRI slice-to-volume reconstruction with learned SE(3) slice poses.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in SUBCOMMANDS.values():
        module.add_parser(subparsers)
    return parser


def _one_line(err: BaseException) -> str:
    """An error's message on one line (library messages may span several), never empty."""
    return " ".join(str(err).split()) or type(err).__name__


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``svr`` command line.

    Args:
        argv: Arguments without the program name (default: ``sys.argv[1:]``).

    Returns:
        The exit status: 0 on success, 1 on a reported error (bad usage included), 130 on an
        interrupt.
    """
    words = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(words)
    except UsageError as err:
        if "-v" in words or "--verbose" in words:
            traceback.print_exc(file=sys.stderr)
        print(
            f"{err.prog}: error: {_one_line(err)} ({err.prog} --help lists the options)",
            file=sys.stderr,
        )
        return 1
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return SUBCOMMANDS[args.command].run(args)
    except OutputExistsError as err:
        if args.verbose:
            traceback.print_exc(file=sys.stderr)
        print(
            f"svr {args.command}: error: {_one_line(err)}; pass --overwrite to replace it",
            file=sys.stderr,
        )
        return 1
    except (CliError, OSError, ValueError) as err:
        if args.verbose:  # straight to stderr: logging may be configured elsewhere (in-process use)
            traceback.print_exc(file=sys.stderr)
        print(f"svr {args.command}: error: {_one_line(err)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"svr {args.command}: interrupted", file=sys.stderr)
        return 130
