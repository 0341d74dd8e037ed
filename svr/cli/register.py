"""``svr register``: slice poses of motion-corrupted stacks (the pipeline's initialisation)."""

from __future__ import annotations

import argparse

from svr.cli.common import CliError, HelpFormatter
from svr.cli.config_options import set_option_default
from svr.cli.reconstruct import add_options
from svr.cli.reconstruct import run as run_reconstruction

DESCRIPTION = """\
Estimate the pose of every slice of thick-slice stacks: the pose initialisation of `svr
reconstruct` (--registration stack|cnn|atlas|none) followed by one super-resolution round, which
scores every slice (NCC with its simulation) for the outputs; --iterations above 1 adds rounds of
slice-to-volume registration. The same pipeline and options as `svr reconstruct`, with the volume
optional: write the poses (--output-transforms), the posed slices (--output-slices, NeSVoR's
folder format, for `nesvor reconstruct --input-slices` or `svr predict --input-slices`) and/or the
volume. Poses are in canonical atlas space with --registration cnn, in the scanner's world frame
otherwise.

examples:
  svr register --input-stacks ax.nii.gz cor.nii.gz sag.nii.gz \\
      --stack-masks ax_mask.nii.gz cor_mask.nii.gz sag_mask.nii.gz --registration cnn \\
      --output-transforms poses.csv --output-slices slices/
  svr register --input-stacks ax.nii.gz cor.nii.gz --registration stack --template 0 \\
      --iterations 3 --output-transforms poses.json --output-qa register_qa.png
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr register``."""
    p = subparsers.add_parser(
        "register",
        help="estimate slice poses of motion-corrupted stacks (no volume needed)",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    add_options(p, volume_required=False)
    set_option_default(p, "--iterations", 1)


def run(args: argparse.Namespace) -> int:
    """Run ``svr register``."""
    if not (args.output_transforms or args.output_slices or args.output_volume):
        raise CliError(
            "nothing to write: give --output-transforms, --output-slices and/or --output-volume"
        )
    return run_reconstruction(args)
