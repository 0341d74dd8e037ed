"""The group level of ``svr bids``: one table, one review page and a cohort plot.

:func:`group_report` reads the provenance sidecar of every finished participant
(:func:`read_sidecars`) and writes ``svr_group.tsv`` (one row per participant and session: the
verdict, what each stack kept, rounds, time, warnings and, with ``--tissue-labels``, the tissue
volumes and measures), ``svr_group.html`` (every participant's QA figure beside its facts) and,
when participants have tissue measures, ``svr_group_tissue.png`` (each measure against
gestational age over the cohort).
"""

from __future__ import annotations

import html
import io
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from svr.apps.bids import BidsError
from svr.files import atomic_write_bytes, atomic_write_text

__all__ = [
    "GROUP_HTML",
    "GROUP_TISSUE_PNG",
    "GROUP_TSV",
    "TISSUE_COLUMNS",
    "group_report",
    "read_sidecars",
]

GROUP_TSV = "svr_group.tsv"
"""The group level's table, at the top of the output folder."""

GROUP_HTML = "svr_group.html"
"""The group level's review page, at the top of the output folder."""


def read_sidecars(
    output_dir: str | os.PathLike[str], participant_labels: Iterable[str] | None = None
) -> list[dict[str, Any]]:
    """The provenance sidecars of every finished participant in ``output_dir``, by label.

    Args:
        output_dir: The derivatives folder.
        participant_labels: Subjects to keep (with or without ``sub-``); ``None`` for all.

    Returns:
        The sidecars' contents, each with ``"_path"`` (the sidecar relative to ``output_dir``).
    """
    root = Path(output_dir)
    keep = (
        None if participant_labels is None else {p.removeprefix("sub-") for p in participant_labels}
    )
    out = []
    for path in sorted(root.glob("sub-*/**/anat/*_rec-svr_T2w.json")):
        if any(part.startswith(".") for part in path.relative_to(root).parts):
            continue  # a participant still being written
        data = json.loads(path.read_text(encoding="utf-8"))
        svr = data.get("svr", {})
        if keep is not None and svr.get("subject") not in keep:
            continue
        data["_path"] = path.relative_to(root).as_posix()
        out.append(data)
    return out


TISSUE_COLUMNS = (
    "intracranial_ml",
    "brain_tissue_ml",
    "ventricles_ml",
    "cerebellum_ml",
    "brain_bpd_mm",
    "brain_ofd_mm",
    "tcd_mm",
    "atrium_left_mm",
    "atrium_right_mm",
    "cc_length_mm",
)
"""The group table's tissue columns (``svr bids --tissue-labels``): volumes and measures."""

GROUP_TISSUE_PNG = "svr_group_tissue.png"
"""The group level's cohort plot of the tissue columns against gestational age."""

_COLUMNS = (
    "participant_id",
    "session_id",
    "verdict",
    "frame_trust",
    "stacks",
    "slices",
    "slices_excluded",
    "initialisation",
    "frame",
    "rounds",
    "converged",
    "seconds",
    "device",
    "gestational_age_weeks",
    "tissue",
    *TISSUE_COLUMNS,
    "warnings",
)


def _row(sidecar: dict[str, Any]) -> dict[str, str]:
    svr = sidecar["svr"]
    tissue = svr.get("tissue") or {}
    measured = {**tissue.get("volumes_ml", {}), **tissue.get("measures_mm", {})}
    kept = svr.get("initialisation", {})
    verdict = svr.get("verdict") or {}
    return {
        "participant_id": f"sub-{svr['subject']}",
        "session_id": f"ses-{svr['session']}" if svr.get("session") else "n/a",
        "verdict": str(verdict.get("status", "n/a")),
        "frame_trust": str(verdict.get("frame", "n/a")),
        "stacks": str(len(svr.get("inputs", []))),
        "slices": str(svr.get("slices", "n/a")),
        "slices_excluded": str(svr.get("slices_excluded", "n/a")),
        "initialisation": ", ".join(f"{v}" for v in kept.values()) or "n/a",
        "frame": str(svr.get("frame", "n/a")),
        "rounds": str(svr.get("rounds", "n/a")),
        "converged": "n/a" if svr.get("converged") is None else str(svr["converged"]).lower(),
        "seconds": f"{svr.get('total_seconds', float('nan')):.1f}",
        "device": str(svr.get("device", "n/a")),
        "gestational_age_weeks": _number(svr.get("gestational_age_weeks")),
        "tissue": _tissue_status(tissue),
        **{column: _number(measured.get(column.removesuffix("_ml"))) for column in TISSUE_COLUMNS},
        "warnings": " | ".join(svr.get("warnings", [])) or "",
    }


def _number(value: Any) -> str:
    return "n/a" if value is None or value != value else f"{float(value):.4g}"


def _tissue_status(tissue: dict[str, Any]) -> str:
    if not tissue:
        return "n/a"
    if "error" in tissue:
        return "error"
    return "trusted" if tissue.get("trusted") else "not trusted"


def _cohort_plot(rows: list[dict[str, str]], path: Path) -> Path | None:
    """The tissue columns against gestational age, one point per participant (``None`` if none).

    Participants whose labels are not trusted are drawn hollow.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    have = [r for r in rows if r["tissue"] in ("trusted", "not trusted")]
    have = [r for r in have if r["gestational_age_weeks"] != "n/a"]
    if not have:
        return None
    figure = Figure(figsize=(12, 5.5))
    for index, column in enumerate(TISSUE_COLUMNS):
        axes = figure.add_subplot(2, 5, index + 1)
        for trusted in (True, False):
            pick = [r for r in have if (r["tissue"] == "trusted") == trusted and r[column] != "n/a"]
            axes.plot(
                [float(r["gestational_age_weeks"]) for r in pick],
                [float(r[column]) for r in pick],
                "o",
                color="#1f77b4",
                markerfacecolor="#1f77b4" if trusted else "none",
                label="trusted" if trusted else "not trusted",
            )
        axes.set_title(column, fontsize=8)
        axes.tick_params(labelsize=7)
        axes.set_xlabel("gestational age (weeks)", fontsize=7)
    figure.axes[0].legend(fontsize=6)
    figure.tight_layout()
    buffer = io.BytesIO()
    FigureCanvasAgg(figure).print_png(buffer)
    return atomic_write_bytes(path, buffer.getvalue(), overwrite=True)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def group_report(
    output_dir: str | os.PathLike[str], participant_labels: Iterable[str] | None = None
) -> tuple[Path, Path, int]:
    """Write the group level: one TSV and one HTML review page over the finished participants.

    Args:
        output_dir: The derivatives folder of the participant level.
        participant_labels: Subjects to include; ``None`` for all.

    Returns:
        The TSV, the HTML page and the number of participants in them.

    Raises:
        BidsError: If no participant has finished in ``output_dir``.
    """
    root = Path(output_dir)
    sidecars = read_sidecars(root, participant_labels)
    if not sidecars:
        raise BidsError(
            f"OUTPUT_DIR {output_dir}: no finished participant (run the participant level first)"
        )
    rows = [_row(s) for s in sidecars]
    tsv = "\t".join(_COLUMNS) + "\n"
    tsv += "".join(
        "\t".join(r[c].replace("\t", " ").replace("\n", " ") for c in _COLUMNS) + "\n" for r in rows
    )
    tsv_path = atomic_write_text(root / GROUP_TSV, tsv, overwrite=True)
    cohort = _cohort_plot(rows, root / GROUP_TISSUE_PNG)
    cohort_html = (
        f"<h2>Tissue volumes and measures</h2><img src='{GROUP_TISSUE_PNG}' alt='cohort plot' "
        "style='max-width:100%'><p>Hollow points: labels not trusted (see each participant's "
        "tissue report).</p>"
        if cohort is not None
        else ""
    )
    index, cards = [], []
    for sidecar, row in zip(sidecars, rows, strict=True):
        session = "" if row["session_id"] == "n/a" else f" {row['session_id']}"
        title = html.escape(row["participant_id"] + session)
        anchor = title.replace(" ", "_")
        sidecar_path = Path(sidecar["_path"])
        qa = html.escape(
            sidecar_path.with_name(sidecar_path.name.replace("_T2w.json", "_qa.png")).as_posix()
        )
        warnings = sidecar["svr"].get("warnings", [])
        flag = " (FAILED)" if row["verdict"] == "failed" else " (warnings)" if warnings else ""
        index.append(f"<li><a href='#{anchor}'>{title}</a>{flag}</li>")
        notes = (
            "<ul class='warn'>" + "".join(f"<li>{html.escape(w)}</li>" for w in warnings) + "</ul>"
            if warnings
            else "<p class='ok'>no warnings</p>"
        )
        facts = "".join(
            f"<tr><th>{html.escape(c.replace('_', ' '))}</th><td>{html.escape(row[c])}</td></tr>"
            for c in _COLUMNS[2:-1]
        )
        cards.append(
            f"<section id='{anchor}'><a href='{qa}'><img src='{qa}' alt='QA figure of {title}' "
            f"loading='lazy'></a><div><h2>{title}</h2><table>{facts}</table>{notes}</div>"
            "</section>"
        )
    flagged = sum(1 for s in sidecars if s["svr"].get("warnings"))
    failed = sum(1 for row in rows if row["verdict"] == "failed")
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>fetal-svr: {_count(len(sidecars), "participant")}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; }}
section {{ border-top: 1px solid #ccc; padding: 0.5em 0; display: flex; gap: 1.5em;
  align-items: flex-start; }}
section img {{ width: 520px; max-width: 60vw; }}
h2 {{ margin-top: 0.2em; }}
th {{ text-align: left; padding-right: 1em; font-weight: normal; color: #555; }}
.warn li {{ color: #a40; }} .ok {{ color: #070; }}
</style></head><body>
<h1>fetal-svr reconstructions</h1>
<p>{_count(len(sidecars), "participant")}, <b>{failed} failed</b> (no usable volume: see each
verdict), {flagged} with warnings; the table:
<a href="{GROUP_TSV}">{GROUP_TSV}</a>. Each figure is the participant's QA page (orthogonal
views of the initial and final volume, each slice's agreement with the volume, the rounds); click
it to enlarge.</p>
<ul>{"".join(index)}</ul>
{cohort_html}
{"".join(cards)}
</body></html>
"""
    html_path = atomic_write_text(root / GROUP_HTML, page, overwrite=True)
    return tsv_path, html_path, len(sidecars)
