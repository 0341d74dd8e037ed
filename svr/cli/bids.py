"""``svr bids``: reconstruct a BIDS cohort, one participant per job (a BIDS App).

``svr bids BIDS_DIR OUTPUT_DIR participant`` reconstructs every T2w stack of each subject (and
session) together, exactly as ``svr reconstruct`` would with the same options
(:func:`svr.cli.reconstruct.load_and_reconstruct`), and writes BIDS derivatives
(:mod:`svr.apps.bids`); ``group`` writes one table and one review page over all of them.
"""

from __future__ import annotations

import argparse
import copy
import logging
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING, Any

from svr.apps.bids import (
    Participant,
    ParticipantOutputs,
    check_output_dir,
    environment,
    find_participants,
    group_report,
    participant_age,
    participant_outputs,
    write_dataset_description,
)
from svr.cli.common import (
    CliError,
    HelpFormatter,
    add_common_options,
    check_run_folder,
    positive_float,
    positive_int,
    resolve_device,
)
from svr.cli.reconstruct import (
    add_mask_options,
    add_settings_options,
    build_configs,
    check_atlas_options,
    excluded_by_stack,
    load_and_reconstruct,
)
from svr.files import file_sha256

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
    from svr.reconstruction.config import ReconstructionResult

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
    masks = p.add_argument_group("automatic masks (without --masks-dir)")
    add_mask_options(masks)
    masks.add_argument(
        "--bias-correction",
        action="store_true",
        help="correct each stack's bias field with N4 before reconstruction",
    )
    add_settings_options(p, iterations=None)
    add_common_options(p)


@dataclass(frozen=True)
class ParticipantJob:
    """What one participant's process needs (picklable).

    Attributes:
        participant: The participant and its stacks.
        output_dir: The derivatives folder.
        settings: The parsed reconstruction settings (a copy, never changed).
        thicknesses: Per stack, the slice thickness (mm).
        threads: CPU threads of this process.
        device: Torch device.
        progress: Show progress bars.
        command: The command line, for the provenance.
    """

    participant: Participant
    output_dir: Path
    settings: argparse.Namespace
    thicknesses: tuple[float, ...]
    threads: int
    device: str
    progress: bool
    command: tuple[str, ...]


@dataclass(frozen=True)
class ParticipantSummary:
    """What a participant's job reports back.

    Attributes:
        label: ``sub-XX[_ses-YY]``.
        seconds: Wall time.
        error: The one-line error, or ``None`` when it succeeded.
        slices: Slices reconstructed.
        excluded: Slices left out.
    """

    label: str
    seconds: float
    error: str | None = None
    slices: int = 0
    excluded: int = 0


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
    for participant in participants:
        try:
            build_configs(args, len(participant.stacks))
        except CliError as err:
            raise CliError(f"{participant.label}: {err}") from err
    _check_model_options(args)
    if args.age_column is not None:
        for participant in participants:  # every age read before any work
            participant_age(args.bids_dir, participant, args.age_column)
    device = resolve_device(args.device)
    thicknesses = {p.label: _thicknesses(p, args.thickness) for p in participants}
    output = Path(args.output_dir)
    output.mkdir(parents=True, exist_ok=True)
    write_dataset_description(output, args.bids_dir)
    todo = []
    for participant in participants:
        if (output / participant.folder).exists() and not args.overwrite:
            log.info("%s: outputs exist, skipped (--overwrite redoes it)", participant.label)
        else:
            todo.append(participant)
    if not todo:
        print(f"nothing to do: all {len(participants)} participants are done in {output}")
        return 0
    jobs = min(args.n_jobs, len(todo))
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    threads = max(1, (cpus or 1) // jobs)
    work = [
        ParticipantJob(
            participant=p,
            output_dir=output,
            settings=copy.copy(args),
            thicknesses=thicknesses[p.label],
            threads=threads,
            device=device,
            progress=jobs == 1 and not args.quiet,
            command=("svr", *sys.argv[1:]),
        )
        for p in todo
    ]
    log.info(
        "%d participants to reconstruct (%d skipped), %d at a time, %d threads each",
        len(todo),
        len(participants) - len(todo),
        jobs,
        threads,
    )
    summaries = []
    if jobs == 1:
        for job in work:
            log.info("%s: started", job.participant.label)
            summaries.append(_report(run_participant(job)))
    else:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
            futures = {pool.submit(run_participant, job): job for job in work}
            for job in work:
                log.info("%s: queued", job.participant.label)
            for future in as_completed(futures):
                summaries.append(_report(future.result()))
    failed = [s for s in summaries if s.error is not None]
    done = len(summaries) - len(failed)
    print(
        f"{done} of {len(summaries)} participants reconstructed in {output}"
        + (f"; failed: {', '.join(s.label for s in failed)}" if failed else "")
    )
    return 1 if failed else 0


def _report(summary: ParticipantSummary) -> ParticipantSummary:
    if summary.error is None:
        log.info(
            "%s: done in %.0f s (%d slices, %d excluded)",
            summary.label,
            summary.seconds,
            summary.slices,
            summary.excluded,
        )
    else:
        print(f"svr bids: {summary.label}: error: {summary.error}", file=sys.stderr)
    return summary


def _check_model_options(args: argparse.Namespace) -> None:
    """The model and atlas checks of ``svr reconstruct``, once, before any participant."""
    if args.age_column is not None:
        if args.atlas_dir is None:
            raise CliError("--age-column needs --atlas-dir")
        if args.gestational_age is not None:
            raise CliError("give --gestational-age or --age-column, not both")
        weeks = 1.0  # any age: the folder and the other options are checked here
    else:
        weeks = None
    check_atlas_options(args, args.registration, weeks)
    if args.registration == "cnn" and args.model != "none":
        from svr.models.predict import load_any_pose_model

        load_any_pose_model(args.model)  # a bad --model fails here, before any work


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


class _Warnings(logging.Handler):
    """Collects the warnings logged while a participant runs, for its sidecar."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(" ".join(record.getMessage().split()))


def run_participant(job: ParticipantJob) -> ParticipantSummary:
    """Reconstruct one participant and write its derivatives atomically (in this process).

    Errors are returned, not raised, so that the other participants go on.
    """
    import torch

    participant = job.participant
    began = time.perf_counter()
    if not logging.getLogger().handlers:  # a fresh worker process
        logging.basicConfig(
            level=logging.WARNING if job.settings.quiet else logging.INFO,
            format=f"%(asctime)s %(levelname)s {participant.label}: %(message)s",
        )
    threads = torch.get_num_threads()  # the caller's, restored after (an in-process call)
    torch.set_num_threads(job.threads)
    handler = _Warnings()
    logging.getLogger().addHandler(handler)
    try:
        result, sidecar = _reconstruct(job, handler)
        _write(job, participant_outputs(participant), result, sidecar, began)
    except (CliError, OSError, ValueError, RuntimeError) as err:
        if job.settings.verbose:
            log.exception("%s failed", participant.label)
        return ParticipantSummary(
            participant.label, time.perf_counter() - began, " ".join(str(err).split())
        )
    finally:
        logging.getLogger().removeHandler(handler)
        torch.set_num_threads(threads)
    return ParticipantSummary(
        participant.label,
        time.perf_counter() - began,
        slices=len(result.slices),
        excluded=int(result.excluded.sum()),
    )


def _reconstruct(
    job: ParticipantJob, warnings: _Warnings
) -> tuple[ReconstructionResult, dict[str, Any]]:
    args, participant = job.settings, job.participant
    args = copy.copy(args)
    args.quiet = args.quiet or not job.progress
    settings = build_configs(args, len(participant.stacks))
    config = settings.reconstruction
    masks = None
    if participant.stacks[0].mask is not None:
        masks = [str(s.mask) for s in participant.stacks]
    weeks = None
    if args.age_column is not None:
        weeks = participant_age(args.bids_dir, participant, args.age_column)
    atlases = check_atlas_options(args, config.registration, weeks)
    _, result = load_and_reconstruct(
        args,
        [str(s.path) for s in participant.stacks],
        masks,
        list(job.thicknesses),
        settings,
        job.device,
        weeks,
    )
    slices = result.slices
    excluded = {Path(name).name: ks for name, ks in excluded_by_stack(result).items()}
    names = [Path(n).name for n in slices.stack_names]
    model = None
    if config.registration == "cnn" and args.model != "none":
        model = {"name": args.model, "sha256": _model_digest(args.model)}
    sidecar = {
        "Description": "Slice-to-volume reconstruction of the participant's T2w stacks",
        "Sources": [f"bids:raw:{s.relative}" for s in participant.stacks],
        "svr": {
            "subject": participant.subject,
            "session": participant.session,
            "command": list(job.command),
            "arguments": {
                key: value
                for key, value in vars(args).items()
                if isinstance(value, str | int | float | bool | list | type(None))
            },
            "software": environment(),
            "model": model,
            "gestational_age_weeks": weeks if weeks is not None else args.gestational_age,
            "atlas": [
                {"volume": volume, "mask": mask, "volume_sha256": file_sha256(volume)}
                for volume, mask in atlases
            ]
            or None,
            "options": {
                "masking": None if masks else asdict(settings.masking),
                "stack_preparation": asdict(settings.stacks),
                "reconstruction": config.settings(),
                "masks": "given (--masks-dir)" if masks else f"automatic ({args.auto_masks})",
                "mask_model": None if masks else args.mask_model,
                "thickness_mm": list(job.thicknesses),
            },
            "inputs": [
                {
                    "file": s.relative,
                    "sha256": file_sha256(s.path),
                    "mask": None if s.mask is None else str(s.mask),
                    "mask_sha256": None if s.mask is None else file_sha256(s.mask),
                    "thickness_mm": t,
                }
                for s, t in zip(participant.stacks, job.thicknesses, strict=True)
            ],
            "initialisation": dict(zip(names, result.initialisation, strict=True)),
            "initialisation_notes": dict(zip(names, result.initialisation_notes, strict=False)),
            "slices": len(slices),
            "slices_excluded": int(result.excluded.sum()),
            "excluded_slices": excluded,
            "frame": slices.frame,
            "atlas_ncc": list(result.atlas_ncc),
            "atlas_chosen": result.atlas_chosen,
            "rounds": len(result.rounds),
            "converged": result.converged,
            "timings_s": result.timings_s,
            "device": job.device,
            "threads": job.threads,
            "warnings": warnings.messages,
        },
    }
    return result, sidecar


def _write(
    job: ParticipantJob,
    names: ParticipantOutputs,
    result: ReconstructionResult,
    sidecar: dict[str, Any],
    began: float,
) -> None:
    """Write every derivative into a temporary folder, then move it into place."""
    import json

    from svr.files import atomic_directory
    from svr.reconstruction.outputs import write_transforms, write_volume
    from svr.reconstruction.qa import qa_figure

    target = job.output_dir / job.participant.folder
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_directory(target, overwrite=job.settings.overwrite) as tmp:
        (tmp / "anat").mkdir()
        write_volume(result.volume, tmp / names.volume)
        write_volume(result.mask, tmp / names.mask)
        write_transforms(result, tmp / names.transforms)
        masks = sidecar["svr"]["options"]["masks"]
        qa_figure(result, tmp / names.qa, notes=[job.participant.label, f"masks: {masks}"])
        sidecar["svr"]["total_seconds"] = time.perf_counter() - began
        (tmp / names.sidecar).write_text(json.dumps(sidecar, indent=1) + "\n", encoding="utf-8")


def _model_digest(name: str) -> str | None:
    """SHA-256 of the weights file of the model that ``--model`` names."""
    from svr.models.checkpoint import CHECKPOINT_WEIGHTS, latest_checkpoint, resolve_model_path
    from svr.models.pretrained import stack_pose_model_path
    from svr.models.stack_pose import STACK_POSE_MODEL

    folder = stack_pose_model_path() if name == STACK_POSE_MODEL else resolve_model_path(name)
    if not (folder / CHECKPOINT_WEIGHTS).is_file():
        folder = latest_checkpoint(folder) or folder
    weights = folder / CHECKPOINT_WEIGHTS
    return file_sha256(weights) if weights.is_file() else None
