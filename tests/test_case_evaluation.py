"""The learned start per slice on simulated cases: truth read right, packets placed right, the CLI.

Oracles: the simulator's own slices (the truth volume cut at each slice's true pose reproduces
what was acquired), the truth file's poses read back with numpy, and a network placement replaced
by the case's true transform (then every start is its truth), or by one turned packet (then only
that packet's slices are off, by the turn).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from synthetic import small_phantom

from svr.cli import main
from svr.geometry import rotation_angle
from svr.models.checkpoint import save_checkpoint
from svr.models.stack_pose import StackPoseConfig, StackPoseNet
from svr.reconstruction.initialisation import case_evaluation
from svr.reconstruction.initialisation.case_evaluation import CaseError, load_case, packet_starts
from svr.reconstruction.initialisation.learned import NetworkPlacement
from svr.reconstruction.slices import array_poses
from svr.sampling.simulate import SimulationConfig, simulate_case, write_case
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import canonicalize


def _case(folder: Path, motion: str) -> Path:
    volume, mask = small_phantom()
    config = SimulationConfig(
        num_stacks=2,
        thickness_mm=4.0,
        in_plane_mm=2.0,
        margin_mm=3.0,
        motion=motion,
        random_walk_rotation_deg=6.0,
        random_walk_translation_mm=2.0,
        noise=0.01,
        seed=4,
    )
    return write_case(simulate_case(canonicalize(volume, mask, name="phantom"), config), folder)


@pytest.fixture(scope="module")
def moving(tmp_path_factory) -> Path:
    return _case(tmp_path_factory.mktemp("cases") / "moving", "random_walk")


@pytest.fixture(scope="module")
def still(tmp_path_factory) -> Path:
    return _case(tmp_path_factory.mktemp("cases") / "still", "none")


def _true_transform(folder: Path) -> torch.Tensor:
    """(4, 4) scanner -> canonical of a still case, from its files with numpy."""
    info = json.loads((folder / "case.json").read_text())
    entry = json.loads((folder / "truth_slices.json").read_text())["stacks"][0]["slices"][0]
    atlas, scanner = np.eye(4), np.eye(4)
    atlas[:3, :3], atlas[:3, 3] = entry["atlas"]["R"], entry["atlas"]["t"]
    scanner[:3, :3], scanner[:3, 3] = entry["scanner"]["R"], entry["scanner"]["t"]
    transform = atlas @ np.linalg.inv(scanner)
    transform[:3, 3] -= info["atlas_centre_mm"]
    return torch.from_numpy(transform)


def test_the_truth_volume_cut_at_the_true_poses_gives_the_acquired_slices(moving) -> None:
    case = load_case(moving)
    slices = case.slices
    assert case.truth.shape == (len(slices), 4, 4)
    config = SliceConfig(
        size=tuple(slices.images.shape[-2:]),
        spacing_mm=float(slices.spacing_mm[0, 0]),
        thickness_mm=4.0,
    )
    cut = sample_slices(case.volume.image, array_poses(slices, case.truth), config).float()
    acquired = slices.images.float() * slices.masks.float()
    inside = slices.masks.flatten(1).sum(1) > 20
    corr = [
        float(np.corrcoef(a[m].numpy(), c[m].numpy())[0, 1])
        for a, c, m in zip(acquired[inside], cut[inside], slices.masks[inside].bool(), strict=True)
    ]
    assert np.median(corr) > 0.95
    # ... and not at a pose turned by 10 degrees (the check can fail)
    turn = torch.eye(4, dtype=torch.float64)
    turn[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0, math.radians(10), 0]).as_matrix())
    off = sample_slices(case.volume.image, array_poses(slices, turn @ case.truth), config).float()
    corr_off = [
        float(np.corrcoef(a[m].numpy(), c[m].numpy())[0, 1])
        for a, c, m in zip(acquired[inside], off[inside], slices.masks[inside].bool(), strict=True)
    ]
    assert np.median(corr_off) < np.median(corr) - 0.05


def test_every_start_is_its_truth_when_the_network_is_right(still, monkeypatch) -> None:
    case = load_case(still)
    transform = _true_transform(still)
    stacks = len(case.stacks)

    def placement(stacks_, model, packets, restart_deg):
        assert packets == 2 and restart_deg == 10.0
        per_packet = transform.repeat(stacks, packets, 1, 1)
        per_packet[1, 1] = turned  # stack 1's second packet (odd k-planes) turned
        return NetworkPlacement(transform.repeat(stacks, 1, 1), per_packet, torch.zeros(2), [])

    turned = transform.clone()
    monkeypatch.setattr(case_evaluation, "network_placement", placement)
    starts = packet_starts(None, case, packets=2, restart_deg=10.0)
    error = torch.rad2deg(rotation_angle(starts, case.truth))
    shift = (starts[:, :3, 3] - case.truth[:, :3, 3]).norm(dim=1)
    assert float(error.max()) < 1e-4 and float(shift.max()) < 1e-4

    axis_turn = torch.eye(4, dtype=torch.float64)
    axis_turn[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0, 0, math.radians(20)]).as_matrix())
    turned = axis_turn @ transform
    starts = packet_starts(None, case, packets=2, restart_deg=10.0)
    error = torch.rad2deg(rotation_angle(starts, case.truth))
    odd = (case.slices.stack_ids == 1) & (case.slices.slice_indices % 2 == 1)
    assert bool(odd.any())
    assert torch.allclose(error[odd], torch.full_like(error[odd], 20.0), atol=1e-4)
    assert float(error[~odd].max()) < 1e-4


def test_bad_case_folders_are_named(still, tmp_path) -> None:
    with pytest.raises(CaseError, match=r"case\.json: missing"):
        load_case(tmp_path)
    broken = tmp_path / "broken"
    broken.mkdir()
    for item in still.iterdir():
        target = broken / item.name
        target.symlink_to(item, target_is_directory=item.is_dir())
    truth = json.loads((still / "truth_slices.json").read_text())
    truth["stacks"][0]["slices"][5]["atlas"]["t"][0] += 5.0
    (broken / "truth_slices.json").unlink()
    (broken / "truth_slices.json").write_text(json.dumps(truth))
    with pytest.raises(CaseError, match="atlas and scanner poses disagree"):
        load_case(broken)


def _stack_pose_model(folder: Path, seed: int) -> Path:
    torch.manual_seed(seed)
    net = StackPoseNet(StackPoseConfig(width=4, grid_size=16, grid_spacing_mm=8.0))
    torch.nn.init.normal_(net.pose.linear.weight, std=0.1)
    config = {"architecture": "stack_pose", "model": net.config.to_dict()}
    folder.mkdir()
    return save_checkpoint(folder / "step_000000001", net.state_dict(), config).parent


def test_svr_evaluate_cases_reports_both_models_on_the_same_slices(moving, tmp_path, capsys):
    a, b = _stack_pose_model(tmp_path / "a", 1), _stack_pose_model(tmp_path / "b", 2)
    out = tmp_path / "report"
    argv = ["evaluate", "--checkpoints", f"a={a}", f"b={b}", "--cases", str(moving)]
    assert main([*argv, "--output-dir", str(out), "--quiet"]) == 0
    assert "2 methods on" in capsys.readouterr().out
    with (out / "per_slice.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    per_method = {m: [r for r in rows if r["method"] == m] for m in ("a", "b")}
    assert len(per_method["a"]) == len(per_method["b"]) > 10
    info = json.loads((out / "evaluation.json").read_text())
    assert info["cases"] is True and info["volumes"] == [str(moving)]
    tests = (out / "paired_tests.csv").read_text()
    assert "geodesic" in tests


@pytest.mark.parametrize(
    ("use_cases", "kind", "message"),
    [
        (False, "stack", "expected a slice-pose model; evaluate stack-pose models per slice"),
        (True, "slice", "expected a stack-pose model (with --cases)"),
        (True, "volumes", "give either --cases or volumes"),
    ],
)
def test_one_line_errors_for_cases(moving, tmp_path, capsys, use_cases, kind, message) -> None:
    from test_cli_evaluate import _save_model

    if kind == "slice":
        model = _save_model(tmp_path / "slice", "se3")
    else:
        model = _stack_pose_model(tmp_path / "stack", 1)
    argv = ["evaluate", "--checkpoints", str(model), "--output-dir", str(tmp_path / "out")]
    if use_cases:
        argv += ["--cases", str(moving)]
    if kind == "volumes" or not use_cases:
        argv += ["--input-volumes", str(moving / "gt_volume.nii.gz")]
        argv += ["--input-masks", str(moving / "gt_mask.nii.gz")]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()
