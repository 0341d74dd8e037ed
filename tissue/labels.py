"""The tissue label set of the fetal brain atlases, and the structures built from it.

The spatio-temporal atlases the toolkit reads (Fidon 2021 spina bifida, Wu 2021 and Gholipour 2017
neurotypical, in the harmonised layout of the FeTA-style ``parcellation.nii.gz``) share one set
of eight labels; 0 is background. The set, its names and its colours live here and nowhere else.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "STRUCTURES",
    "TISSUE_LABELS",
    "TissueLabel",
    "label_names",
]


@dataclass(frozen=True)
class TissueLabel:
    """One tissue label.

    Attributes:
        value: The voxel value in a label map (1-8).
        key: Short machine name (column names in TSV/JSON).
        name: Name for people (reports).
        colour: Overlay colour, ``#rrggbb``.
    """

    value: int
    key: str
    name: str
    colour: str


TISSUE_LABELS: tuple[TissueLabel, ...] = (
    TissueLabel(1, "white_matter", "White matter", "#f5f5dc"),
    TissueLabel(2, "ventricles", "Ventricles (intra-axial CSF)", "#1f77b4"),
    TissueLabel(3, "cerebellum", "Cerebellum", "#ff7f0e"),
    TissueLabel(4, "extra_axial_csf", "Extra-axial CSF", "#17becf"),
    TissueLabel(5, "cortical_grey_matter", "Cortical grey matter", "#d62728"),
    TissueLabel(6, "deep_grey_matter", "Deep grey matter", "#2ca02c"),
    TissueLabel(7, "brainstem", "Brainstem", "#9467bd"),
    TissueLabel(8, "corpus_callosum", "Corpus callosum", "#e377c2"),
)
"""Labels 1-8 in value order (FeTA / Fidon 2021 convention: ``parcellation.nii.gz``)."""

STRUCTURES: dict[str, tuple[int, ...]] = {
    "intracranial": (1, 2, 3, 4, 5, 6, 7, 8),
    "brain_tissue": (1, 3, 5, 6, 7, 8),
    "cerebrum": (1, 2, 5, 6, 8),
}
"""Structures made of several labels: everything inside the skull (intracranial volume), the
brain's tissue (CSF spaces left out) and the cerebrum (hemispheres with their ventricles, without
cerebellum, brainstem and extra-axial CSF: the parenchyma the brain diameters measure)."""


def label_names() -> dict[int, str]:
    """Value -> key of every label, background included as ``0 -> "background"``."""
    return {0: "background", **{label.value: label.key for label in TISSUE_LABELS}}
