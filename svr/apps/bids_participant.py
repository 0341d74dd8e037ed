"""One participant of ``svr bids``: reconstruct it and write its derivatives atomically.

:func:`run_participant` runs in the command's process or in a worker process; it takes a
picklable :class:`ParticipantJob` (the participant, its
:class:`~svr.apps.reconstruct.ReconstructionJob` and what its provenance records) and returns a
:class:`ParticipantSummary`, its error included, so that the other participants go on.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from svr.apps.bids import Participant, ParticipantOutputs, environment, participant_outputs
from svr.apps.reconstruct import (
    ReconstructionJob,
    excluded_by_stack,
    provenance,
    run_reconstruction,
)
from svr.files import file_sha256
from svr.image import Image
from svr.reconstruction.result import ReconstructionResult
from svr.tissue.labels import TISSUE_LABELS

__all__ = ["ParticipantJob", "ParticipantSummary", "run_participant"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ParticipantJob:
    """What one participant's process needs (picklable).

    Attributes:
        participant: The participant and its stacks.
        output_dir: The derivatives folder.
        job: Its reconstruction.
        threads: CPU threads of this process.
        command: The command line, for the provenance.
        arguments: The command's options and their values, for the provenance.
        weeks: The participant's gestational age (weeks), or ``None``.
        tissue_atlases: Atlas folders to label the tissues with (``--tissue-labels``); empty
            for none.
        overwrite: Replace the participant's folder if it exists.
        verbose: Log errors with their traceback.
        quiet: Warnings and errors only.
    """

    participant: Participant
    output_dir: Path
    job: ReconstructionJob
    threads: int
    command: tuple[str, ...]
    arguments: dict[str, Any] = field(default_factory=dict)
    weeks: float | None = None
    tissue_atlases: tuple[str, ...] = ()
    overwrite: bool = False
    verbose: bool = False
    quiet: bool = False


@dataclass(frozen=True)
class ParticipantSummary:
    """What a participant's job reports back.

    Attributes:
        label: ``sub-XX[_ses-YY]``.
        seconds: Wall time.
        error: The one-line error, or ``None`` when it succeeded.
        slices: Slices reconstructed.
        excluded: Slices left out.
        verdict: The reconstruction's verdict line, or ``None`` (an error, or none assessed).
        failed: Whether the verdict is that no usable volume came out.
    """

    label: str
    seconds: float
    error: str | None = None
    slices: int = 0
    excluded: int = 0
    verdict: str | None = None
    failed: bool = False


class _Warnings(logging.Handler):
    """Collects the warnings logged while a participant runs, for its sidecar."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(" ".join(record.getMessage().split()))


def run_participant(work: ParticipantJob) -> ParticipantSummary:
    """Reconstruct one participant and write its derivatives atomically (in this process).

    Errors are returned, not raised, so that the other participants go on.
    """
    import torch

    participant = work.participant
    began = time.perf_counter()
    if not logging.getLogger().handlers:  # a fresh worker process
        logging.basicConfig(
            level=logging.WARNING if work.quiet else logging.INFO,
            format=f"%(asctime)s %(levelname)s {participant.label}: %(message)s",
        )
    threads = torch.get_num_threads()  # the caller's, restored after (an in-process call)
    torch.set_num_threads(work.threads)
    handler = _Warnings()
    logging.getLogger().addHandler(handler)
    try:
        _, result = run_reconstruction(work.job)
        sidecar = _sidecar(work, result, handler.messages)
        _write(work, participant_outputs(participant), result, sidecar, began)
    except (OSError, ValueError, RuntimeError) as err:
        if work.verbose:
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
        verdict=None if result.verdict is None else result.verdict.line(),
        failed=result.verdict is not None and result.verdict.status == "failed",
    )


def _sidecar(
    work: ParticipantJob, result: ReconstructionResult, warnings: list[str]
) -> dict[str, Any]:
    """The derivative's provenance: inputs and their checksums, settings, what was kept."""
    job, participant = work.job, work.participant
    slices = result.slices
    excluded = {Path(name).name: ks for name, ks in excluded_by_stack(result).items()}
    names = [Path(n).name for n in slices.stack_names]
    model = None if job.model is None else {"name": job.model, "sha256": model_digest(job.model)}
    return {
        "Description": "Slice-to-volume reconstruction of the participant's T2w stacks",
        "Sources": [f"bids:raw:{s.relative}" for s in participant.stacks],
        "svr": {
            "subject": participant.subject,
            "session": participant.session,
            "command": list(work.command),
            "arguments": work.arguments,
            "software": environment(),
            "model": model,
            "gestational_age_weeks": work.weeks,
            "atlas": [
                {"volume": volume, "mask": mask, "volume_sha256": file_sha256(volume)}
                for volume, mask in job.atlases
            ]
            or None,
            "options": {
                **provenance(job),
                "mask_model": None if job.masks else job.mask_model,
                "thickness_mm": list(job.thicknesses or ()),
            },
            "inputs": [
                {
                    "file": s.relative,
                    "sha256": file_sha256(s.path),
                    "mask": None if s.mask is None else str(s.mask),
                    "mask_sha256": None if s.mask is None else file_sha256(s.mask),
                    "thickness_mm": t,
                }
                for s, t in zip(participant.stacks, job.thicknesses or (), strict=True)
            ],
            "initialisation": dict(zip(names, result.initialisation, strict=True)),
            "initialisation_notes": dict(zip(names, result.initialisation_notes, strict=False)),
            "slices": len(slices),
            "slices_excluded": int(result.excluded.sum()),
            "excluded_slices": excluded,
            "frame": slices.frame,
            "verdict": None
            if result.verdict is None
            else {
                "status": result.verdict.status,
                "frame": result.verdict.frame,
                "reasons": list(result.verdict.reasons),
                "line": result.verdict.line(),
            },
            "from_scanner": None if result.from_scanner is None else result.from_scanner.tolist(),
            "frame_margin": result.frame_margin,
            "atlas_margin": result.atlas_margin,
            "atlas_turn_deg": result.atlas_turn_deg,
            "atlas_turn_applied": result.atlas_turn_applied,
            "midplane_tilt_deg": result.midplane_tilt_deg,
            "mirror_correlation": result.mirror_correlation,
            "mirror_tilt_deg": result.mirror_tilt_deg,
            "atlas_ncc": list(result.atlas_ncc),
            "atlas_chosen": result.atlas_chosen,
            "rounds": len(result.rounds),
            "converged": result.converged,
            "timings_s": result.timings_s,
            "device": job.device,
            "threads": work.threads,
            "warnings": warnings,
        },
    }


def _write(
    work: ParticipantJob,
    names: ParticipantOutputs,
    result: ReconstructionResult,
    sidecar: dict[str, Any],
    began: float,
) -> None:
    """Write every derivative into a temporary folder, then move it into place."""
    from svr.files import atomic_directory
    from svr.reconstruction.outputs import write_transforms, write_volume
    from svr.reconstruction.qa import qa_figure

    target = work.output_dir / work.participant.folder
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_directory(target, overwrite=work.overwrite) as tmp:
        (tmp / "anat").mkdir()
        write_volume(result.volume, tmp / names.volume, verdict=result.verdict)
        write_volume(result.mask, tmp / names.mask)
        write_transforms(result, tmp / names.transforms)
        masks = sidecar["svr"]["options"]["masks"]
        labels = _tissue(work, names, result, tmp, sidecar)
        qa_figure(
            result,
            tmp / names.qa,
            notes=[work.participant.label, f"masks: {masks}"],
            labels=labels,
            label_colours=[label.colour for label in TISSUE_LABELS],
        )
        sidecar["svr"]["total_seconds"] = time.perf_counter() - began
        (tmp / names.sidecar).write_text(json.dumps(sidecar, indent=1) + "\n", encoding="utf-8")


def _tissue(
    work: ParticipantJob,
    names: ParticipantOutputs,
    result: ReconstructionResult,
    tmp: Path,
    sidecar: dict[str, Any],
) -> Image | None:
    """Label, measure and report the tissues (``--tissue-labels``) into ``tmp``; the labels.

    A failure (no age, the volume not in an atlas frame) is a warning (the sidecar's), not the
    participant's error; a reconstruction whose verdict is not ok (stamped in its volume) has its
    labels flagged, and labels not trusted are a warning too (both from
    :func:`~svr.apps.tissue.run_tissue`).
    """
    if not work.tissue_atlases:
        return None
    from svr.apps.tissue import TissueJob, run_tissue
    from svr.image import load_nifti

    if work.weeks is None:
        sidecar["svr"]["tissue"] = {"error": "no gestational age (--age-column)"}
        log.warning("tissue labels: no gestational age (--age-column)")
        return None
    job = TissueJob(
        input_volume=tmp / names.volume,
        atlas_dirs=tuple(Path(d) for d in work.tissue_atlases),
        weeks=work.weeks,
        output_labels=tmp / names.labels,
        output_report=tmp / names.report,
        output_measures=(tmp / names.measures, (tmp / names.measures).with_suffix(".json")),
        input_mask=tmp / names.mask,
    )
    try:
        outcome = run_tissue(job)
    except ValueError as err:
        message = " ".join(str(err).split()).replace(str(tmp) + "/", "")
        sidecar["svr"]["tissue"] = {"error": message}
        log.warning("tissue labels: %s", message)
        return None
    segmentation, biometry = outcome.segmentation, outcome.biometry
    sidecar["svr"]["tissue"] = {
        "trusted": segmentation.trusted,
        "problems": list(segmentation.problems),
        "atlases": [str(fit.path) for fit in segmentation.atlases],
        "suggested_age_weeks": outcome.suggested_age_weeks,
        "volumes_ml": biometry.volumes_ml,
        "measures_mm": {k: (v if v == v else None) for k, v in biometry.measures_mm.items()},
    }
    return load_nifti(tmp / names.labels)


def model_digest(name: str) -> str | None:
    """SHA-256 of the weights file of the model that ``--model`` names (``None`` if none)."""
    from svr.models.checkpoint import CHECKPOINT_WEIGHTS, latest_checkpoint, resolve_model_path
    from svr.models.pretrained import stack_pose_model_path
    from svr.models.stack_pose import STACK_POSE_MODEL

    folder = stack_pose_model_path() if name == STACK_POSE_MODEL else resolve_model_path(name)
    if not (folder / CHECKPOINT_WEIGHTS).is_file():
        folder = latest_checkpoint(folder) or folder
    weights = folder / CHECKPOINT_WEIGHTS
    return file_sha256(weights) if weights.is_file() else None
