"""ReconstructionConfig checks itself: every bad field is named, with what it accepts."""

from __future__ import annotations

import pickle

import pytest

from svr.errors import ConfigFieldError
from svr.reconstruction.config import REGISTRATIONS, SCHEDULES, ReconstructionConfig

BACKGROUND = "a tuple (low, high) of finite numbers with 0 <= low <= high"
BAD = [
    ("output_resolution_mm", 0.0, "a finite number > 0"),
    ("output_resolution_mm", float("nan"), "a finite number > 0"),
    ("registration", "learned", f"one of {', '.join(map(repr, REGISTRATIONS))}"),
    ("template", -1, "None or an integer >= 0"),
    ("template", 1.5, "None or an integer >= 0"),
    ("outer_iterations", 0, "None or an integer >= 1"),
    ("outer_iterations", True, "None or an integer >= 1"),
    ("schedule", "fast", f"one of {', '.join(map(repr, SCHEDULES))}"),
    ("converged_deg", -0.1, "None or a finite number >= 0"),
    ("converged_mm", float("nan"), "None or a finite number >= 0"),
    ("converged_fraction", 1.0, "in [0, 1)"),
    ("background_mm", (3.0, 2.0), BACKGROUND),
    ("background_mm", (2.0,), BACKGROUND),
    ("background_mm", [2.0, 5.0], BACKGROUND),
    ("recapture", 1, "a bool"),
    ("svr_levels", 0, "an integer >= 1"),
    ("svr_iterations", 0, "an integer >= 1"),
    ("packets", 0, "an integer >= 1"),
    ("min_slice_pixels", -1, "an integer >= 0"),
    ("seed", -1, "an integer >= 0"),
    ("sr_iterations", (), "a non-empty tuple of integers >= 1"),
    ("sr_iterations", (7, 0), "a non-empty tuple of integers >= 1"),
    ("sr_iterations", [7], "a non-empty tuple of integers >= 1"),
    ("group_sizes", (4, 0), "a tuple of integers >= 1"),
    ("regularization", (0.1, -0.1), "a non-empty tuple of finite numbers >= 0"),
    ("regularization", (), "a non-empty tuple of finite numbers >= 0"),
    ("edge_delta", 0.0, "a finite number > 0"),
    ("robust", 1, "a bool"),
    ("ncc_threshold", 1.5, "in [-1, 1]"),
    ("ncc_threshold", float("nan"), "in [-1, 1]"),
    ("cnn_max_deviation_deg", 0.0, "a finite number > 0"),
    ("cnn_max_deviation_mm", float("inf"), "a finite number > 0"),
    ("cnn_min_support", 1.2, "in [0, 1]"),
]


@pytest.mark.parametrize(("field", "value", "expected"), BAD)
def test_bad_fields_are_named(field, value, expected):
    with pytest.raises(ConfigFieldError) as info:
        ReconstructionConfig(**{field: value})
    err = info.value
    assert (err.owner, err.field, err.expected) == ("ReconstructionConfig", field, expected)
    assert str(err).startswith(f"ReconstructionConfig: '{field}' must be {expected}, got ")
    assert isinstance(err, ValueError)
    again = pickle.loads(pickle.dumps(err))
    assert str(again) == str(err) and again.field == field


def test_defaults_and_edges_are_accepted():
    ReconstructionConfig()
    ReconstructionConfig(
        template=0,
        group_sizes=(),
        regularization=(0.0,),
        ncc_threshold=-1.0,
        cnn_min_support=0.0,
        min_slice_pixels=0,
        registration="cnn",
    )


def test_rounds_default_per_schedule():
    assert ReconstructionConfig(schedule="fixed").rounds == 5
    assert ReconstructionConfig().rounds == 16
    # The adaptive cap follows the registration: the learned start's rounds keep paying.
    assert ReconstructionConfig(registration="cnn").rounds == 24
    assert ReconstructionConfig(registration="cnn", schedule="fixed").rounds == 5
    assert ReconstructionConfig(registration="cnn", outer_iterations=7).rounds == 7
    assert ReconstructionConfig(registration="cnn").settings()["outer_iterations"] == 24
    assert ReconstructionConfig(schedule="fixed", outer_iterations=3).rounds == 3
    assert ReconstructionConfig(outer_iterations=1).rounds == 1
    ReconstructionConfig(converged_deg=0.0, converged_mm=0.0, converged_fraction=0.0)
    ReconstructionConfig(background_mm=(0.0, 0.0), recapture=False)
