"""``svr segment-volume``: tissue labels, volumes, biometry and a report of a reconstruction."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from svr.cli.common import HelpFormatter, add_verbosity_options, positive_float, positive_int

DESCRIPTION = """\
Label the tissues of a reconstruction, measure them and write a report. The volume must be in an
atlas frame: the output of `svr reconstruct --registration cnn` with an --atlas-volume (a
volume left in the scanner frame is refused with one line). The atlases of the ages nearest the
fetus's (--gestational-age; within --window-weeks, at most --max-atlases) are each registered
to the volume (SimpleITK: affine, then demons), and their labels are fused voxel by voxel,
weighted by how well each atlas matches the volume around that voxel, within the atlases'
brains after the affine step (a loose brain mask is not filled with tissue). The labels are those of
the atlases' parcellation.nii.gz: 1 white matter, 2 ventricles, 3 cerebellum, 4 extra-axial
CSF, 5 cortical grey matter, 6 deep grey matter, 7 brainstem, 8 corpus callosum; they are
written as uint8 on the volume's own grid with its header.

An atlas folder holds one GA<weeks>*/ subfolder per age with srr.nii.gz, mask.nii.gz and
parcellation.nii.gz (the layout of the Fidon 2021 spina bifida atlas and of the neurotypical
atlases of the same source; see the documentation, "Tissue labels and biometry", for where to
get them). Give the family that matches the fetus (neurotypical or spina bifida).

The numbers (--output-measures, .tsv and/or .json) are every label's volume, the intracranial,
brain-tissue and cerebrum volumes, and the brain biparietal and fronto-occipital diameters, the
transverse cerebellar diameter, the atrial width of each lateral ventricle and the corpus
callosum length, each beside the atlas ages' mean at the fetus's age and the age the value
suggests on the atlas's growth curve (an atlas is a mean brain, not a normative centile). The
HTML report (--output-report) shows the overlay in the three planes, where the atlases
disagree and the measures against the atlas ages. Labels that cannot be trusted are written
with a warning, and the report and the JSON say why: the atlases fit the volume poorly or
disagree, or the reconstruction's own verdict (which svr reconstruct stamps in the volume's
header) is not "ok, frame trusted".

examples:
  svr segment-volume --input-volume recon.nii.gz --atlas-dir atlases/Neurotypical_Wu2021 \\
      --gestational-age 28 --output-labels recon_dseg.nii.gz --output-report recon_tissue.html
  svr segment-volume --input-volume recon.nii.gz --atlas-dir atlases/sb-fidon2021 \\
      --gestational-age 26.5 --output-labels dseg.nii.gz --output-measures tissue.tsv \\
      tissue.json --output-qa tissue.png --threads 2
"""

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr segment-volume``."""
    p = subparsers.add_parser(
        "segment-volume",
        help="tissue labels, volumes, biometry and a report of a reconstruction (atlases, CPU)",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument("--input-volume", required=True, metavar="VOLUME", help="the reconstruction")
    p.add_argument(
        "--atlas-dir",
        nargs="+",
        required=True,
        metavar="DIR",
        help="atlas folders of GA<weeks>*/{srr,mask,parcellation}.nii.gz",
    )
    p.add_argument(
        "--gestational-age",
        required=True,
        type=positive_float,
        metavar="WEEKS",
        help="the fetus's gestational age (weeks)",
    )
    p.add_argument("--output-labels", required=True, metavar="FILE", help="label map (.nii.gz)")
    p.add_argument("--output-report", metavar="FILE", help="HTML report (.html)")
    p.add_argument(
        "--output-measures",
        nargs="+",
        default=[],
        metavar="FILE",
        help="the volumes and measures (.tsv and/or .json)",
    )
    p.add_argument("--output-qa", metavar="FILE", help="label overlay figure (.png)")
    p.add_argument(
        "--input-mask",
        metavar="MASK",
        help="brain mask on the volume's grid (default: the volume's nonzero voxels)",
    )
    p.add_argument(
        "--window-weeks",
        type=float,
        default=1.0,
        metavar="WEEKS",
        help="use the atlas ages within this many weeks of the fetus's",
    )
    p.add_argument(
        "--max-atlases", type=positive_int, default=3, metavar="N", help="use at most N atlases"
    )
    p.add_argument(
        "--threads",
        type=positive_int,
        default=None,
        metavar="N",
        help="CPU threads of the registrations (default: all cores)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_verbosity_options(p)


def run(args: argparse.Namespace) -> int:
    """Run ``svr segment-volume``."""
    import SimpleITK as sitk  # noqa: N813 (the usual alias)

    from svr.apps.tissue import TissueJob, run_tissue
    from svr.tissue.segment import TissueConfig

    if args.threads is not None:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(args.threads)
    optional = lambda value: None if value is None else Path(value)  # noqa: E731
    job = TissueJob(
        input_volume=Path(args.input_volume),
        atlas_dirs=tuple(Path(d) for d in args.atlas_dir),
        weeks=args.gestational_age,
        output_labels=Path(args.output_labels),
        output_report=optional(args.output_report),
        output_measures=tuple(Path(p) for p in args.output_measures),
        output_qa=optional(args.output_qa),
        input_mask=optional(args.input_mask),
        config=TissueConfig(window_weeks=args.window_weeks, max_atlases=args.max_atlases),
        overwrite=args.overwrite,
    )
    outcome = run_tissue(job)
    volumes = outcome.biometry.volumes_ml
    verdict = (
        "trusted"
        if outcome.segmentation.trusted
        else "NOT TRUSTED: " + "; ".join(outcome.segmentation.problems)
    )
    print(
        f"wrote {', '.join(str(p) for p in outcome.written)}: intracranial "
        f"{volumes['intracranial']:.1f} mL, brain tissue {volumes['brain_tissue']:.1f} mL; "
        f"labels {verdict}"
    )
    return 0
