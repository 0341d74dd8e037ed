"""Cohorts as BIDS datasets: which stacks each participant has, where the derivatives go.

The library side of ``svr bids`` (a BIDS App: ``svr bids BIDS_DIR OUTPUT_DIR participant|group``).
The dataset is read with pybids (:class:`bids.BIDSLayout`), never by parsing paths by hand:

* :func:`find_participants`: every T2w stack (``anat``, ``.nii``/``.nii.gz``, no ``desc``
  entity) of each subject and session, with its brain mask from a derivatives folder
  (``desc-brain_mask``, the same entities as the stack) when one is given and its slice thickness
  from the JSON sidecar (``SliceThickness``) when it has one. Every problem a user can cause is a
  :class:`BidsError` with a one-line message, raised before anything is written.
* :func:`participant_outputs` names the derivatives of one participant (and session):
  ``sub-XX[/ses-YY]/anat/sub-XX[_ses-YY]_rec-svr_T2w.nii.gz``, its brain mask
  (``_rec-svr_desc-brain_mask.nii.gz``), the slice transforms (``_rec-svr_transforms.csv``), the
  quality figure (``_rec-svr_qa.png``) and the JSON sidecar with the provenance
  (``_rec-svr_T2w.json``). The participant's folder (``sub-XX``, or ``sub-XX/ses-YY``) is built
  in a temporary sibling and moved into place when complete (:func:`svr.files.atomic_directory`),
  so a job killed half-way leaves no partial derivative, and a folder that exists is a finished
  participant.
* :func:`write_dataset_description`: ``dataset_description.json`` with ``GeneratedBy``.

The group level is :mod:`svr.apps.bids_group`.
"""

from __future__ import annotations

import csv
import json
import math
import os
import platform
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from svr import __version__
from svr.files import atomic_write_text

__all__ = [
    "BidsError",
    "BidsStack",
    "Participant",
    "ParticipantOutputs",
    "check_output_dir",
    "find_participants",
    "participant_age",
    "participant_outputs",
    "write_dataset_description",
]

PIPELINE = "fetal-svr"
"""The ``GeneratedBy`` name of the derivatives."""

_NIFTI = [".nii", ".nii.gz"]
_MATCHED = ("session", "acquisition", "run", "reconstruction", "direction")
"""Entities a stack's brain mask must share with it (absent on the stack: absent on the mask)."""


class BidsError(ValueError):
    """A problem with the BIDS input or the output folder, worded for the command line."""


@dataclass(frozen=True)
class BidsStack:
    """One T2w stack of a participant.

    Attributes:
        path: The stack (NIfTI).
        mask: Its brain mask from the masks folder, or ``None`` (an automatic mask).
        thickness_mm: ``SliceThickness`` from its JSON sidecar (mm), or ``None``.
        relative: The stack's path relative to the dataset, for provenance.
    """

    path: Path
    mask: Path | None
    thickness_mm: float | None
    relative: str


@dataclass(frozen=True)
class Participant:
    """The stacks of one subject (and session) that are reconstructed together.

    Attributes:
        subject: The subject label, without ``sub-``.
        session: The session label without ``ses-``, or ``None``.
        stacks: The T2w stacks, in the dataset's order (by file name).
    """

    subject: str
    session: str | None
    stacks: tuple[BidsStack, ...] = field(default_factory=tuple)

    @property
    def label(self) -> str:
        """``sub-XX`` or ``sub-XX_ses-YY``: the prefix of the derivatives' file names."""
        return f"sub-{self.subject}" + (f"_ses-{self.session}" if self.session else "")

    @property
    def folder(self) -> Path:
        """``sub-XX`` or ``sub-XX/ses-YY``: the unit that is written atomically."""
        base = Path(f"sub-{self.subject}")
        return base / f"ses-{self.session}" if self.session else base


@dataclass(frozen=True)
class ParticipantOutputs:
    """The derivatives of one participant, relative to the participant's folder.

    Attributes:
        volume: The reconstruction.
        mask: Its brain mask.
        transforms: The slices' poses and quality.
        qa: The quality figure.
        sidecar: The JSON sidecar (provenance).
        labels: The tissue labels (``--tissue-labels``).
        measures: The tissue volumes and measures (TSV; a JSON beside with the suffix changed).
        report: The tissue report (HTML).
    """

    volume: Path
    mask: Path
    transforms: Path
    qa: Path
    sidecar: Path
    labels: Path
    measures: Path
    report: Path


def participant_outputs(participant: Participant) -> ParticipantOutputs:
    """The derivative file names of a participant (relative to :attr:`Participant.folder`)."""
    stem = f"anat/{participant.label}_rec-svr"
    return ParticipantOutputs(
        volume=Path(f"{stem}_T2w.nii.gz"),
        mask=Path(f"{stem}_desc-brain_mask.nii.gz"),
        transforms=Path(f"{stem}_transforms.csv"),
        qa=Path(f"{stem}_qa.png"),
        sidecar=Path(f"{stem}_T2w.json"),
        labels=Path(f"{stem}_dseg.nii.gz"),
        measures=Path(f"{stem}_desc-tissue_measures.tsv"),
        report=Path(f"{stem}_desc-tissue_report.html"),
    )


def _layout(root: Path, validate: bool, derivative: bool = False) -> Any:
    """A pybids layout of ``root`` (imported here: pybids takes a second to import)."""
    from bids import BIDSLayout
    from bids.exceptions import BIDSValidationError

    try:
        return BIDSLayout(root, validate=validate, is_derivative=derivative)
    except BIDSValidationError as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise BidsError(
            f"{root}: not a BIDS dataset ({first.rstrip('.')}); --skip-bids-validation reads it "
            "anyway"
        ) from err
    except ValueError as err:
        raise BidsError(f"{root}: {err}") from err


def check_output_dir(bids_dir: str | os.PathLike[str], output_dir: str | os.PathLike[str]) -> None:
    """Refuse an output folder inside the input dataset (or the dataset itself).

    Raises:
        BidsError: If ``output_dir`` is ``bids_dir`` or lies inside it.
    """
    source, out = Path(bids_dir).resolve(), Path(output_dir).resolve()
    if out == source or source in out.parents:
        raise BidsError(
            f"OUTPUT_DIR {output_dir}: inside the input dataset {bids_dir}; give a folder outside "
            "it (e.g. next to it)"
        )


def participant_age(
    bids_dir: str | os.PathLike[str], participant: Participant, column: str
) -> float:
    """A participant's gestational age (weeks) from the dataset's tables.

    The session's row of ``sub-XX/sub-XX_sessions.tsv`` (``session_id`` ``ses-YY``) where the
    participant has a session and that table has the column; else the subject's row of
    ``participants.tsv`` (``participant_id`` ``sub-XX``).

    Args:
        bids_dir: The BIDS dataset.
        participant: The participant.
        column: The column holding gestational ages in weeks.

    Returns:
        The age (weeks, > 0).

    Raises:
        BidsError: Naming the file, for a missing table, column or row, or a value that is not a
            positive number.
    """
    root = Path(bids_dir)
    subject = f"sub-{participant.subject}"
    path, key, wanted = root / "participants.tsv", "participant_id", subject
    if participant.session:
        sessions = root / subject / f"{subject}_sessions.tsv"
        if column in _tsv(sessions)[0]:
            path, key, wanted = sessions, "session_id", f"ses-{participant.session}"
    if not path.is_file():
        raise BidsError(f"{path}: no such file (--age-column {column} is read from it)")
    header, rows = _tsv(path)
    for name in (column, key):
        if name not in header:
            raise BidsError(f"{path}: no column {name!r} (--age-column {column})")
    row = next((r for r in rows if r[key] == wanted), None)
    if row is None:
        raise BidsError(f"{path}: no row for {wanted}")
    text = (row[column] or "").strip()
    try:
        weeks = float(text)
    except ValueError:
        weeks = math.nan
    if not (math.isfinite(weeks) and weeks > 0):
        raise BidsError(f"{path}: {wanted}'s {column} is {text!r}, not a gestational age in weeks")
    return weeks


def _tsv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """A TSV file's column names and rows; none of either where the file does not exist."""
    if not path.is_file():
        return [], []
    with path.open(newline="", encoding="utf-8") as file:
        reader = csv.DictReader(file, delimiter="\t")
        rows = list(reader)
        return list(reader.fieldnames or []), rows


def find_participants(
    bids_dir: str | os.PathLike[str],
    participant_labels: Sequence[str] | None = None,
    session_labels: Sequence[str] | None = None,
    masks_dir: str | os.PathLike[str] | None = None,
    validate: bool = True,
) -> list[Participant]:
    """The participants (subject and session) to reconstruct, with their stacks and masks.

    Args:
        bids_dir: The BIDS dataset.
        participant_labels: Subjects to take (with or without ``sub-``); ``None`` for all.
        session_labels: Sessions to take (with or without ``ses-``); ``None`` for all.
        masks_dir: A derivatives folder of brain masks (``desc-brain_mask``), or ``None``.
        validate: Require a valid dataset (``dataset_description.json``).

    Returns:
        One :class:`Participant` per subject and session, ordered by label.

    Raises:
        BidsError: For a folder that is not a BIDS dataset, an unknown participant or session
            label, a participant with no T2w stack, or masks that do not match the stacks one
            to one.
    """
    root = Path(bids_dir)
    if not root.is_dir():
        raise BidsError(f"BIDS_DIR {bids_dir}: no such folder")
    layout = _layout(root, validate)
    subjects = sorted(layout.get_subjects())
    if not subjects:
        raise BidsError(f"BIDS_DIR {bids_dir}: no sub-* folder; is it a BIDS dataset?")
    if participant_labels:
        wanted = [label.removeprefix("sub-") for label in participant_labels]
        unknown = [label for label in wanted if label not in subjects]
        if unknown:
            raise BidsError(
                f"--participant-label {' '.join(unknown)}: no such participant in {bids_dir} "
                f"(it has {', '.join(subjects)})"
            )
        subjects = list(dict.fromkeys(wanted))
    sessions_wanted = None
    if session_labels:
        sessions_wanted = [label.removeprefix("ses-") for label in session_labels]
        known = set(layout.get_sessions())
        unknown = [label for label in sessions_wanted if label not in known]
        if unknown:
            raise BidsError(
                f"--session-label {' '.join(unknown)}: no such session in {bids_dir}"
                + (f" (it has {', '.join(sorted(known))})" if known else " (it has none)")
            )
    mask_folder = None if masks_dir is None else Path(masks_dir)
    masks = None if mask_folder is None else _masks_layout(mask_folder)
    out = []
    for subject in subjects:
        sessions = sorted(layout.get_sessions(subject=subject)) or [None]
        if sessions_wanted is not None:
            sessions = [s for s in sessions if s in sessions_wanted]
            if not sessions:
                continue
        for session in sessions:
            files = layout.get(
                subject=subject,
                session=session,
                datatype="anat",
                suffix="T2w",
                extension=_NIFTI,
                desc=None,
                invalid_filters="allow",
            )
            label = f"sub-{subject}" + (f"_ses-{session}" if session else "")
            if not files:
                raise BidsError(f"{label}: no T2w stack (anat/*_T2w.nii[.gz]) in {bids_dir}")
            files = sorted(files, key=lambda f: f.path)
            found = []
            if masks is not None and mask_folder is not None:
                found = [_mask_for(masks, f, label, mask_folder) for f in files]
                _check_mask_count(masks, subject, session, label, len(files), mask_folder)
            stacks = tuple(
                BidsStack(
                    path=Path(f.path),
                    mask=found[i] if found else None,
                    thickness_mm=_thickness(layout.get_metadata(f.path), f.path),
                    relative=Path(f.path).relative_to(root.resolve()).as_posix()
                    if Path(f.path).is_relative_to(root.resolve())
                    else f.path,
                )
                for i, f in enumerate(files)
            )
            out.append(Participant(subject, session, stacks))
    if not out:
        raise BidsError(f"{bids_dir}: no participant has the sessions asked for")
    return out


def _masks_layout(folder: Path) -> Any:
    if not folder.is_dir():
        raise BidsError(f"--masks-dir {folder}: no such folder")
    return _layout(folder, validate=False, derivative=True)


def _mask_query(subject: str, session: str | None) -> dict[str, Any]:
    return {
        "subject": subject,
        "session": session,
        "desc": "brain",
        "suffix": "mask",
        "extension": _NIFTI,
        "invalid_filters": "allow",
    }


def _mask_for(masks: Any, stack: Any, label: str, folder: Path) -> Path:
    """The brain mask with the stack's entities, exactly one."""
    entities = stack.get_entities()
    query = _mask_query(entities["subject"], entities.get("session"))
    query.update({key: entities.get(key) for key in _MATCHED if key != "session"})
    found = masks.get(**query)
    if len(found) != 1:
        what = "no brain mask" if not found else f"{len(found)} brain masks"
        raise BidsError(
            f"--masks-dir {folder}: {what} (desc-brain_mask) for {Path(stack.path).name} of {label}"
        )
    return Path(found[0].path)


def _check_mask_count(
    masks: Any, subject: str, session: str | None, label: str, stacks: int, folder: Path
) -> None:
    count = len(masks.get(**_mask_query(subject, session)))
    if count != stacks:
        raise BidsError(
            f"--masks-dir {folder}: {label} has {count} brain masks for {stacks} T2w stacks; "
            "give one per stack or none"
        )


def _thickness(metadata: dict[str, Any], path: str) -> float | None:
    value = metadata.get("SliceThickness")
    if value is None:
        return None
    try:
        thickness = float(value)
    except (TypeError, ValueError) as err:
        raise BidsError(f"{path}: sidecar SliceThickness {value!r} is not a number") from err
    if not thickness > 0:
        raise BidsError(f"{path}: sidecar SliceThickness must be > 0, got {value!r}")
    return thickness


def write_dataset_description(
    output_dir: str | os.PathLike[str], bids_dir: str | os.PathLike[str]
) -> Path:
    """Write (or refresh) the derivatives' ``dataset_description.json`` with ``GeneratedBy``."""
    description = {
        "Name": "fetal-svr slice-to-volume reconstructions",
        "BIDSVersion": "1.9.0",
        "DatasetType": "derivative",
        "GeneratedBy": [
            {
                "Name": PIPELINE,
                "Version": __version__,
                "Description": "Fetal MRI slice-to-volume reconstruction (svr bids)",
            }
        ],
        "SourceDatasets": [{"URL": Path(bids_dir).resolve().as_uri()}],
    }
    return atomic_write_text(
        Path(output_dir) / "dataset_description.json",
        json.dumps(description, indent=2) + "\n",
        overwrite=True,
    )


def environment() -> dict[str, str]:
    """The software a derivative was made with (for the provenance)."""
    import torch

    return {
        "fetal-svr": __version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "platform": platform.platform(),
    }
