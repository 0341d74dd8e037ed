"""Slice-pose evaluation: Table-3 metrics, summaries, paired tests and the report folder."""

from __future__ import annotations

import csv
import logging
import sys

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation
from skimage import io as skio

from svr.files import OutputExistsError
from svr.geometry.mirror import mirror_twin
from svr.image import Image
from svr.models.evaluation import EvalConfig, evaluate_poses, paired_tests, summarize, write_report
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import CanonicalVolume, canonicalize

N_SLICES = 24
CONFIG = EvalConfig(slice=SliceConfig(size=(32, 32), spacing_mm=2.0))
KEYS = {
    "cc",
    "mse",
    "psnr",
    "ssim",
    "geodesic",
    "rotation_deg",
    "euler_x_deg",
    "euler_y_deg",
    "euler_z_deg",
    "translation_mm",
    "geodesic_twin",
    "rotation_twin_deg",
    "translation_twin_mm",
}


@pytest.fixture(scope="module")
def volume() -> CanonicalVolume:
    """A 40^3 1.5 mm volume: smooth random intensities inside an ellipsoid mask."""
    rng = np.random.default_rng(3)
    n, spacing = 40, 1.5
    affine = torch.diag(torch.tensor([spacing, spacing, spacing, 1.0], dtype=torch.float64))
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1) * spacing
    inside = (((idx - n * spacing / 2) / np.array([26.0, 22.0, 18.0])) ** 2).sum(-1) <= 1.0
    data = np.clip(1.0 + gaussian_filter(rng.normal(size=(n,) * 3), 2.0) * 5.0, 0.1, None)
    image = Image(torch.from_numpy(data * inside).float(), affine)
    return canonicalize(image, Image(torch.from_numpy(inside.astype(np.float32)), affine))


@pytest.fixture(scope="module")
def true_poses() -> torch.Tensor:
    rng = np.random.default_rng(4)
    rot = Rotation.random(N_SLICES, random_state=5)
    t = rot.apply(
        np.stack([np.zeros(N_SLICES), np.zeros(N_SLICES), rng.uniform(-8, 8, N_SLICES)], 1)
    )
    return torch.from_numpy(np.concatenate([rot.as_rotvec(), t], 1))


def perturb(
    poses: torch.Tensor, angle_deg: float, shift_mm: float, seed: int, spread: float = 0.0
) -> torch.Tensor:
    """Poses rotated about random axes and shifted in random directions.

    The angles and shifts are ``angle_deg`` and ``shift_mm`` times U[1 - spread, 1 + spread].
    """
    rng = np.random.default_rng(seed)
    n = poses.shape[0]
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    scale = rng.uniform(1 - spread, 1 + spread, size=(n, 1))
    rot = Rotation.from_rotvec(axes * np.deg2rad(angle_deg) * scale) * Rotation.from_rotvec(
        poses[:, :3]
    )
    t = poses[:, 3:].numpy() + shift_mm * scale * directions
    return torch.from_numpy(np.concatenate([rot.as_rotvec(), t], 1))


@pytest.fixture(scope="module")
def results(volume, true_poses) -> dict[str, dict[str, np.ndarray]]:
    return {
        "good": evaluate_poses(volume, true_poses, perturb(true_poses, 3, 1, 0, 0.8), CONFIG),
        "bad": evaluate_poses(volume, true_poses, perturb(true_poses, 20, 6, 1, 0.8), CONFIG),
    }


def test_perfect_predictions(volume, true_poses):
    out = evaluate_poses(volume, true_poses, true_poses, CONFIG)
    assert set(out) == KEYS
    for value in out.values():
        assert isinstance(value, np.ndarray) and value.shape == (N_SLICES,)
        assert value.dtype == np.float64
    np.testing.assert_allclose(out["cc"], 1.0, atol=1e-6)
    np.testing.assert_allclose(out["mse"], 0.0, atol=1e-12)
    np.testing.assert_allclose(out["ssim"], 1.0, atol=1e-6)
    assert (out["psnr"] >= 60).all()
    for key in KEYS - {"cc", "mse", "psnr", "ssim"}:
        np.testing.assert_allclose(out[key], 0.0, atol=1e-5, err_msg=key)


def test_errors_up_to_the_mirror_twin(volume, true_poses):
    """Predicting the twin: large raw errors, zero up to the twin; no planes: no twin columns."""
    twins = mirror_twin(true_poses)
    out = evaluate_poses(volume, true_poses, twins, CONFIG)
    np.testing.assert_allclose(out["rotation_twin_deg"], 0.0, atol=1e-5)
    np.testing.assert_allclose(out["translation_twin_mm"], 0.0, atol=1e-5)
    np.testing.assert_allclose(out["geodesic_twin"], 0.0, atol=1e-5)
    assert float(np.median(out["rotation_deg"])) > 30.0
    # the twin error is the smaller of the errors to the truth and to its twin
    noisy = perturb(true_poses, 10, 2, 3)
    near = evaluate_poses(volume, true_poses, noisy, CONFIG)
    to_twin = evaluate_poses(volume, twins, noisy, CONFIG, planes=())
    expected = np.minimum(near["geodesic"], to_twin["geodesic"])
    np.testing.assert_allclose(near["geodesic_twin"], expected, atol=1e-9)
    assert "rotation_twin_deg" not in to_twin


def test_worse_predictions_give_worse_metrics(volume, true_poses):
    levels = [(0, 0), (2, 0.5), (8, 2), (20, 6), (45, 12)]
    means = [
        summarize(evaluate_poses(volume, true_poses, perturb(true_poses, a, s, 7), CONFIG))
        for a, s in levels
    ]
    for key in ("cc", "psnr", "ssim"):
        series = [m[key]["mean"] for m in means]
        assert all(np.diff(series) < 0), (key, series)
    for key in ("mse", "geodesic", "rotation_deg", "translation_mm"):
        series = [m[key]["mean"] for m in means]
        assert all(np.diff(series) > 0), (key, series)
    np.testing.assert_allclose(
        [m["rotation_deg"]["mean"] for m in means], [a for a, _ in levels], atol=1e-6
    )


def test_given_slices_are_the_ground_truth(volume, true_poses):
    truth = sample_slices(volume.image, true_poses, CONFIG.slice)
    noisy = truth + 0.05 * torch.randn_like(truth)
    out = evaluate_poses(volume, true_poses, true_poses, CONFIG, slices=noisy)
    assert (out["cc"] < 0.999).all() and (out["cc"] > 0.5).all()
    np.testing.assert_allclose(out["mse"], ((noisy - truth) ** 2).mean((1, 2)).numpy(), rtol=1e-5)
    np.testing.assert_allclose(out["geodesic"], 0.0, atol=1e-5)


def test_data_range_default_is_the_999th_percentile_of_the_truth(volume, true_poses):
    pred = perturb(true_poses, 5, 1, 2)
    truth = sample_slices(volume.image, true_poses, CONFIG.slice)
    explicit = EvalConfig(slice=CONFIG.slice, data_range=float(np.percentile(truth, 99.9)))
    default, given = (evaluate_poses(volume, true_poses, pred, c) for c in (CONFIG, explicit))
    np.testing.assert_allclose(default["psnr"], given["psnr"], rtol=1e-6)
    np.testing.assert_allclose(default["ssim"], given["ssim"], rtol=1e-6)
    doubled = EvalConfig(slice=CONFIG.slice, data_range=2 * explicit.data_range)
    np.testing.assert_allclose(
        evaluate_poses(volume, true_poses, pred, doubled)["psnr"],
        given["psnr"] + 20 * np.log10(2),
        rtol=1e-6,
    )


def test_bad_arguments_name_the_argument(volume, true_poses):
    with pytest.raises(ValueError, match="'pred_poses'"):
        evaluate_poses(volume, true_poses, true_poses[:3], CONFIG)
    with pytest.raises(ValueError, match="'true_poses'"):
        evaluate_poses(volume, true_poses[:, :5], true_poses, CONFIG)
    with pytest.raises(ValueError, match="'true_poses'"):
        evaluate_poses(volume, true_poses[None], true_poses[None], CONFIG)
    with pytest.raises(ValueError, match="'slices'"):
        evaluate_poses(volume, true_poses, true_poses, CONFIG, slices=torch.zeros(3, 32, 32))
    with pytest.raises(ValueError, match="'data_range'"):
        EvalConfig(slice=CONFIG.slice, data_range=0.0)
    empty = torch.zeros(N_SLICES, 32, 32)
    with pytest.raises(ValueError, match="percentile"):
        evaluate_poses(volume, true_poses, true_poses, CONFIG, slices=empty)


def test_summarize_shapes_and_values():
    per_slice = {"cc": np.array([0.5, 0.7, 0.9, 1.0]), "geodesic": np.array([3.0, 1.0, 2.0, 6.0])}
    summary = summarize(per_slice)
    assert list(summary) == ["cc", "geodesic"]
    assert all(set(s) == {"mean", "median", "std"} for s in summary.values())
    assert summary["geodesic"] == pytest.approx({"mean": 3.0, "median": 2.5, "std": np.sqrt(3.5)})
    assert all(isinstance(v, float) for s in summary.values() for v in s.values())
    with pytest.raises(ValueError, match="one length"):
        summarize({"cc": np.ones(3), "mse": np.ones(4)})
    with pytest.raises(ValueError, match="empty"):
        summarize({"cc": np.ones(0)})


def test_paired_test_detects_a_clearly_better_method(results):
    for metric in ("geodesic", "cc", "translation_mm", "ssim"):
        (row,) = paired_tests(results, metric)
        assert (row["method_a"], row["method_b"], row["n"]) == ("good", "bad", N_SLICES)
        assert row["t_pvalue"] < 0.01 and row["wilcoxon_pvalue"] < 0.01, row
        assert row["better"] == "good", row


def test_paired_test_statistic_matches_the_closed_form():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=30), rng.normal(size=30) + 0.2
    (row,) = paired_tests({"a": {"mse": a}, "b": {"mse": b}}, "mse")
    d = a - b
    assert row["t_statistic"] == pytest.approx(d.mean() / (d.std(ddof=1) / np.sqrt(d.size)))
    assert row["mean_difference"] == pytest.approx(d.mean())
    assert row["better"] == ("a" if d.mean() < 0 else "b")


def test_paired_test_of_identical_methods_finds_nothing(results):
    same = {"one": results["good"], "two": dict(results["good"])}
    (row,) = paired_tests(same, "geodesic")
    assert row["t_pvalue"] == 1.0 and row["wilcoxon_pvalue"] == 1.0 and row["better"] is None
    rng = np.random.default_rng(1)
    base = rng.normal(size=40)
    noisy = {"x": {"cc": base}, "y": {"cc": base + rng.normal(scale=1e-3, size=40)}}
    (row,) = paired_tests(noisy, "cc")
    assert row["t_pvalue"] > 0.01 and row["wilcoxon_pvalue"] > 0.01


def test_paired_tests_pairs_and_errors(results):
    three = {**results, "third": results["bad"]}
    assert [(r["method_a"], r["method_b"]) for r in paired_tests(three)] == [
        ("good", "bad"),
        ("good", "third"),
        ("bad", "third"),
    ]
    assert [(r["method_a"], r["method_b"]) for r in paired_tests(three, reference="third")] == [
        ("third", "good"),
        ("third", "bad"),
    ]
    assert paired_tests({"only": results["good"]}) == []
    with pytest.raises(ValueError, match="'reference'"):
        paired_tests(results, reference="nope")
    with pytest.raises(ValueError, match="no metric"):
        paired_tests(results, "nope")
    with pytest.raises(ValueError, match="numbers of slices"):
        paired_tests({"a": {"cc": np.ones(3)}, "b": {"cc": np.ones(4)}}, "cc")


def read_csv(path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_report_folder(results, volume, true_poses, tmp_path, monkeypatch, caplog):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    pred = perturb(true_poses[:3], 20, 6, 1)
    examples = {
        "bad": (
            sample_slices(volume.image, true_poses[:3], CONFIG.slice).numpy(),
            sample_slices(volume.image, pred, CONFIG.slice).numpy(),
        )
    }
    out = tmp_path / "report"
    with caplog.at_level(logging.WARNING, logger="svr.models.evaluation"):
        assert write_report(results, out, examples=examples) == out
    assert "matplotlib" in caplog.text
    assert sorted(p.name for p in out.iterdir()) == [
        "examples_00_bad.png",
        "paired_tests.csv",
        "per_slice.csv",
        "summary.csv",
        "summary.md",
    ]
    assert [p.name for p in tmp_path.iterdir()] == ["report"]  # no temporary folder left

    rows = read_csv(out / "per_slice.csv")
    assert len(rows) == 2 * N_SLICES and set(rows[0]) == {"method", "slice"} | KEYS
    back = np.array([float(r["geodesic"]) for r in rows if r["method"] == "bad"])
    np.testing.assert_allclose(back, results["bad"]["geodesic"], rtol=1e-9)
    summary = read_csv(out / "summary.csv")
    assert len(summary) == 2 * len(KEYS)
    cc_good = next(r for r in summary if r["method"] == "good" and r["metric"] == "cc")
    assert float(cc_good["median"]) == pytest.approx(np.median(results["good"]["cc"]))
    tests = read_csv(out / "paired_tests.csv")
    assert [r["metric"] for r in tests] == ["geodesic", "geodesic_twin", "cc"]

    md = (out / "summary.md").read_text(encoding="utf-8")
    table = [line for line in md.splitlines() if line.startswith("| ")]
    assert table[0].startswith("| Method | CC")
    for label in ("MSE", "PSNR", "SSIM", "GD", "Euler x", "Euler y", "Euler z", "Translation"):
        assert label in table[0]
    assert any(line.startswith("| good | ") for line in table)
    assert any(line.startswith("| bad | ") for line in table)
    assert "Paired tests" in md

    montage = skio.imread(out / "examples_00_bad.png")
    assert montage.shape == (2 * 32 + 2, 3 * 32 + 2 * 2) and montage.dtype == np.uint8


def test_report_refuses_to_overwrite(results, tmp_path):
    out = tmp_path / "report"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(OutputExistsError):
        write_report(results, out)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    write_report({"good": results["good"]}, out, overwrite=True)
    names = {p.name for p in out.iterdir()}
    assert "keep.txt" not in names and "paired_tests.csv" not in names
    assert "summary.md" in names


def test_report_rejects_inconsistent_results(results, tmp_path):
    with pytest.raises(ValueError, match="same metrics"):
        write_report({"a": results["good"], "b": {"cc": results["bad"]["cc"]}}, tmp_path / "r")
    with pytest.raises(ValueError, match="unknown method"):
        write_report(results, tmp_path / "r", examples={"x": (np.zeros((1, 4, 4)),) * 2})
    assert not (tmp_path / "r").exists()


def test_report_plots_with_matplotlib(results, tmp_path):
    pytest.importorskip("matplotlib")
    out = write_report(results, tmp_path / "report")
    assert (out / "error_histograms.png").stat().st_size > 0


def test_paired_test_of_constant_differences_is_decisive():
    a = np.linspace(0.1, 1.0, 12)
    (row,) = paired_tests({"a": {"geodesic": a}, "b": {"geodesic": a + 0.3}})
    assert row["t_statistic"] == -np.inf and row["t_pvalue"] == 0.0
    assert row["wilcoxon_pvalue"] < 0.01 and row["better"] == "a"
