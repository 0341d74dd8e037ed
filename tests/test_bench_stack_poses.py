"""The stack-pose benchmark's front-back twins (bench_learned_stack_poses.nearest_twin_deg).

Oracle: scipy ``Rotation``: a pose turned 180 degrees about a canonical axis (applied in the
canonical frame, i.e. on the left) is its twin, so its nearest twin is the truth itself; a pose
turned by a small angle about another axis is that angle from the truth and about 180 degrees
from each twin of the truth's.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_learned_stack_poses import best_of_within, nearest_twin_deg


def _pose(rotation: Rotation, shift=(0.0, 0.0, 0.0)) -> torch.Tensor:
    out = np.eye(4)
    out[:3, :3] = rotation.as_matrix()
    out[:3, 3] = shift
    return torch.from_numpy(out)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_a_front_back_twin_is_zero_from_its_truth(axis: str) -> None:
    truth = Rotation.random(random_state=3)
    twin = Rotation.from_euler(axis, 180, degrees=True) * truth
    assert nearest_twin_deg(_pose(twin, (4.0, -2.0, 7.0)), _pose(truth)) == pytest.approx(
        0.0, abs=1e-5
    )
    # Turned about the axis on the right (the stack's own frame), it is not a twin in general.
    other = truth * Rotation.from_euler(axis, 180, degrees=True)
    assert nearest_twin_deg(_pose(other), _pose(truth)) > 20.0


def test_a_near_pose_is_far_from_every_twin() -> None:
    truth = Rotation.random(random_state=5)
    near = Rotation.from_rotvec(np.radians(12.0) * np.array([0.6, 0.0, 0.8])) * truth
    expected = min(
        np.degrees((Rotation.from_euler(a, 180, degrees=True) * near * truth.inv()).magnitude())
        for a in "xyz"
    )
    assert nearest_twin_deg(_pose(near), _pose(truth)) == pytest.approx(expected, abs=1e-6)
    assert expected > 160.0


def test_best_of_within_counts_stacks_with_any_estimate_near_the_truth() -> None:
    rows = [
        {"a": {"rot_deg": 3.0}, "b": {"rot_deg": 40.0}},
        {"a": {"rot_deg": 12.0}, "b": {"rot_deg": 9.0}},
        {"a": {"rot_deg": 12.0}, "b": {"rot_deg": 10.5}},
    ]
    assert best_of_within(rows, ["a"]) == 1
    assert best_of_within(rows, ["b"]) == 1
    assert best_of_within(rows, ["a", "b"]) == 2
    assert best_of_within(rows, ["a", "b"], limit_deg=11.0) == 3
