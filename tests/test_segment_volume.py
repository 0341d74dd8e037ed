"""``svr segment-volume`` end to end on a labelled phantom (no shared data), and its bad inputs."""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
import torch
from scipy import ndimage
from scipy.spatial.transform import Rotation
from tissue_phantom import atlas_folder, centred_affine, grid_points, image_of, phantom_labels, save

from svr.cli import main
from svr.image import Image, load_nifti, save_nifti
from svr.stamp import read_stamp, verdict_stamp
from svr.tissue.segment import TissueConfig, segment_volume


@pytest.fixture(scope="module")
def atlases(tmp_path_factory):
    return atlas_folder(tmp_path_factory.mktemp("atlases"))


def _case(folder, degrees=(3.0, -2.0, 4.0), shift=(1.5, -1.0, 2.0)):
    """The phantom of age 28 (between the atlas ages) seen on a 1.6 mm grid, turned a little."""
    shape = (44, 52, 44)
    turn = Rotation.from_euler("xyz", degrees, degrees=True).as_matrix()
    affine = centred_affine(shape, 1.6)
    # the case's world point q shows the phantom at turn @ q + shift
    points = grid_points(shape, affine) @ turn.T + np.asarray(shift)
    truth = phantom_labels(points)
    volume = save(folder / "volume.nii.gz", image_of(truth).astype(np.float32), affine)
    return volume, truth, affine


def _run(argv, capsys):
    capsys.readouterr()
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _dice(a, b):
    return 2.0 * (a & b).sum() / max(1, a.sum() + b.sum())


def _argv(volume, atlases, labels, *extra) -> list[str]:
    return [
        "segment-volume", "--input-volume", str(volume), "--atlas-dir", str(atlases),
        "--gestational-age", "28", "--output-labels", str(labels), *map(str, extra),
    ]  # fmt: skip


def test_phantom_is_labelled_measured_and_reported(tmp_path, atlases, capsys):
    volume, truth, affine = _case(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    argv = _argv(
        volume, atlases, out / "dseg.nii.gz", "--output-report", out / "report.html",
        "--output-measures", out / "m.tsv", out / "m.json", "--output-qa", out / "qa.png",
        "--threads", "2",
    )  # fmt: skip
    code, stdout, _ = _run(argv, capsys)
    assert code == 0
    assert "labels trusted" in stdout
    written = nib.load(str(out / "dseg.nii.gz"))
    assert written.get_data_dtype() == np.uint8
    np.testing.assert_allclose(written.affine, affine, atol=1e-5)
    labels = np.asarray(written.dataobj)
    dice = [_dice(labels == v, truth == v) for v in range(1, 9)]
    assert np.mean(dice) > 0.8, dice
    data = json.loads((out / "m.json").read_text())
    assert data["trusted"] and data["gestational_age_weeks"] == 28
    rows = {row["key"]: row for row in data["measures"]}
    # the volume the labels give, and a suggested age between the two atlas ages
    voxel_ml = 1.6**3 / 1000
    assert rows["ventricles"]["value"] == pytest.approx((labels == 2).sum() * voxel_ml)
    assert 26.5 < data["suggested_age_weeks_median"] < 29.5
    table = (out / "m.tsv").read_text().splitlines()
    assert table[0].split("\t")[:3] == ["key", "name", "value"] and len(table) == 18
    page = (out / "report.html").read_text()
    assert "Tissue report" in page and "Labels trusted" in page and "data:image/png" in page
    assert (out / "qa.png").read_bytes()[:4] == b"\x89PNG"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["dseg.nii.gz", "report.html", "m.tsv", "m.json", "qa.png"]
    )  # nothing temporary left behind
    # an existing output is kept unless --overwrite
    before = (out / "report.html").read_bytes()
    code, _, err = _run(argv, capsys)
    assert code != 0 and "exists" in err and len(err.strip().splitlines()) == 1
    assert (out / "report.html").read_bytes() == before


def test_volume_not_in_an_atlas_frame_is_refused_in_one_line(tmp_path, atlases, capsys):
    volume, _, _ = _case(tmp_path, degrees=(0.0, 0.0, 90.0))
    labels = tmp_path / "dseg.nii.gz"
    code, _, err = _run(_argv(volume, atlases, labels), capsys)
    assert code != 0
    assert "not in an atlas frame" in err and str(volume) in err
    assert len(err.strip().splitlines()) == 1
    assert not labels.exists()


def test_missing_atlas_folder_is_one_line(tmp_path, capsys):
    volume, _, _ = _case(tmp_path)
    missing = tmp_path / "no-atlases"
    code, _, err = _run(_argv(volume, missing, tmp_path / "l.nii.gz"), capsys)
    assert code != 0 and str(missing) in err and len(err.strip().splitlines()) == 1


def test_bad_output_names_are_refused_before_any_work(tmp_path, atlases, capsys):
    volume, _, _ = _case(tmp_path)
    argv = _argv(volume, atlases, tmp_path / "l.nii.gz", "--output-measures", tmp_path / "m.csv")
    code, _, err = _run(argv, capsys)
    assert code != 0 and "m.csv" in err and ".tsv or .json" in err
    assert not (tmp_path / "l.nii.gz").exists()


@pytest.mark.parametrize(
    ("status", "frame", "refused"),
    [("warning", "uncertain", False), ("failed", "trusted", False), ("ok", "scanner", True)],
)
def test_the_reconstructions_own_verdict_is_heeded(
    tmp_path, atlases, capsys, status, frame, refused
):
    """A volume stamped by svr reconstruct: not ok -> labels flagged; scanner frame -> refused."""
    volume, _, _ = _case(tmp_path)
    stamped = tmp_path / "stamped.nii.gz"
    save_nifti(load_nifti(volume), stamped, description=verdict_stamp(status, frame))
    assert read_stamp(nib.load(str(stamped)).header["descrip"].tobytes()) == (status, frame)
    out = tmp_path / "m.json"
    code, stdout, err = _run(
        _argv(stamped, atlases, tmp_path / "l.nii.gz", "--output-measures", out), capsys
    )
    if refused:
        assert code != 0 and "scanner frame" in err and len(err.strip().splitlines()) == 1
        assert not out.exists()
        return
    assert code == 0 and "NOT TRUSTED" in stdout
    data = json.loads(out.read_text())
    assert not data["trusted"]
    assert f"the reconstruction's verdict is {status}" in data["problems"][0]


def test_stamps_round_trip_and_refuse_what_they_cannot_hold():
    for status in ("ok", "warning", "failed"):
        for frame in ("scanner", "trusted", "uncertain", "untrusted"):
            text = verdict_stamp(status, frame)
            assert len(text) <= 80 and read_stamp(text.encode() + b"\0" * 4) == (status, frame)
    assert read_stamp(b"") is None and read_stamp("made by another tool") is None
    with pytest.raises(ValueError, match="status"):
        verdict_stamp("fine", "trusted")


def test_a_loose_mask_does_not_inflate_the_labels(tmp_path, atlases):
    """Non-brain signal inside a loose mask (as a reconstruction's) is not labelled as tissue.

    The volume carries a 0.3 halo 0-6 mm around the brain, all of it inside its mask; registering
    once on that mask draws the atlases outwards, the second pass on the cut volume does not.
    """
    volume_path, truth, affine = _case(tmp_path)
    data = load_nifti(volume_path).data.numpy()
    halo = ndimage.binary_dilation(truth > 0, iterations=4) & (truth == 0)
    data = np.where(halo, 0.3, data).astype(np.float32)
    volume = Image(torch.from_numpy(data), torch.from_numpy(affine))
    errors = {}
    for refine in (False, True):
        result = segment_volume(volume, [atlases], 28.0, TissueConfig(refine_brain=refine))
        errors[refine] = (result.labels > 0).sum() / (truth > 0).sum() - 1.0
        assert result.trusted
    assert abs(errors[True]) < 0.03 and errors[False] > 2 * abs(errors[True]), errors
