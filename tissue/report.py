"""A tissue report a clinician can read: one self-contained HTML page, and its numbers as JSON/TSV.

The page shows the verdict (and why the labels are not to be trusted when they are not), the
label overlay in the three standard planes, where the atlases disagree, every volume and linear
measure beside the atlas ages' growth (plots: the atlas ages' values, the fitted curve, the case
at its gestational age), and a table with the atlas mean at that age and the age each value
suggests. Figures are matplotlib (Agg), embedded as PNG, so the page is one file.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from svr.files import atomic_write_bytes, atomic_write_text
from svr.tissue.biometry import LINEAR_MEASURES, Biometry, atlas_aligned
from svr.tissue.growth import GrowthCurve, suggested_age
from svr.tissue.labels import STRUCTURES, TISSUE_LABELS

__all__ = [
    "CAVEAT",
    "label_overlay_figure",
    "measure_rows",
    "report_data",
    "write_html",
    "write_json",
    "write_png",
    "write_tsv",
]

CAVEAT = (
    "Atlas ages are the mean brains of a few fetuses of each week: the curves are not normative "
    "centiles, and an age suggested by one measure says how the brain compares with the atlas, "
    "not whether it is normal."
)
_PLANES = ("sagittal", "coronal", "axial")


def measure_rows(
    biometry: Biometry,
    weeks: float,
    curves: Mapping[str, GrowthCurve],
    atlas_spread: Mapping[str, tuple[float, float]] | None = None,
) -> list[dict[str, Any]]:
    """One row per volume and measure: value, atlas mean at ``weeks``, suggested age, spread.

    Args:
        biometry: The case's volumes and measures.
        weeks: Its gestational age.
        curves: The atlases' growth curves by key.
        atlas_spread: Key -> (low, high) of the value each atlas alone gives (volumes).

    Returns:
        Rows with ``key``, ``name``, ``value``, ``unit``, ``atlas_mean_at_age``,
        ``suggested_age_weeks``, ``atlas_low``, ``atlas_high`` (NaN where not known).
    """
    names = {label.key: label.name for label in TISSUE_LABELS}
    names.update(
        intracranial="Intracranial (all labels)",
        brain_tissue="Brain tissue (no CSF)",
        cerebrum="Cerebrum (hemispheres and ventricles)",
    )
    names.update(LINEAR_MEASURES)
    rows = []
    values = [(key, value, "mL") for key, value in biometry.volumes_ml.items()]
    values += [(key, value, "mm") for key, value in biometry.measures_mm.items()]
    for key, value, unit in values:
        curve = curves.get(key)
        low, high = (atlas_spread or {}).get(key, (math.nan, math.nan))
        rows.append(
            {
                "key": key,
                "name": names.get(key, key),
                "value": float(value),
                "unit": unit,
                "atlas_mean_at_age": float(curve.at(weeks)) if curve is not None else math.nan,
                "suggested_age_weeks": suggested_age(curve, value)
                if curve is not None
                else math.nan,
                "atlas_low": float(low),
                "atlas_high": float(high),
            }
        )
    return rows


def report_data(
    case: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], problems: Sequence[str]
) -> dict[str, Any]:
    """The report's numbers as one JSON-ready dict (NaN written as ``null``)."""

    def clean(value: Any) -> Any:
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [clean(v) for v in value]
        return value

    ages = [r["suggested_age_weeks"] for r in rows if math.isfinite(r["suggested_age_weeks"])]
    return clean(
        {
            **case,
            "trusted": not problems,
            "problems": list(problems),
            "suggested_age_weeks_median": float(np.median(ages)) if ages else math.nan,
            "caveat": CAVEAT,
            "measures": [dict(r) for r in rows],
        }
    )


def write_tsv(
    path: str | os.PathLike[str], rows: Sequence[Mapping[str, Any]], overwrite: bool
) -> Path:
    """The rows as a tab-separated table (``n/a`` for NaN, as BIDS writes it), atomically."""
    columns = list(rows[0]) if rows else ["key"]

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return "n/a" if not math.isfinite(value) else f"{value:.4g}"
        return str(value)

    lines = ["\t".join(columns)] + ["\t".join(cell(r[c]) for c in columns) for r in rows]
    return atomic_write_text(path, "\n".join(lines) + "\n", overwrite)


def _png_bytes(figure: Figure) -> bytes:
    buffer = io.BytesIO()
    FigureCanvasAgg(figure).print_png(buffer)
    return buffer.getvalue()


def _png(figure: Figure) -> str:
    return base64.b64encode(_png_bytes(figure)).decode("ascii")


def write_png(path: str | os.PathLike[str], figure: Figure, overwrite: bool = False) -> Path:
    """A figure as a PNG file, atomically."""
    return atomic_write_bytes(path, _png_bytes(figure), overwrite)


def label_overlay_figure(
    volume: np.ndarray, labels: np.ndarray, affine: np.ndarray, agreement: np.ndarray | None = None
) -> Figure:
    """The labels over the volume in the three standard planes (and the atlases' agreement).

    The planes are those of the atlas frame (the volume's world axes) through the brain's centre.

    Args:
        volume: (I, J, K) the reconstruction.
        labels: (I, J, K) its labels.
        affine: (4, 4) voxel-to-world (RAS).
        agreement: (I, J, K) fraction of the atlases that chose each voxel's label, or ``None``.

    Returns:
        The figure: the volume, the overlay and (with ``agreement``) where the atlases disagree.
    """
    brain = labels > 0
    top = float(np.percentile(volume[brain], 99.5)) if brain.any() else 1.0
    grey = np.clip(volume / max(top, 1e-6), 0, 1).astype(np.float32)
    arrays = [labels, grey] + ([1.0 - agreement] if agreement is not None else [])
    aligned, _ = atlas_aligned(arrays, affine)
    i, j, k = (round(float(c)) for c in np.argwhere(aligned[0] > 0).mean(0))
    views = [[a[i, :, :].T, a[:, j, :].T, a[:, :, k].T] for a in aligned]
    rows = len(aligned)
    figure = Figure(figsize=(10, 3.3 * rows))
    colours = ListedColormap(["#000000", *(label.colour for label in TISSUE_LABELS)])
    for column, name in enumerate(_PLANES):
        for row in range(rows):
            axes = figure.add_subplot(rows, 3, 3 * row + column + 1)
            axes.imshow(views[1][column], cmap="gray", origin="lower", vmin=0, vmax=1)
            axes.set_axis_off()
            if row == 0:
                axes.set_title(name)
            elif row == 1:
                shown = np.ma.masked_equal(views[0][column], 0)
                axes.imshow(
                    shown,
                    cmap=colours,
                    origin="lower",
                    vmin=0,
                    vmax=8,
                    alpha=0.45,
                    interpolation="nearest",
                )
            else:
                shown = np.ma.masked_less(views[2][column], 0.01)
                axes.imshow(shown, cmap="autumn_r", origin="lower", vmin=0, vmax=0.7, alpha=0.8)
                if column == 0:
                    axes.set_title("where the atlases disagree", loc="left", fontsize=9)
    figure.tight_layout()
    return figure


def _curves_figure(
    rows: Sequence[Mapping[str, Any]], curves: Mapping[str, GrowthCurve], weeks: float
) -> Figure:
    keys = [r for r in rows if r["key"] in curves]
    columns = 4
    lines = max(1, math.ceil(len(keys) / columns))
    figure = Figure(figsize=(12, 2.6 * lines))
    for index, row in enumerate(keys):
        curve = curves[row["key"]]
        axes = figure.add_subplot(lines, columns, index + 1)
        grid = np.linspace(curve.ages.min(), curve.ages.max(), 100)
        axes.plot(curve.ages, curve.values, "o", color="0.6", markersize=3, label="atlas ages")
        axes.plot(grid, curve.at(grid), "-", color="0.3", linewidth=1, label="atlas fit")
        axes.plot([weeks], [row["value"]], "*", color="#d62728", markersize=11, label="this case")
        axes.set_title(f"{row['name']} ({row['unit']})", fontsize=8)
        axes.tick_params(labelsize=7)
        axes.set_xlabel("gestational age (weeks)", fontsize=7)
    if keys:
        figure.axes[0].legend(fontsize=6, loc="upper left")
    figure.tight_layout()
    return figure


def _number(value: float, digits: int = 1) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.{digits}f}"


def write_html(
    path: str | os.PathLike[str],
    data: Mapping[str, Any],
    rows: Sequence[Mapping[str, Any]],
    overlay: Figure,
    curves: Mapping[str, GrowthCurve],
    overwrite: bool = False,
) -> Path:
    """Write the HTML report (module docstring), atomically.

    Args:
        path: The ``.html`` file.
        data: :func:`report_data`'s dict (case, verdict, problems).
        rows: :func:`measure_rows`'s rows.
        overlay: :func:`label_overlay_figure`'s figure.
        curves: The growth curves.
        overwrite: Whether an existing file may be replaced.

    Returns:
        The written path.
    """
    weeks = float(data["gestational_age_weeks"])
    verdict = (
        "<p class='ok'>Labels trusted: the atlases fit the volume and agree.</p>"
        if data["trusted"]
        else "<p class='bad'>Labels NOT trusted: "
        + "; ".join(html.escape(p) for p in data["problems"])
        + ". Check the overlay before using any number below.</p>"
    )
    table = "".join(
        f"<tr><td>{html.escape(r['name'])}</td><td>{_number(r['value'])} {r['unit']}</td>"
        f"<td>{_number(r['atlas_mean_at_age'])}</td>"
        f"<td>{_number(r['atlas_low'])}&ndash;{_number(r['atlas_high'])}</td>"
        f"<td>{_number(r['suggested_age_weeks'])}</td></tr>"
        for r in rows
    )
    atlases = "".join(
        f"<li>{html.escape(str(a['path']))}: GA {a['weeks']:g}, turned "
        f"{a['rotation_deg']:.1f} deg, correlation {a['ncc']:.2f}, vote weight "
        f"{a['weight']:.2f}</li>"
        for a in data.get("atlases", [])
    )
    title = html.escape(str(data["input"]))
    suggested = _number(data.get("suggested_age_weeks_median") or math.nan)
    legend = " ".join(
        f"<span style='background:{lab.colour}'>&nbsp;&nbsp;</span> {lab.name}"
        for lab in TISSUE_LABELS
    )
    structures = html.escape(", ".join(f"{k} = labels {v}" for k, v in STRUCTURES.items()))
    growth = _png(_curves_figure(rows, curves, weeks))
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:auto} .ok{color:#2a7} "
        ".bad{color:#c22;font-weight:bold} td,th{padding:2px 8px;text-align:right} "
        "td:first-child{text-align:left} table{border-collapse:collapse} "
        "tr:nth-child(even){background:#f4f4f4} img{max-width:100%}"
    )
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Tissue report: {title}</title>
<style>{style}</style></head>
<body><h1>Tissue report</h1>
<p>Volume: {title}<br>Gestational age given: {weeks:g} weeks;
ages suggested by the measures (median): {suggested} weeks</p>
{verdict}
<h2>Labels</h2><img alt="label overlay" src="data:image/png;base64,{_png(overlay)}">
<p>{legend}</p>
<h2>Against the atlas ages</h2><img alt="growth curves" src="data:image/png;base64,{growth}">
<table><tr><th>measure</th><th>this case</th><th>atlas mean at {weeks:g} w</th>
<th>range over the atlases used</th><th>suggested age (weeks)</th></tr>{table}</table>
<p><em>{html.escape(CAVEAT)}</em> Definitions of the measures: the fetal-svr documentation
(tissue labels and biometry). Structures: {structures}.</p>
<h2>Atlases used</h2><ul>{atlases}</ul>
</body></html>
"""
    return atomic_write_text(path, page, overwrite)


def write_json(path: str | os.PathLike[str], data: Mapping[str, Any], overwrite: bool) -> Path:
    """The report's numbers as JSON, atomically."""
    return atomic_write_text(path, json.dumps(data, indent=1) + "\n", overwrite)
