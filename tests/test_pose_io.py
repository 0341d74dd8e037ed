"""Pose tables: CSV and JSON round trips, matrices consistent with vectors, bad files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from oracles import random_poses

from svr.files import OutputExistsError
from svr.geometry import vector_to_se3
from svr.pose_io import PoseTable, matrices_to_table, read_pose_table, write_pose_table


def table(rng, n=7, frame="canonical") -> PoseTable:
    return PoseTable(
        [f"stack{i % 2}.nii.gz" for i in range(n)],
        torch.arange(n),
        torch.from_numpy(random_poses(rng, n)),
        frame,
    )


@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_round_trip(tmp_path, rng, suffix):
    t = table(rng, frame="scanner")
    path = write_pose_table(t, tmp_path / f"poses{suffix}")
    back = read_pose_table(path)
    assert back.files == t.files and back.frame == "scanner"
    torch.testing.assert_close(back.slice_indices, t.slice_indices)
    torch.testing.assert_close(back.poses, t.poses, rtol=0, atol=1e-15)
    with pytest.raises(OutputExistsError):
        write_pose_table(t, path)


def test_csv_matrix_columns_match_the_vectors(tmp_path, rng):
    t = table(rng)
    path = write_pose_table(t, tmp_path / "p.csv")
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    assert header[:8] == ["file", "slice_index", "r_x", "r_y", "r_z", "t_x", "t_y", "t_z"]
    assert header[-1] == "frame" and len(header) == 21
    m = np.array([float(x) for x in lines[1].split(",")[8:20]]).reshape(3, 4)
    np.testing.assert_allclose(m, vector_to_se3(t.poses[0])[:3].numpy(), atol=1e-15)
    torch.testing.assert_close(
        matrices_to_table(t.files, t.slice_indices, vector_to_se3(t.poses), "canonical").poses,
        t.poses,
    )


def test_bad_tables(tmp_path, rng):
    (tmp_path / "bad.csv").write_text("file,slice_index\nx.nii.gz,0\n")
    with pytest.raises(ValueError, match=r"bad\.csv: not a readable pose table"):
        read_pose_table(tmp_path / "bad.csv")
    with pytest.raises(ValueError, match=r"missing\.json: not a readable pose table"):
        read_pose_table(tmp_path / "missing.json")
    with pytest.raises(ValueError, match=r"\.txt"):
        write_pose_table(table(rng), tmp_path / "p.txt")
    with pytest.raises(ValueError, match="'frame'"):
        table(rng, frame="world")
