"""The tissue stage: labels, regional volumes, biometry and a report of a reconstruction.

It runs after reconstruction, on a volume in an atlas frame (``svr reconstruct --registration
cnn``)::

    from svr.image import load_nifti
    from svr.tissue import measure_labels, segment_volume

    volume = load_nifti("recon.nii.gz")
    result = segment_volume(volume, ["atlas-wu/"], weeks=28.0)
    best = max(result.atlases, key=lambda fit: fit.weight)
    biometry = measure_labels(result.labels, volume.affine.numpy(), best.rotation)

Homes:

* :mod:`svr.tissue.labels`: the atlases' label set, its names and colours, the structures;
* :mod:`svr.tissue.segment`: :func:`segment_volume`, multi-atlas segmentation and its verdict;
* :mod:`svr.tissue.registration`: an atlas registered to the volume (SimpleITK: affine, demons);
* :mod:`svr.tissue.fusion`: the atlases' labels fused by locally weighted voting;
* :mod:`svr.tissue.biometry`: volumes and linear measures of a label map in the atlas frame;
* :mod:`svr.tissue.growth`: the atlas ages' curves and the age a value suggests;
* :mod:`svr.tissue.report`: the HTML report, the TSV/JSON numbers, the overlay figure;
* :mod:`svr.tissue.sitk_images`: arrays with RAS affines to and from SimpleITK images.

It reads files of the core and :mod:`svr.sampling` (atlas folders) only; nothing below it imports
it. ``svr segment-volume`` and ``svr bids --tissue-labels`` run it through
:func:`svr.apps.tissue.run_tissue`.
"""

from __future__ import annotations

from svr.tissue.biometry import LINEAR_MEASURES, Biometry, measure_labels
from svr.tissue.growth import GrowthCurve, growth_curves, suggested_age
from svr.tissue.labels import STRUCTURES, TISSUE_LABELS, TissueLabel
from svr.tissue.segment import (
    NotInAtlasFrameError,
    TissueConfig,
    TissueSegmentation,
    segment_volume,
)

__all__ = [
    "LINEAR_MEASURES",
    "STRUCTURES",
    "TISSUE_LABELS",
    "Biometry",
    "GrowthCurve",
    "NotInAtlasFrameError",
    "TissueConfig",
    "TissueLabel",
    "TissueSegmentation",
    "growth_curves",
    "measure_labels",
    "segment_volume",
    "suggested_age",
]
