"""The atlases' own growth: each measure over the atlas ages, and the age a case's values suggest.

An atlas age is the mean brain of a few fetuses of that week; its volumes and measures are taken
with the same code as a case's (:func:`svr.tissue.biometry.measure_labels` on its
``parcellation.nii.gz``). A quadratic in the age is fitted to each measure over the ages of an
atlas folder (least squares: neighbouring ages of a small atlas jump), and a case's value is read
back on the fitted curve as the age it suggests. These are atlas means, not normative centiles:
a value between two ages' means says nothing about how unusual it is.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from svr.image import load_nifti
from svr.sampling.volume import atlas_labels_path, atlas_volume_paths
from svr.tissue.biometry import Biometry, measure_labels

__all__ = ["GrowthCurve", "atlas_biometry", "growth_curves", "suggested_age"]

AGE_MARGIN_WEEKS = 2.0
"""How far beyond the atlas's ages a curve is read (weeks)."""


class GrowthCurve(NamedTuple):
    """One measure over an atlas's ages.

    Attributes:
        key: The measure or volume key.
        ages: (N,) the atlas ages (weeks).
        values: (N,) the measure at each age (mL or mm).
        coefficients: The fitted quadratic's coefficients (``numpy.polyval`` order).
    """

    key: str
    ages: np.ndarray
    values: np.ndarray
    coefficients: np.ndarray

    def at(self, weeks: float | np.ndarray) -> np.ndarray:
        """The fitted curve at ``weeks``."""
        return np.polyval(self.coefficients, weeks)


@lru_cache(maxsize=64)
def _measure_atlas(parcellation: str) -> Biometry:
    image = load_nifti(parcellation)
    return measure_labels(image.data.numpy().round().astype(np.int64), image.affine.numpy())


def atlas_biometry(folder: str | os.PathLike[str]) -> list[tuple[float, Biometry]]:
    """``(weeks, biometry)`` of every age of an atlas folder, by age (kept for the session)."""
    out = []
    for volume, _ in atlas_volume_paths(folder):
        weeks = float(Path(volume).parent.name[2:4])
        out.append((weeks, _measure_atlas(str(atlas_labels_path(volume)))))
    out.sort(key=lambda entry: entry[0])
    return out


def growth_curves(folders: Sequence[str | os.PathLike[str]]) -> dict[str, GrowthCurve]:
    """A curve per volume and measure over the ages of the atlas folders (pooled).

    Args:
        folders: Atlas folders (``GA<weeks>*/parcellation.nii.gz``).

    Returns:
        Key -> curve (a measure NaN at some age is fitted over the others; one with fewer
        than 3 ages is left out).
    """
    rows = [entry for folder in folders for entry in atlas_biometry(folder)]
    curves: dict[str, GrowthCurve] = {}
    if not rows:
        return curves
    keys = [*rows[0][1].volumes_ml, *rows[0][1].measures_mm]
    for key in keys:
        ages = np.array([weeks for weeks, _ in rows])
        values = np.array(
            [{**bio.volumes_ml, **bio.measures_mm}[key] for _, bio in rows], dtype=np.float64
        )
        finite = np.isfinite(values)
        if finite.sum() < 3:
            continue
        coefficients = np.polyfit(ages[finite], values[finite], 2)
        curves[key] = GrowthCurve(key, ages[finite], values[finite], coefficients)
    return curves


def suggested_age(curve: GrowthCurve, value: float) -> float:
    """The age (weeks) at which the fitted curve is nearest ``value``.

    Read within the atlas's ages +- :data:`AGE_MARGIN_WEEKS`; NaN for a NaN value or a curve that
    does not grow.
    """
    if not math.isfinite(value):
        return math.nan
    weeks = np.linspace(
        curve.ages.min() - AGE_MARGIN_WEEKS, curve.ages.max() + AGE_MARGIN_WEEKS, 801
    )
    fitted = curve.at(weeks)
    if fitted[-1] <= fitted[0]:
        return math.nan
    return float(weeks[int(np.argmin(np.abs(fitted - value)))])
