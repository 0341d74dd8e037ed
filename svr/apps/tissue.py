"""Tissue labels, volumes, biometry and a report of one reconstruction, from files.

:func:`run_tissue` is the one path from a :class:`TissueJob` to written outputs, shared by
``svr segment-volume`` and each participant of ``svr bids``: it segments the volume
(:func:`svr.tissue.segment.segment_volume`), measures the labels
(:func:`svr.tissue.biometry.measure_labels`) in the frame the best-fitting atlas says the volume
is in, reads the measures against the atlases' growth (:mod:`svr.tissue.growth`) and writes the
label map on the volume's own grid and header, the numbers (TSV and/or JSON), the HTML report and
the overlay figure, each atomically. Every output path is checked before any work.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, cast

import nibabel as nib

from svr.files import check_output_path
from svr.image import load_nifti, save_labels_like
from svr.stamp import read_stamp
from svr.tissue.biometry import Biometry, measure_labels
from svr.tissue.growth import growth_curves
from svr.tissue.labels import TISSUE_LABELS
from svr.tissue.report import (
    label_overlay_figure,
    measure_rows,
    report_data,
    write_html,
    write_json,
    write_png,
    write_tsv,
)
from svr.tissue.segment import (
    NotInAtlasFrameError,
    TissueConfig,
    TissueSegmentation,
    segment_volume,
)

__all__ = ["MEASURE_SUFFIXES", "TissueJob", "TissueOutcome", "run_tissue"]

log = logging.getLogger(__name__)

MEASURE_SUFFIXES = (".tsv", ".json")
"""The suffixes the numbers may be written as."""


@dataclass(frozen=True)
class TissueJob:
    """What one tissue segmentation reads and writes (picklable).

    Attributes:
        input_volume: The reconstruction (NIfTI, in an atlas frame).
        atlas_dirs: Atlas folders (``GA<weeks>*/{srr,mask,parcellation}.nii.gz``).
        weeks: The fetus's gestational age (weeks).
        output_labels: The label map to write (NIfTI).
        output_report: The HTML report, or ``None``.
        output_measures: ``.tsv`` and/or ``.json`` files of the numbers.
        output_qa: The overlay figure (``.png``), or ``None``.
        input_mask: The brain mask (NIfTI on the volume's grid), or ``None`` for the volume's
            nonzero voxels.
        config: How the labels are found.
        overwrite: Whether existing outputs may be replaced.
    """

    input_volume: Path
    atlas_dirs: tuple[Path, ...]
    weeks: float
    output_labels: Path
    output_report: Path | None = None
    output_measures: tuple[Path, ...] = ()
    output_qa: Path | None = None
    input_mask: Path | None = None
    config: TissueConfig = field(default_factory=TissueConfig)
    overwrite: bool = False

    def outputs(self) -> list[Path]:
        """Every file the job writes."""
        extra = [self.output_report, self.output_qa]
        return [self.output_labels, *self.output_measures, *(p for p in extra if p is not None)]


class TissueOutcome(NamedTuple):
    """What one tissue job found.

    Attributes:
        segmentation: The labels and how sure they are.
        biometry: The volumes and measures.
        suggested_age_weeks: The median of the ages the measures suggest (NaN if none).
        written: The files written.
    """

    segmentation: TissueSegmentation
    biometry: Biometry
    suggested_age_weeks: float
    written: list[Path]


def _check(job: TissueJob) -> None:
    if not (math.isfinite(job.weeks) and job.weeks > 0):
        raise ValueError(f"gestational age: must be a positive number of weeks, got {job.weeks}")
    for path in job.output_measures:
        if not str(path).endswith(MEASURE_SUFFIXES):
            raise ValueError(f"{path}: the numbers are written as .tsv or .json")
    if job.output_report is not None and job.output_report.suffix != ".html":
        raise ValueError(f"{job.output_report}: the report is written as .html")
    if job.output_qa is not None and job.output_qa.suffix != ".png":
        raise ValueError(f"{job.output_qa}: the overlay figure is written as .png")
    seen: set[Path] = set()
    for path in job.outputs():
        if path.resolve() in seen or path.resolve() == job.input_volume.resolve():
            raise ValueError(f"{path}: given twice (as an input or another output)")
        seen.add(path.resolve())
        check_output_path(path, job.overwrite)


def _reconstruction_problems(path: Path) -> list[str]:
    """Why the reconstruction's own verdict (stamped in its header) says not to trust it.

    Raises:
        NotInAtlasFrameError: If the stamp says the volume is in the scanner frame.
    """
    header = cast("nib.Nifti1Image", nib.load(str(path))).header
    stamp = read_stamp(header["descrip"].tobytes())
    if stamp is None or stamp.ok():
        return []
    if stamp.frame == "scanner":
        raise NotInAtlasFrameError(
            f"{path}: not in an atlas frame (svr reconstruct wrote it in the scanner frame); "
            "reconstruct it with --registration cnn and an --atlas-volume"
        )
    return [f"the reconstruction's verdict is {stamp.line()} (its log and QA page say why)"]


def run_tissue(job: TissueJob) -> TissueOutcome:
    """Segment, measure and report one reconstruction (module docstring).

    Args:
        job: The files and settings.

    Returns:
        What was found and written.

    Raises:
        ImageError: An input cannot be read (the message names it).
        NotInAtlasFrameError: The volume is not in an atlas frame.
        VolumeSourceError: An atlas folder is missing or incomplete.
        OutputExistsError: An output exists and ``overwrite`` is false.
        ValueError: A bad age, output name or mask.
    """
    _check(job)
    volume = load_nifti(job.input_volume)
    known = _reconstruction_problems(job.input_volume)
    mask = None
    if job.input_mask is not None:
        mask = load_nifti(job.input_mask).data.numpy() > 0.5
    name = str(job.input_volume)
    segmentation = segment_volume(volume, job.atlas_dirs, job.weeks, job.config, mask, name)
    if known:
        problems = [*known, *segmentation.problems]
        segmentation = segmentation._replace(problems=problems)
    for problem in segmentation.problems:
        log.warning("%s: labels not trusted: %s", name, problem)
    best = max(segmentation.atlases, key=lambda fit: fit.weight)
    affine = volume.affine.numpy()
    biometry = measure_labels(segmentation.labels, affine, best.rotation)
    written = [
        save_labels_like(segmentation.labels, job.input_volume, job.output_labels, job.overwrite)
    ]
    suggested = math.nan
    if job.output_measures or job.output_report is not None:
        curves = growth_curves(job.atlas_dirs)
        spread = {
            label.key: (
                min(v[label.value] for v in segmentation.atlas_volumes_ml),
                max(v[label.value] for v in segmentation.atlas_volumes_ml),
            )
            for label in TISSUE_LABELS
        }
        rows = measure_rows(biometry, job.weeks, curves, spread)
        case = {
            "input": name,
            "gestational_age_weeks": job.weeks,
            "atlases": [
                {
                    "path": str(fit.path),
                    "weeks": fit.weeks,
                    "rotation_deg": fit.rotation_deg,
                    "scale": fit.scale,
                    "ncc_affine": fit.ncc_affine,
                    "ncc": fit.ncc,
                    "weight": fit.weight,
                }
                for fit in segmentation.atlases
            ],
        }
        data = report_data(case, rows, segmentation.problems)
        suggested = data["suggested_age_weeks_median"] or math.nan
        for path in job.output_measures:
            if path.suffix == ".tsv":
                written.append(write_tsv(path, rows, job.overwrite))
            else:
                written.append(write_json(path, data, job.overwrite))
        if job.output_report is not None:
            figure = label_overlay_figure(
                volume.data.numpy(), segmentation.labels, affine, segmentation.agreement
            )
            written.append(write_html(job.output_report, data, rows, figure, curves, job.overwrite))
    if job.output_qa is not None:
        figure = label_overlay_figure(
            volume.data.numpy(), segmentation.labels, affine, segmentation.agreement
        )
        written.append(write_png(job.output_qa, figure, job.overwrite))
    log.info(
        "%s: labels %s; wrote %s",
        name,
        "trusted" if segmentation.trusted else "NOT trusted",
        ", ".join(str(p) for p in written),
    )
    return TissueOutcome(segmentation, biometry, float(suggested), written)
