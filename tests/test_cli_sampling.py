"""``svr simulate`` and ``svr sample``: outputs, round trips and one-line errors."""

from __future__ import annotations

import json

import pytest
from oracles import foreground_cc, truth_poses
from synthetic import ellipsoid_brain

from svr.cli import main
from svr.image import load_nifti, save_nifti
from svr.pose_io import read_pose_table
from svr.sampling.slicer import SliceConfig, sample_slices


@pytest.fixture(scope="module")
def brain_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("brain")
    volume, mask = ellipsoid_brain(40, 1.5, (22, 26, 20), seed=5, origin_mm=(-20.0, -35.0, 10.0))
    save_nifti(volume, folder / "brain.nii.gz")
    save_nifti(mask, folder / "mask.nii.gz")
    return [
        "--input-volume",
        str(folder / "brain.nii.gz"),
        "--input-mask",
        str(folder / "mask.nii.gz"),
    ]


def test_simulate_writes_a_bench_style_case(brain_files, tmp_path, capsys):
    out = tmp_path / "case"
    args = [
        "simulate",
        "--output-dir",
        str(out),
        *brain_files,
        "--in-plane-resolution",
        "2",
        "--thickness",
        "3",
        "--noise",
        "0",
        "--quiet",
        "--device",
        "cpu",
    ]
    assert main(args) == 0
    assert "wrote" in capsys.readouterr().out
    truth = json.loads((out / "truth_slices.json").read_text())
    gt = load_nifti(out / "gt_volume.nii.gz")
    for entry in truth["stacks"]:
        stack = load_nifti(out / entry["file"])
        config = SliceConfig(size=stack.shape[:2], spacing_mm=2.0, thickness_mm=3.0)
        sim = sample_slices(gt, truth_poses(entry, "scanner"), config)
        assert foreground_cc(sim, stack.data.permute(2, 0, 1)) > 0.99
    assert main(args) == 1
    assert "output exists; pass --overwrite" in capsys.readouterr().err
    assert main([*args, "--overwrite", "--seed", "3"]) == 0


def test_sample_writes_preview_and_dataset(brain_files, tmp_path):
    preview, dataset = tmp_path / "p.png", tmp_path / "ds"
    assert (
        main(
            [
                "sample",
                *brain_files,
                "--num-slices",
                "12",
                "--size",
                "32",
                "--spacing",
                "1.5",
                "--thickness",
                "2",
                "--output-preview",
                str(preview),
                "--output-dataset",
                str(dataset),
                "--quiet",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    assert preview.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    slices = load_nifti(dataset / "slices.nii.gz")
    table = read_pose_table(dataset / "poses.csv")
    assert slices.shape == (32, 32, 12) and len(table.files) == 12 and table.frame == "canonical"
    assert json.loads((dataset / "config.json").read_text())["thickness_mm"] == 2.0
    # every slice shows brain
    assert ((slices.data > 0).float().mean(dim=(0, 1)) >= 0.1).all()


def test_sample_euler_grid_and_uniform(brain_files, tmp_path):
    for kind in ("euler-grid", "uniform"):
        out = tmp_path / kind
        assert (
            main(
                [
                    "sample",
                    *brain_files,
                    "--poses",
                    kind,
                    "--num-slices",
                    "5",
                    "--size",
                    "16",
                    "--output-dataset",
                    str(out),
                    "--quiet",
                    "--device",
                    "cpu",
                ]
            )
            == 0
        )
        assert len(read_pose_table(out / "poses.csv").files) == 5


def test_builtin_phantom_is_the_default_input(tmp_path):
    out = tmp_path / "case"
    assert (
        main(
            [
                "simulate",
                "--output-dir",
                str(out),
                "--num-stacks",
                "1",
                "--thickness",
                "4",
                "--in-plane-resolution",
                "2",
                "--phantom-ga",
                "24",
                "--quiet",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    assert "phantom" in json.loads((out / "case.json").read_text())["source"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["simulate", "--output-dir", "OUT", "--input-volume", "x.nii.gz"],
            "--input-volume and --input-mask go together",
        ),
        (
            [
                "simulate",
                "--output-dir",
                "OUT",
                "--input-volume",
                "missing.nii.gz",
                "--input-mask",
                "missing.nii.gz",
            ],
            "missing.nii.gz: no such file",
        ),
        (
            ["simulate", "--output-dir", "OUT", "--motion", "trajectories"],
            "--motion-path must be a trajectory file with motion 'trajectories', got None",
        ),
        (
            ["simulate", "--output-dir", "OUT", "--noise", "-1"],
            "--noise must be a finite number >= 0, got -1.0",
        ),
        (["sample", "--num-slices", "2"], "nothing to write"),
        (
            ["sample", "--output-preview", "OUT", "--min-brain-fraction", "1.5"],
            "--min-brain-fraction must be in [0, 1)",
        ),
    ],
)
def test_bad_input_is_one_line(args, message, tmp_path, capsys):
    args = [a.replace("OUT", str(tmp_path / "out")) for a in args]
    assert main([*args, "--quiet", "--device", "cpu"]) == 1
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
