"""``svr reconstruct``: a volume from motion-corrupted thick-slice stacks (SVR + super-resolution).

The options are shared with ``svr register`` (the same pipeline with fewer rounds and the volume
optional) and ``svr bids`` (:mod:`svr.cli.recon_options`); the run is the library's
:func:`svr.apps.reconstruct.run_reconstruction`.
"""

from __future__ import annotations

import argparse
import io
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from svr.cli.common import (
    CliError,
    HelpFormatter,
    add_common_options,
    check_outputs,
    check_thickness_count,
    positive_float,
    resolve_device,
)
from svr.cli.recon_options import add_reconstruction_options, build_job
from svr.files import atomic_write_text

if TYPE_CHECKING:
    from svr.apps.reconstruct import ReconstructionJob
    from svr.reconstruction.result import ReconstructionResult

DESCRIPTION = """\
Reconstruct a 3D brain volume from thick-slice stacks of a fetus that moved.

You give the stacks (--input-stacks: NIfTI, slices along the third array axis) and their slice
thickness (--thicknesses); you get the volume (--output-volume) and, if you ask, every slice's
pose and quality (--output-transforms), the posed slices (--output-slices, NeSVoR's folder
format), a QA page (--output-qa) and a log (--output-log). Brain masks are found automatically
unless you give them (--stack-masks). With --registration stack (the default) the volume is in the
scanner's frame; with --registration cnn every stack is placed in an atlas's canonical space by
the shipped stack-pose model, and with --atlas-volume (or --atlas-dir and --gestational-age) the
volume is written in that atlas's frame. Output paths are checked before any work and never
replaced without --overwrite.

examples:
  svr reconstruct --input-stacks ax.nii.gz cor.nii.gz sag.nii.gz --thicknesses 3 \\
      --output-volume srr.nii.gz --output-qa srr_qa.png
  svr reconstruct --input-stacks ax.nii.gz cor.nii.gz sag.nii.gz --thicknesses 3 \\
      --registration cnn --atlas-dir atlas/ --gestational-age 27.5 \\
      --output-volume srr_atlas.nii.gz --output-transforms slices.csv --output-log srr.log
  svr reconstruct --input-stacks case1/stacks/stack*.nii.gz --stack-masks case1/masks/*.nii.gz \\
      --registration cnn --atlas-volume atlas/GA28/srr.nii.gz --atlas-mask atlas/GA28/mask.nii.gz \\
      --output-volume srr_atlas.nii.gz --output-slices slices/ --device cuda
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
    add_options(p, volume_required=True)


def add_options(parser: argparse.ArgumentParser, volume_required: bool) -> None:
    """Add the inputs, outputs and settings of ``svr reconstruct`` and ``svr register``.

    Args:
        parser: The subcommand's parser.
        volume_required: Whether ``--output-volume`` is required.
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
    outputs.add_argument("--output-qa", metavar="FILE", help="quality page (.png or .pdf)")
    outputs.add_argument(
        "--output-log", metavar="FILE", help="text log: messages, settings, timings per phase"
    )
    outputs.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_reconstruction_options(parser, inputs)
    add_common_options(parser)


def run(args: argparse.Namespace) -> int:
    """Run ``svr reconstruct`` (and ``svr register``): check, reconstruct, write the outputs.

    Raises:
        CliError: For inconsistent options or output paths.
        ValueError, OSError: From the library (bad or missing files, checkpoints), naming the file.
    """
    from svr.apps.reconstruct import run_reconstruction

    count = len(args.input_stacks)
    if args.stack_masks is not None and len(args.stack_masks) != count:
        raise CliError(
            f"--stack-masks: got {len(args.stack_masks)} masks for {count} stacks; give none or "
            "one per stack"
        )
    check_thickness_count(args.thicknesses, count)
    device = resolve_device(args.device)
    job = build_job(args, args.input_stacks, args.stack_masks, args.thicknesses, device)
    _check_outputs(args)
    with _captured_log() as captured:
        stacks, result = run_reconstruction(job)
        _log_result(result)
        written = _write_outputs(args, job, result)
    if args.output_log is not None:
        text = captured.getvalue() + _summary(args, job, result)
        if result.verdict is not None:  # the log's last line
            text += f"verdict: {result.verdict.line()}\n"
        atomic_write_text(args.output_log, text, args.overwrite)
        written.append(args.output_log)
    excluded = int(result.excluded.sum())
    print(
        f"wrote {', '.join(written)}: {len(result.slices)} slices from {len(stacks)} stacks, "
        f"{excluded} excluded, {result.slices.frame} frame"
    )
    if result.verdict is not None:
        print(f"verdict: {result.verdict.line()}")
    return 0


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


def _log_result(result: ReconstructionResult) -> None:
    from svr.apps.reconstruct import excluded_by_stack

    frame = result.slices.frame
    where = "an atlas's canonical space" if frame == "canonical" else "the stacks' world frame"
    log.info("the output volume and poses are in the %s frame (%s)", frame, where)
    for name, ks in excluded_by_stack(result).items():
        log.info("%s: excluded slices k = %s", name, ", ".join(map(str, ks)))


def _write_outputs(
    args: argparse.Namespace, job: ReconstructionJob, result: ReconstructionResult
) -> list[str]:
    """Write the requested outputs (the log aside); returns their paths."""
    from svr.reconstruction.outputs import write_slices_folder, write_transforms, write_volume
    from svr.reconstruction.qa import qa_figure

    written = []
    if args.output_volume is not None:
        volume = write_volume(result.volume, args.output_volume, args.overwrite, result.verdict)
        written.append(str(volume))
    if args.output_transforms is not None:
        written.append(str(write_transforms(result, args.output_transforms, args.overwrite)))
    if args.output_slices is not None:
        keep = ~result.excluded
        written.append(
            str(write_slices_folder(result.slices, args.output_slices, args.overwrite, keep))
        )
    if args.output_qa is not None:
        notes = [f"masks: {job.mask_source}"]
        written.append(
            str(qa_figure(result, args.output_qa, overwrite=args.overwrite, notes=notes))
        )
    return written


def _summary(args: argparse.Namespace, job: ReconstructionJob, result: ReconstructionResult) -> str:
    """The settings, timings, initialisation and exclusions, as text for --output-log."""
    from svr.apps.reconstruct import excluded_by_stack, provenance
    from svr.reconstruction.atlas_frame import atlas_turn_line
    from svr.reconstruction.convergence import verdict
    from svr.reconstruction.midplane import mirror_plane_line

    lines = [f"# svr {args.command} summary", "inputs:"]
    masks = job.masks or [job.mask_source] * len(job.stacks)
    lines += [f"  {stack} (mask {mask})" for stack, mask in zip(job.stacks, masks, strict=True)]
    record = provenance(job)
    for key in ("start", "model", "masks", "device"):
        lines.append(f"{key}: {record[key]}")
    lines.append("options:")
    lines += [f"  {flag}: {value}" for flag, value in record["options"].items()]
    for section in ("masking", "stack_preparation"):
        if record[section] is not None:
            lines.append(f"{section.replace('_', ' ')}:")
            lines += [f"  {key}: {value}" for key, value in record[section].items()]
    lines.append("time per phase (s):")
    lines += [f"  {name}: {seconds:.2f}" for name, seconds in result.timings_s.items()]
    lines.append(f"  total: {sum(result.timings_s.values()):.2f}")
    lines.append("initialisation per stack:")
    notes = result.initialisation_notes or ("",) * len(result.initialisation)
    for name, init, note in zip(
        result.slices.stack_names, result.initialisation, notes, strict=True
    ):
        lines.append(f"  {name}: {init}")
        lines += [f"    {note}"] if note else []
    lines.append(f"frame: {result.slices.frame}")
    if result.atlas_chosen is not None:
        volumes = [volume for volume, _ in job.atlases]
        lines.append(f"atlas frame: {volumes[result.atlas_chosen]}")
        lines += [
            f"  {path}: NCC {ncc:.3f}" for path, ncc in zip(volumes, result.atlas_ncc, strict=True)
        ]
        lines.append(f"  {atlas_turn_line(result)}")
    mirror = mirror_plane_line(result)
    lines += [mirror] if mirror else []
    ending = verdict(result.converged)
    schedule = job.config.schedule.kind
    lines.append(
        f"rounds: {len(result.rounds)} ({schedule} schedule{', ' + ending if ending else ''})"
    )
    lines += [f"  {item.line()}" for item in result.rounds]
    excluded = excluded_by_stack(result)
    lines.append(f"excluded slices: {int(result.excluded.sum())} of {len(result.slices)}")
    lines += [f"  {name}: k = {', '.join(map(str, ks))}" for name, ks in excluded.items()]
    return "\n".join(lines) + "\n"
