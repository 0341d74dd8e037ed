"""Evaluation of slice-pose predictions: the paper's Table 3, paired tests and a report folder.

For every slice, the ground-truth slice (given, or cut from the volume at the true pose) is
compared with the slice cut from the same volume at the predicted pose, as SVRnet's Table 3 does:

* ``cc``, ``mse``, ``psnr``, ``ssim``: :mod:`svr.image_metrics` on the whole slices. The
  intensities are those of the :class:`~svr.sampling.volume.CanonicalVolume` (in-mask 99th
  percentile = 1), so MSE is in those units, not in the paper's 8-bit ones. PSNR and SSIM need the
  intensity span: :attr:`EvalConfig.data_range`, by default the 99.9th percentile of all the
  ground-truth slices of the call pooled (so every method evaluated on the same slices gets the same
  span). PSNR of a perfect prediction is capped at 100 dB.
* ``geodesic``, ``rotation_deg``, ``euler_x_deg``, ``euler_y_deg``, ``euler_z_deg``,
  ``translation_mm``: :func:`svr.metrics.pose_errors`. ``geodesic`` is the left-invariant SE(3)
  distance in radian-equivalents (1 = 1 rad or 30 mm), not the paper's GD scale.
* ``geodesic_twin``, ``rotation_twin_deg``, ``translation_twin_mm``: the same errors up to the
  mirror twin (:mod:`svr.geometry.mirror`): to whichever of the true pose and its twin is
  nearer the prediction. A single slice of a symmetric brain cannot tell the two apart, so these
  are what a network can achieve on slices alone; the raw errors stay beside them.

Higher is better for ``cc``, ``psnr`` and ``ssim``; lower is better for every other metric.
"""

from __future__ import annotations

import csv
import itertools
import logging
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import stats
from skimage import io as skio
from torch import Tensor

from svr.files import atomic_directory
from svr.geometry._validation import check_tensor
from svr.geometry.mirror import SAGITTAL, ReflectionPlane
from svr.image_metrics import mse, ncc, psnr, ssim
from svr.metrics import nearest_orbit_member, pose_errors
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import CanonicalVolume
from svr.validation import check_instance, check_number

log = logging.getLogger(__name__)

DEFAULT_RANGE_PERCENTILE = 99.9
HIGHER_IS_BETTER = frozenset({"cc", "psnr", "ssim"})
DEFAULT_TEST_METRICS = ("geodesic", "geodesic_twin", "cc")
_HISTOGRAM_METRICS = ("geodesic", "rotation_deg", "rotation_twin_deg", "translation_mm", "cc")
_CONSTANT_RTOL = 1e-12  # differences that vary less than this (relative) count as constant
_EXAMPLE_GAP = 2  # pixels between the example slices in a montage


@dataclass(frozen=True)
class _MetricFormat:
    label: str
    fmt: str


# Report columns, in the order of the paper's Table 3 followed by the pose errors.
_METRICS: dict[str, _MetricFormat] = {
    "cc": _MetricFormat("CC ↑", ".3f"),
    "mse": _MetricFormat("MSE ↓", ".4g"),
    "psnr": _MetricFormat("PSNR (dB) ↑", ".2f"),
    "ssim": _MetricFormat("SSIM ↑", ".3f"),
    "geodesic": _MetricFormat("GD ↓", ".3f"),
    "rotation_deg": _MetricFormat("Rotation (°) ↓", ".2f"),
    "euler_x_deg": _MetricFormat("Euler x (°) ↓", ".2f"),
    "euler_y_deg": _MetricFormat("Euler y (°) ↓", ".2f"),
    "euler_z_deg": _MetricFormat("Euler z (°) ↓", ".2f"),
    "translation_mm": _MetricFormat("Translation (mm) ↓", ".2f"),
    "geodesic_twin": _MetricFormat("GD up to twin ↓", ".3f"),
    "rotation_twin_deg": _MetricFormat("Rotation up to twin (°) ↓", ".2f"),
    "translation_twin_mm": _MetricFormat("Translation up to twin (mm) ↓", ".2f"),
}


@dataclass(frozen=True)
class EvalConfig:
    """How slices are compared.

    Attributes:
        slice: How the slices are cut (size, spacing, PSF); the same for the ground truth and
            the prediction.
        data_range: Intensity span for PSNR and SSIM, or ``None`` for the 99.9th percentile of
            the ground-truth slices.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    slice: SliceConfig
    data_range: float | None = None

    def __post_init__(self) -> None:
        check_instance("EvalConfig", "slice", self.slice, SliceConfig)
        check_number("EvalConfig", "data_range", self.data_range, gt=0, allow_none=True)


def _check_poses(poses: object, name: str) -> Tensor:
    x = check_tensor(poses, "evaluate_poses", name, (6,))
    if x.dim() != 2:
        raise ValueError(f"evaluate_poses(): '{name}' must have shape (N, 6), got {tuple(x.shape)}")
    return x


def evaluate_poses(
    volume: CanonicalVolume,
    true_poses: Tensor,
    pred_poses: Tensor,
    config: EvalConfig,
    slices: Tensor | None = None,
    planes: Sequence[ReflectionPlane] = (SAGITTAL,),
) -> dict[str, np.ndarray]:
    """Per-slice image similarity and pose errors of predicted slice poses.

    Args:
        volume: The ground-truth volume in canonical space (the poses' frame).
        true_poses: (N, 6) true slice poses.
        pred_poses: (N, 6) predicted slice poses.
        config: Slice geometry and intensity span.
        slices: (N, H, W) ground-truth slices with ``(H, W) = config.slice.size`` (e.g. the
            acquired slices), or ``None`` to cut them from ``volume`` at ``true_poses``.
        planes: Mirror planes for the errors up to the twin (default: the sagittal plane, as a
            brain is nearly symmetric whatever the model was trained with); empty for none.

    Returns:
        (N,) float64 arrays keyed ``cc``, ``mse``, ``psnr``, ``ssim``, ``geodesic``,
        ``rotation_deg``, ``euler_x_deg``, ``euler_y_deg``, ``euler_z_deg``, ``translation_mm``
        (the module docstring defines them) and, with ``planes``, ``geodesic_twin``,
        ``rotation_twin_deg`` and ``translation_twin_mm``: the errors to the member of the true
        pose's mirror orbit nearest to the prediction by the geodesic distance.

    Raises:
        TypeError: If a pose or slice argument is not a floating-point tensor.
        ValueError: For wrong shapes (naming the argument), or ground-truth slices whose
            99.9th percentile is not positive when ``config.data_range`` is ``None``.
    """
    true_poses, pred_poses = (
        _check_poses(true_poses, "true_poses"),
        _check_poses(pred_poses, "pred_poses"),
    )
    if true_poses.shape != pred_poses.shape:
        raise ValueError(
            f"evaluate_poses(): 'pred_poses' must have the shape of 'true_poses' "
            f"{tuple(true_poses.shape)}, got {tuple(pred_poses.shape)}"
        )
    n = true_poses.shape[0]
    device = volume.image.data.device
    true_poses = true_poses.to(device=device, dtype=torch.float64)
    pred_poses = pred_poses.to(device=device, dtype=torch.float64)
    if slices is None:
        truth = sample_slices(volume.image, true_poses, config.slice)
    else:
        check_tensor(slices, "evaluate_poses", "slices", config.slice.size)
        if tuple(slices.shape) != (n, *config.slice.size):
            raise ValueError(
                f"evaluate_poses(): 'slices' must have shape (N, H, W) = "
                f"{(n, *config.slice.size)}, got {tuple(slices.shape)}"
            )
        truth = slices.to(device)
    predicted = sample_slices(volume.image, pred_poses, config.slice)
    data_range = config.data_range
    if data_range is None:
        data_range = float(np.percentile(truth.detach().cpu().numpy(), DEFAULT_RANGE_PERCENTILE))
        if not data_range > 0:
            raise ValueError(
                f"evaluate_poses(): the {DEFAULT_RANGE_PERCENTILE}th percentile of the "
                f"ground-truth slices is {data_range}; set EvalConfig.data_range"
            )
    out = {
        "cc": ncc(truth, predicted),
        "mse": mse(truth, predicted),
        "psnr": psnr(truth, predicted, data_range),
        "ssim": ssim(truth, predicted, data_range),
    }
    errors = pose_errors(pred_poses, true_poses)
    out.update({key: errors[key] for key in _METRICS if key in errors})
    if planes:
        twin_errors = pose_errors(
            pred_poses, nearest_orbit_member(pred_poses, true_poses, planes)[0]
        )
        out["geodesic_twin"] = twin_errors["geodesic"]
        out["rotation_twin_deg"] = twin_errors["rotation_deg"]
        out["translation_twin_mm"] = twin_errors["translation_mm"]
    return {key: value.detach().cpu().numpy().astype(np.float64) for key, value in out.items()}


def _check_per_slice(per_slice: Mapping[str, np.ndarray], owner: str) -> dict[str, np.ndarray]:
    """The metrics as 1-D float64 arrays of one common, non-zero length."""
    if not per_slice:
        raise ValueError(f"{owner}: no metrics")
    arrays = {key: np.asarray(value, dtype=np.float64) for key, value in per_slice.items()}
    shapes = {key: a.shape for key, a in arrays.items()}
    if len(set(shapes.values())) != 1 or len(next(iter(shapes.values()))) != 1:
        raise ValueError(f"{owner}: metrics must be 1-D arrays of one length, got shapes {shapes}")
    if next(iter(shapes.values()))[0] == 0:
        raise ValueError(f"{owner}: the metrics are empty (no slices)")
    return arrays


def summarize(per_slice: Mapping[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Mean, median and (population, ``ddof = 0``) standard deviation of each metric.

    Args:
        per_slice: (N,) arrays keyed by metric, e.g. from :func:`evaluate_poses`.

    Returns:
        ``{metric: {"mean": ..., "median": ..., "std": ...}}`` in the order of ``per_slice``.

    Raises:
        ValueError: If the arrays are not 1-D, differ in length or are empty.
    """
    arrays = _check_per_slice(per_slice, "summarize()")
    return {
        key: {"mean": float(a.mean()), "median": float(np.median(a)), "std": float(a.std())}
        for key, a in arrays.items()
    }


def _paired_statistics(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """Paired t-test and Wilcoxon signed-rank test of the differences ``d = x - y``.

    Both tests are undefined when every difference is 0 (identical methods): the result is then
    "no difference" (statistics 0, p-values 1). When every difference is the same non-zero value
    (to within ``1e-12`` relative, rounding noise) the t statistic is infinite (p = 0).

    Returns:
        t statistic, its two-sided p-value, Wilcoxon statistic, its two-sided p-value.
    """
    d = x - y
    if np.all(d == 0):
        return 0.0, 1.0, 0.0, 1.0
    if np.ptp(d) <= _CONSTANT_RTOL * np.abs(d).max():
        t, p_t = math.copysign(math.inf, float(d.mean())), 0.0
    else:
        t_res = stats.ttest_rel(x, y)
        t, p_t = float(t_res.statistic), float(t_res.pvalue)
    w_res = stats.wilcoxon(d)
    return t, p_t, float(w_res.statistic), float(w_res.pvalue)


def paired_tests(
    results: Mapping[str, Mapping[str, np.ndarray]],
    metric: str = "geodesic",
    reference: str | None = None,
) -> list[dict[str, Any]]:
    """Paired tests between methods evaluated on the same slices.

    Each pair ``(a, b)`` gets a two-sided paired t-test (:func:`scipy.stats.ttest_rel`) and a
    two-sided Wilcoxon signed-rank test (:func:`scipy.stats.wilcoxon`, zero differences
    dropped) of ``metric[a] - metric[b]`` over the slices.

    Args:
        results: ``{method: per-slice metrics}`` (from :func:`evaluate_poses`), the slices in the
            same order for every method.
        metric: The metric to compare.
        reference: Compare this method with each other one; ``None``: every pair, in the order
            of ``results``.

    Returns:
        One dict per pair with keys ``metric``, ``method_a``, ``method_b``, ``n`` (slices),
        ``mean_a``, ``mean_b``, ``mean_difference`` (``mean_a - mean_b``), ``t_statistic``,
        ``t_pvalue``, ``wilcoxon_statistic``, ``wilcoxon_pvalue`` and ``better`` (the method
        with the better mean -- higher for cc, psnr and ssim, lower otherwise -- or ``None`` if
        the means are equal). Empty for fewer than two methods.

    Raises:
        ValueError: If ``reference`` or ``metric`` is missing, or the methods have different
            numbers of slices (or fewer than 2).
    """
    if reference is not None and reference not in results:
        raise ValueError(
            f"paired_tests(): 'reference' {reference!r} is not one of the methods {list(results)}"
        )
    values: dict[str, np.ndarray] = {}
    for method, per_slice in results.items():
        if metric not in per_slice:
            raise ValueError(f"paired_tests(): method {method!r} has no metric {metric!r}")
        values[method] = np.asarray(per_slice[metric], dtype=np.float64).reshape(-1)
    sizes = {method: v.size for method, v in values.items()}
    if len(set(sizes.values())) > 1:
        raise ValueError(f"paired_tests(): the methods have different numbers of slices {sizes}")
    if values and next(iter(sizes.values())) < 2:
        raise ValueError("paired_tests(): at least 2 slices are needed")
    pairs = (
        [(reference, m) for m in values if m != reference]
        if reference is not None
        else list(itertools.combinations(values, 2))
    )
    rows = []
    for a, b in pairs:
        t, p_t, w, p_w = _paired_statistics(values[a], values[b])
        mean_a, mean_b = float(values[a].mean()), float(values[b].mean())
        diff = mean_a - mean_b
        better = None if diff == 0 else (a if (diff > 0) == (metric in HIGHER_IS_BETTER) else b)
        rows.append(
            {
                "metric": metric,
                "method_a": a,
                "method_b": b,
                "n": int(values[a].size),
                "mean_a": mean_a,
                "mean_b": mean_b,
                "mean_difference": diff,
                "t_statistic": t,
                "t_pvalue": p_t,
                "wilcoxon_statistic": w,
                "wilcoxon_pvalue": p_w,
                "better": better,
            }
        )
    return rows


def _check_results(
    results: Mapping[str, Mapping[str, np.ndarray]],
) -> tuple[dict[str, dict[str, np.ndarray]], list[str]]:
    """Validated results and their common metric keys (report order first, then the rest)."""
    if not results:
        raise ValueError("write_report(): 'results' has no methods")
    checked = {}
    for method, per_slice in results.items():
        if not isinstance(method, str) or not method:
            raise ValueError(f"write_report(): method names must be non-empty strings: {method!r}")
        checked[method] = _check_per_slice(per_slice, f"write_report(): method {method!r}")
    keys = [set(per_slice) for per_slice in checked.values()]
    if any(k != keys[0] for k in keys):
        raise ValueError("write_report(): the methods must have the same metrics")
    first = next(iter(checked.values()))
    metrics = [k for k in _METRICS if k in first] + [k for k in first if k not in _METRICS]
    return checked, metrics


def _number(value: float) -> str:
    return format(value, ".10g")


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _markdown(
    summaries: dict[str, dict[str, dict[str, float]]],
    metrics: Sequence[str],
    tests: Sequence[dict[str, Any]],
) -> str:
    """The report's Markdown: a Table-3 style summary and the paired tests."""

    def label(key: str) -> str:
        return _METRICS[key].label if key in _METRICS else key

    def cell(key: str, stat: dict[str, float]) -> str:
        fmt = _METRICS[key].fmt if key in _METRICS else ".4g"
        return f"{format(stat['mean'], fmt)} / {format(stat['median'], fmt)}"

    lines = [
        "# Slice-pose evaluation",
        "",
        "Ground-truth slice vs the slice resampled from the ground-truth volume at the predicted "
        "pose. Cells: mean / median over the slices. ↑ higher is better, ↓ lower is better. "
        "GD: SE(3) geodesic distance in radian-equivalents (1 = 1 rad or 30 mm).",
        "",
        "| Method | " + " | ".join(label(k) for k in metrics) + " |",
        "|---|" + "---:|" * len(metrics),
    ]
    for method, summary in summaries.items():
        cells = " | ".join(cell(k, summary[k]) for k in metrics)
        lines.append(f"| {_md_escape(method)} | {cells} |")
    if tests:
        lines += [
            "",
            "## Paired tests",
            "",
            "Two-sided paired t-test and Wilcoxon signed-rank test over the same slices; "
            "difference = mean A − mean B.",
            "",
            "| Metric | A | B | n | Mean A | Mean B | Difference | t-test p | Wilcoxon p "
            "| Better |",
            "|---|---|---|---:|---:|---:|---:|---:|---:|---|",
        ]
        for row in tests:
            fmt = _METRICS[row["metric"]].fmt if row["metric"] in _METRICS else ".4g"
            lines.append(
                f"| {label(row['metric'])} | {_md_escape(row['method_a'])} | "
                f"{_md_escape(row['method_b'])} | {row['n']} | {format(row['mean_a'], fmt)} | "
                f"{format(row['mean_b'], fmt)} | {format(row['mean_difference'], fmt)} | "
                f"{row['t_pvalue']:.3g} | {row['wilcoxon_pvalue']:.3g} | "
                f"{_md_escape(row['better'] or '–')} |"
            )
    return "\n".join(lines) + "\n"


def _example_montage(truth: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """8-bit montage: ground-truth slices on the top row, predicted ones below, one scale."""
    k, h, w = truth.shape
    hi = float(np.percentile(truth, DEFAULT_RANGE_PERCENTILE))
    if not hi > 0:
        hi = max(float(truth.max()), float(predicted.max()), 1e-12)
    montage = np.full((2 * h + _EXAMPLE_GAP, k * w + (k - 1) * _EXAMPLE_GAP), hi)  # white gaps
    for i in range(k):
        col = i * (w + _EXAMPLE_GAP)
        montage[:h, col : col + w] = truth[i]
        montage[h + _EXAMPLE_GAP :, col : col + w] = predicted[i]
    return np.round(np.clip(montage / hi, 0.0, 1.0) * 255).astype(np.uint8)


def _check_examples(
    examples: Mapping[str, tuple[np.ndarray, np.ndarray]], methods: Mapping[str, object]
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    checked = {}
    for method, (truth, predicted) in examples.items():
        if method not in methods:
            raise ValueError(f"write_report(): 'examples' names an unknown method {method!r}")
        truth, predicted = np.asarray(truth, np.float64), np.asarray(predicted, np.float64)
        if truth.ndim != 3 or truth.shape != predicted.shape or truth.shape[0] == 0:
            raise ValueError(
                f"write_report(): 'examples'[{method!r}] must be two (K, H, W) arrays of one "
                f"shape with K >= 1, got {truth.shape} and {predicted.shape}"
            )
        checked[method] = (truth, predicted)
    return checked


def _plot_histograms(
    path: Path, results: dict[str, dict[str, np.ndarray]], metrics: Sequence[str]
) -> None:
    """Overlaid per-method histograms of the main errors (nothing if matplotlib is missing)."""
    shown = [k for k in _HISTOGRAM_METRICS if k in metrics]
    if not shown:
        return
    try:
        from matplotlib.figure import Figure
    except ImportError:
        log.warning("matplotlib is not installed: the report has no plots (pip install matplotlib)")
        return
    fig = Figure(figsize=(5 * len(shown), 4), layout="constrained")
    for ax, key in zip(fig.subplots(1, len(shown), squeeze=False)[0], shown, strict=True):
        pooled = np.concatenate([per_slice[key] for per_slice in results.values()])
        bins = np.histogram_bin_edges(pooled, bins=30)
        for method, per_slice in results.items():
            ax.hist(per_slice[key], bins=bins, histtype="step", linewidth=1.5, label=method)
        ax.set_xlabel(_METRICS[key].label)
        ax.set_ylabel("slices")
    fig.axes[0].legend()
    fig.savefig(path, dpi=100)


def write_report(
    results: Mapping[str, Mapping[str, np.ndarray]],
    out_dir: str | os.PathLike[str],
    overwrite: bool = False,
    *,
    test_metrics: Sequence[str] = DEFAULT_TEST_METRICS,
    reference: str | None = None,
    examples: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Path:
    """Write an evaluation report folder, atomically.

    Contents:
        * ``per_slice.csv``: ``method, slice, <metric>...``, one row per method and slice.
        * ``summary.csv``: ``method, metric, mean, median, std`` (:func:`summarize`).
        * ``paired_tests.csv`` (two or more methods): :func:`paired_tests` for each of
          ``test_metrics`` present in the results.
        * ``summary.md``: a Table-3 style Markdown table (rows: methods; cells: mean / median of
          CC, MSE, PSNR, SSIM, GD, rotation, Euler x/y/z and translation errors) and the paired
          tests.
        * ``examples_<i>_<method>.png`` for each entry of ``examples``: ground-truth slices on
          the top row and the slices at the predicted poses below, on one 8-bit scale.
        * ``error_histograms.png``: per-method histograms of the GD, rotation and translation
          errors and the CC, if matplotlib is installed (otherwise a warning is logged).

    Args:
        results: ``{method: per-slice metrics}`` (from :func:`evaluate_poses`); every method
            must have the same metrics.
        out_dir: The folder to create (its parent must exist).
        overwrite: Whether an existing folder may be replaced.
        test_metrics: The metrics to run paired tests on.
        reference: As in :func:`paired_tests`.
        examples: ``{method: (truth, predicted)}``, two (K, H, W) arrays of example slices
            (e.g. from :func:`svr.sampling.slicer.sample_slices` at the true and predicted poses).

    Returns:
        The report folder.

    Raises:
        OutputExistsError: If ``out_dir`` exists and ``overwrite`` is false.
        ValueError: For inconsistent results or examples.
    """
    checked, metrics = _check_results(results)
    checked_examples = _check_examples(examples or {}, checked)
    summaries = {method: summarize(per_slice) for method, per_slice in checked.items()}
    tests = [
        row
        for metric in test_metrics
        if metric in metrics
        for row in paired_tests(checked, metric, reference)
    ]
    with atomic_directory(out_dir, overwrite) as tmp:
        _write_csv(
            tmp / "per_slice.csv",
            ["method", "slice", *metrics],
            [
                [method, i, *(_number(per_slice[k][i]) for k in metrics)]
                for method, per_slice in checked.items()
                for i in range(per_slice[metrics[0]].size)
            ],
        )
        _write_csv(
            tmp / "summary.csv",
            ["method", "metric", "mean", "median", "std"],
            [
                [method, k, *(_number(summary[k][s]) for s in ("mean", "median", "std"))]
                for method, summary in summaries.items()
                for k in metrics
            ],
        )
        if tests:
            header = list(tests[0])
            _write_csv(
                tmp / "paired_tests.csv",
                header,
                [
                    [
                        _number(v) if isinstance(v, float) else ("" if v is None else v)
                        for v in (row[h] for h in header)
                    ]
                    for row in tests
                ],
            )
        (tmp / "summary.md").write_text(_markdown(summaries, metrics, tests), encoding="utf-8")
        for i, (method, (truth, predicted)) in enumerate(checked_examples.items()):
            name = re.sub(r"[^A-Za-z0-9._-]+", "_", method)
            skio.imsave(
                tmp / f"examples_{i:02d}_{name}.png",
                _example_montage(truth, predicted),
                check_contrast=False,
            )
        _plot_histograms(tmp / "error_histograms.png", checked, metrics)
    return Path(out_dir)
