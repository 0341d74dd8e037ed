"""``svr bids``: reconstruct a BIDS cohort, one participant per job (a BIDS App).

``svr bids BIDS_DIR OUTPUT_DIR participant`` reconstructs every T2w stack of each subject (and
session) together, exactly as ``svr reconstruct`` would with the same options (both run
:func:`svr.apps.reconstruct.run_reconstruction`), and writes BIDS derivatives
(:mod:`svr.apps.bids_participant`); ``group`` writes one table and one review page over all of
them (:mod:`svr.apps.bids`).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING

from svr.apps.bids import (
    Participant,
    check_output_dir,
    find_participants,
    participant_age,
    write_dataset_description,
)
from svr.apps.bids_group import group_report
from svr.cli.common import (
    CliError,
    HelpFormatter,
    add_common_options,
    check_run_folder,
    positive_float,
    positive_int,
    resolve_device,
)
from svr.cli.recon_options import add_reconstruction_options, build_job

DESCRIPTION = """\
Reconstruct a cohort kept as a BIDS dataset (a BIDS App). Participant level: every T2w stack of
a subject (and session: sub-XX/[ses-YY/]anat/*_T2w.nii.gz) is reconstructed together, as
`svr reconstruct` does with the same options; brain masks come from --masks-dir (a derivatives
folder with one *_desc-brain_mask.nii.gz per stack, with the stack's entities) or are made
automatically; the slice thickness comes from each stack's JSON sidecar (SliceThickness).
Outputs are BIDS derivatives in OUTPUT_DIR:

  sub-XX[/ses-YY]/anat/sub-XX[_ses-YY]_rec-svr_T2w.nii.gz      the reconstruction
                       ..._rec-svr_desc-brain_mask.nii.gz       its brain mask
                       ..._rec-svr_transforms.csv               every slice's pose and quality
                       ..._rec-svr_qa.png                       the quality figure
                       ..._rec-svr_T2w.json                     provenance: version, model and
                                                                its hash, every option, input
                                                                checksums, initialisation kept,
                                                                slices excluded, timings, device
  dataset_description.json                                      with GeneratedBy

A participant's folder appears only when it is complete, so a killed job leaves nothing half
written; a participant whose folder exists is skipped (--overwrite redoes it). --n-jobs runs
participants side by side on one machine (one process each, the CPU threads shared out). On a
cluster, run one participant per job, e.g. a SLURM job array over the participants.tsv rows.

Group level: OUTPUT_DIR/svr_group.tsv and svr_group.html (QA figures, slices kept, timings,
warnings) over every finished participant, to review a cohort in one page.

examples:
  svr bids study/ study-svr/ participant --participant-label 01 02 --masks-dir study-masks/
  svr bids study/ study-svr/ participant --n-jobs 2
  svr bids study/ study-svr/ group

  # a SLURM job array, one participant per task (the script is in the documentation,
  # docs/slurm/svr-bids-array.sh: task N takes row N of participants.tsv, SLURM_ARRAY_TASK_ID):
  BIDS_DIR=study OUTPUT_DIR=study-svr sbatch --array=1-40 svr-bids-array.sh
"""

if TYPE_CHECKING:
    from svr.apps.bids_participant import ParticipantJob, ParticipantSummary

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr bids``."""
    p = subparsers.add_parser(
        "bids",
        help="reconstruct a BIDS cohort, one participant per job (BIDS App)",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument("bids_dir", metavar="BIDS_DIR", help="the input BIDS dataset")
    p.add_argument(
        "output_dir", metavar="OUTPUT_DIR", help="the derivatives folder (outside BIDS_DIR)"
    )
    p.add_argument(
        "analysis_level",
        metavar="{participant,group}",
        choices=("participant", "group"),
        help="participant: reconstruct; group: the table and review page over all participants",
    )
    bids = p.add_argument_group("BIDS")
    bids.add_argument(
        "--participant-label",
        nargs="+",
        metavar="LABEL",
        help="subjects to process (with or without sub-); default: all",
    )
    bids.add_argument(
        "--session-label",
        nargs="+",
        metavar="LABEL",
        help="sessions to process (with or without ses-); default: all",
    )
    bids.add_argument(
        "--skip-bids-validation",
        action="store_true",
        help="read BIDS_DIR even without a valid dataset_description.json",
    )
    bids.add_argument(
        "--masks-dir",
        metavar="DIR",
        help="derivatives folder of brain masks, one sub-XX[_ses-YY]_..._desc-brain_mask.nii.gz "
        "per stack (default: automatic masks, see --auto-masks)",
    )
    bids.add_argument(
        "--age-column",
        metavar="NAME",
        help="with --atlas-dir: the column of participants.tsv (or of a subject's "
        "sub-XX_sessions.tsv, per session) holding each participant's gestational age in weeks, "
        "so that each is fitted to the atlases of its own age",
    )
    bids.add_argument(
        "--tissue-labels",
        action="store_true",
        help="also label each reconstruction's tissues with the atlases of --atlas-dir (svr "
        "segment-volume: labels, volumes, biometry, an HTML report; needs each participant's age)",
    )
    bids.add_argument(
        "--thickness",
        type=positive_float,
        metavar="MM",
        help="slice thickness of stacks whose sidecar has no SliceThickness (default: their "
        "slice spacing, with a warning)",
    )
    bids.add_argument(
        "--n-jobs",
        type=positive_int,
        default=1,
        metavar="N",
        help="participants reconstructed side by side (one process each)",
    )
    bids.add_argument(
        "--overwrite", action="store_true", help="redo participants whose outputs exist"
    )
    masks = p.add_argument_group("automatic brain masks (without --masks-dir)")
    masks.add_argument(
        "--bias-correction",
        action="store_true",
        help="correct each stack's bias field with N4 before reconstruction",
    )
    add_reconstruction_options(p, masks)
    add_common_options(p)


def run(args: argparse.Namespace) -> int:
    """Run ``svr bids``."""
    check_output_dir(args.bids_dir, args.output_dir)
    check_run_folder(args.output_dir, "OUTPUT_DIR")
    if args.analysis_level == "group":
        tsv, page, count = group_report(args.output_dir, args.participant_label)
        print(f"wrote {tsv} and {page}: {count} participants")
        return 0
    participants = find_participants(
        args.bids_dir,
        args.participant_label,
        args.session_label,
        args.masks_dir,
        validate=not args.skip_bids_validation,
    )
    if args.age_column is not None and args.atlas_dir is None:
        raise CliError("--age-column needs --atlas-dir")
    if args.tissue_labels and args.atlas_dir is None:
        raise CliError("--tissue-labels needs --atlas-dir (the atlases whose labels are used)")
    if args.age_column is not None and args.gestational_age is not None:
        raise CliError("give --gestational-age or --age-column, not both")
    device = resolve_device(args.device)
    output = Path(args.output_dir)
    todo = []
    for participant in participants:
        if (output / participant.folder).exists() and not args.overwrite:
            log.info("%s: outputs exist, skipped (--overwrite redoes it)", participant.label)
        else:
            todo.append(participant)
    # Every participant's options, ages and model checked before any work.
    jobs = min(args.n_jobs, len(todo)) or 1
    work = [_participant_job(args, p, device, jobs) for p in todo]
    output.mkdir(parents=True, exist_ok=True)
    write_dataset_description(output, args.bids_dir)
    if not todo:
        print(f"nothing to do: all {len(participants)} participants are done in {output}")
        return 0
    log.info(
        "%d participants to reconstruct (%d skipped), %d at a time, %d threads each",
        len(todo),
        len(participants) - len(todo),
        jobs,
        work[0].threads,
    )
    summaries = _run_all(work, jobs)
    failed = [s for s in summaries if s.error is not None]
    unusable = [s for s in summaries if s.failed]
    done = len(summaries) - len(failed)
    print(
        f"{done} of {len(summaries)} participants reconstructed in {output}"
        + (f"; errors: {', '.join(s.label for s in failed)}" if failed else "")
        + (
            f"; failed verdict (no usable volume): {', '.join(s.label for s in unusable)}"
            if unusable
            else ""
        )
    )
    return 1 if failed else 0


def _participant_job(
    args: argparse.Namespace, participant: Participant, device: str, jobs: int
) -> ParticipantJob:
    """The participant's job: its stacks, masks, thicknesses and age, the options resolved."""
    from svr.apps.bids_participant import ParticipantJob

    weeks = None
    if args.age_column is not None:
        weeks = participant_age(args.bids_dir, participant, args.age_column)
    masks = None
    if participant.stacks[0].mask is not None:
        masks = [str(s.mask) for s in participant.stacks]
    thicknesses = _thicknesses(participant, args.thickness)
    try:
        job = build_job(
            args, [str(s.path) for s in participant.stacks], masks, thicknesses, device, weeks
        )
    except CliError as err:
        raise CliError(f"{participant.label}: {err}") from err
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    job = dataclasses.replace(job, progress=jobs == 1 and not args.quiet)
    arguments = {
        key: value
        for key, value in vars(args).items()
        if isinstance(value, str | int | float | bool | list | type(None))
    }
    return ParticipantJob(
        participant=participant,
        output_dir=Path(args.output_dir),
        job=job,
        threads=max(1, (cpus or 1) // jobs),
        command=("svr", *sys.argv[1:]),
        arguments=arguments,
        weeks=weeks if weeks is not None else args.gestational_age,
        tissue_atlases=(args.atlas_dir,) if args.tissue_labels else (),
        overwrite=args.overwrite,
        verbose=args.verbose,
        quiet=args.quiet,
    )


def _run_all(work: list[ParticipantJob], jobs: int) -> list[ParticipantSummary]:
    """Every participant, one after another or ``jobs`` processes side by side."""
    from svr.apps.bids_participant import run_participant

    summaries = []
    if jobs == 1:
        for item in work:
            log.info("%s: started", item.participant.label)
            summaries.append(_report(run_participant(item)))
        return summaries
    with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(run_participant, item): item for item in work}
        for item in work:
            log.info("%s: queued", item.participant.label)
        for future in as_completed(futures):
            summaries.append(_report(future.result()))
    return summaries


def _report(summary: ParticipantSummary) -> ParticipantSummary:
    if summary.error is None:
        log.info(
            "%s: done in %.0f s (%d slices, %d excluded); verdict: %s",
            summary.label,
            summary.seconds,
            summary.slices,
            summary.excluded,
            summary.verdict,
        )
    else:
        print(f"svr bids: {summary.label}: error: {summary.error}", file=sys.stderr)
    return summary


def _thicknesses(participant: Participant, default: float | None) -> tuple[float, ...]:
    """Per stack: the sidecar's SliceThickness, else ``--thickness``, else the slice spacing."""
    from svr.image import load_nifti

    out = []
    for stack in participant.stacks:
        if stack.thickness_mm is not None:
            out.append(stack.thickness_mm)
        elif default is not None:
            out.append(default)
        else:
            spacing = float(load_nifti(stack.path).spacing[2])
            log.warning(
                "%s: %s has no SliceThickness in its sidecar; using its slice spacing %.2f mm "
                "(--thickness sets it)",
                participant.label,
                stack.path.name,
                spacing,
            )
            out.append(spacing)
    return tuple(out)
