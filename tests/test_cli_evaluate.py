"""``svr evaluate``: the Table-3 report of several checkpoints on shared slices, and its errors."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from synthetic import ellipsoid_brain

from svr.cli import evaluate, main
from svr.image import save_nifti
from svr.models.backbones import BackboneConfig
from svr.models.checkpoint import checkpoint_name, save_checkpoint
from svr.models.network import ModelConfig, build_model, checkpoint_model_config


def _save_model(folder, representation, size=32, seed=0):
    """A tiny network whose head predicts varied poses, saved as train does."""
    cfg = ModelConfig(
        backbone=BackboneConfig(width=8, depth=2),
        input_size=(size, size),
        spacing_mm=2.0,
        representation=representation,
    )
    torch.manual_seed(seed)
    model = build_model(cfg)
    torch.nn.init.normal_(model.head.linear.weight, std=0.5)
    return save_checkpoint(folder, model.state_dict(), checkpoint_model_config(cfg))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("evaluate")
    volume, mask = ellipsoid_brain(40, 1.5, (22, 26, 20), seed=3)
    save_nifti(volume, folder / "brain.nii.gz")
    save_nifti(mask, folder / "mask.nii.gz")
    run_dir = folder / "run_se3" / "checkpoints"
    run_dir.mkdir(parents=True)
    _save_model(run_dir / checkpoint_name(10), "se3", seed=1)
    _save_model(folder / "anchor", "anchor_points", seed=2)
    _save_model(folder / "big", "se3", size=48)
    return {
        "folder": folder,
        "volume": ["--input-volumes", str(folder / "brain.nii.gz")],
        "mask": ["--input-masks", str(folder / "mask.nii.gz")],
    }


def _args(files, out, *checkpoints, extra=()):
    return [
        "evaluate",
        "--checkpoints",
        *checkpoints,
        *files["volume"],
        *files["mask"],
        "--num-slices",
        "16",
        "--batch-size",
        "5",
        "--output-dir",
        str(out),
        "--device",
        "cpu",
        "--quiet",
        *extra,
    ]


def _read_csv(path):
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_report_of_two_checkpoints_on_shared_slices(files, tmp_path, capsys):
    folder, out = files["folder"], tmp_path / "report"
    code = main(_args(files, out, str(folder / "run_se3"), f"anchor={folder / 'anchor'}"))
    assert code == 0
    printed = capsys.readouterr().out
    assert "| run_se3 |" in printed and "| anchor |" in printed and "## Paired tests" in printed

    summary = (out / "summary.md").read_text()
    assert "| run_se3 |" in summary and "| anchor |" in summary
    rows = _read_csv(out / "per_slice.csv")
    assert len(rows) == 32
    assert [r["method"] for r in rows] == ["run_se3"] * 16 + ["anchor"] * 16
    tests = _read_csv(out / "paired_tests.csv")
    assert {(t["metric"], t["method_a"], t["method_b"]) for t in tests} == {
        ("geodesic", "run_se3", "anchor"),
        ("geodesic_twin", "run_se3", "anchor"),
        ("cc", "run_se3", "anchor"),
    }
    assert (out / "error_histograms.png").is_file()
    assert len(list(out.glob("examples_*_*.png"))) == 2

    poses = _read_csv(out / "poses.csv")
    assert [p["poses"] for p in poses] == ["true"] * 16 + ["run_se3"] * 16 + ["anchor"] * 16
    pred = {
        name: np.array(
            [[float(p[c]) for c in evaluate.POSE_COLUMNS] for p in poses if p["poses"] == name]
        )
        for name in ("true", "run_se3", "anchor")
    }
    assert not np.allclose(pred["run_se3"], pred["anchor"])  # two different predictors
    info = json.loads((out / "evaluation.json").read_text())
    assert info["input_size"] == [32, 32] and info["spacing_mm"] == 2.0
    assert info["checkpoints"]["run_se3"].endswith(checkpoint_name(10))

    # The same checkpoint under two names: identical per-slice metrics (same slices, same order),
    # and the same validation poses as the first run (the seed fixes them).
    again = tmp_path / "again"
    ckpt = str(folder / "run_se3")
    assert main(_args(files, again, f"a={ckpt}", f"b={ckpt}")) == 0
    rows = _read_csv(again / "per_slice.csv")
    a = [{k: v for k, v in r.items() if k != "method"} for r in rows if r["method"] == "a"]
    b = [{k: v for k, v in r.items() if k != "method"} for r in rows if r["method"] == "b"]
    assert a == b
    first = _read_csv(out / "poses.csv")
    second = _read_csv(again / "poses.csv")
    assert [p for p in first if p["poses"] == "true"] == [p for p in second if p["poses"] == "true"]
    assert [list(p.values())[1:] for p in first if p["poses"] == "run_se3"] == [
        list(p.values())[1:] for p in second if p["poses"] == "a"
    ]


def test_thickness_changes_the_slices(files, tmp_path):
    ckpt = str(files["folder"] / "anchor")
    thin, thick = tmp_path / "thin", tmp_path / "thick"
    assert main(_args(files, thin, ckpt)) == 0
    assert main(_args(files, thick, ckpt, extra=["--thickness", "4"])) == 0
    assert not (thin / "paired_tests.csv").exists()  # one method: no paired tests
    cc_thin = [r["cc"] for r in _read_csv(thin / "per_slice.csv")]
    cc_thick = [r["cc"] for r in _read_csv(thick / "per_slice.csv")]
    assert cc_thin != cc_thick
    assert json.loads((thick / "evaluation.json").read_text())["thickness_mm"] == 4.0


@pytest.mark.parametrize(
    ("checkpoints", "extra", "message"),
    [
        (["run_se3", "big"], [], "must share input size and spacing"),
        (["run_se3", "missing"], [], "missing: checkpoint folder does not exist"),
        (["run_se3", "x=anchor", "x=big"], [], "method names must differ"),
        (["run_se3"], ["--min-brain-fraction", "1.5"], "--min-brain-fraction must be in [0, 1)"),
        (["run_se3"], ["--only-ga", "24"], "--only-ga needs --atlas-dir"),
    ],
)
def test_one_line_errors(files, tmp_path, capsys, checkpoints, extra, message):
    folder = files["folder"]
    specs = [
        f"{c.split('=')[0]}={folder / c.split('=')[1]}" if "=" in c else str(folder / c)
        for c in checkpoints
    ]
    assert main(_args(files, tmp_path / "out", *specs, extra=extra)) == 1
    err = capsys.readouterr().err
    assert err.startswith("svr evaluate: error: ") and message in err
    assert err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_refuses_to_overwrite_the_report(files, tmp_path, capsys):
    out = tmp_path / "report"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    args = _args(files, out, str(files["folder"] / "anchor"))
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "output exists; pass --overwrite" in err and err.count("\n") == 1
    assert (out / "keep.txt").exists()
    assert main([*args, "--overwrite"]) == 0
    assert not (out / "keep.txt").exists() and (out / "summary.md").is_file()


def test_atlas_only_ga_and_help(files, tmp_path, capsys):
    atlas = tmp_path / "atlas"
    for ga in (24, 28):
        (atlas / f"GA{ga}").mkdir(parents=True)
        for name, src in (("srr", "brain"), ("mask", "mask")):
            (atlas / f"GA{ga}" / f"{name}.nii.gz").write_bytes(
                (files["folder"] / f"{src}.nii.gz").read_bytes()
            )
    base = [
        "evaluate",
        "--checkpoints",
        str(files["folder"] / "anchor"),
        "--atlas-dir",
        str(atlas),
        "--num-slices",
        "4",
        "--device",
        "cpu",
        "--quiet",
    ]
    assert main([*base, "--only-ga", "28", "--output-dir", str(tmp_path / "one")]) == 0
    volumes = json.loads((tmp_path / "one" / "evaluation.json").read_text())["volumes"]
    assert volumes == [str(atlas / "GA28" / "srr.nii.gz")]
    assert main([*base, "--only-ga", "24", "28", "--output-dir", str(tmp_path / "both")]) == 0
    assert len(_read_csv(tmp_path / "both" / "per_slice.csv")) == 8
    assert main([*base, "--only-ga", "30", "--output-dir", str(tmp_path / "none")]) == 1
    assert "--only-ga 30: no such GA*/srr.nii.gz" in capsys.readouterr().err

    with pytest.raises(SystemExit):
        main(["evaluate", "--help"])
    out = capsys.readouterr().out
    for option in ("--checkpoints", "--only-ga", "--num-slices", "--thickness", "--overwrite"):
        assert option in out
