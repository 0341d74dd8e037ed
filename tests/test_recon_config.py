"""The reconstruction's grouped configuration checks itself, and its options are declared once."""

from __future__ import annotations

import argparse
import dataclasses
import pickle

import pytest

from svr.cli.config_options import (
    add_config_options,
    config_from_options,
    option_names,
    set_option_default,
)
from svr.errors import ConfigFieldError
from svr.options import option, option_fields, option_values
from svr.reconstruction.config import (
    INITIALISATIONS,
    LEARNED_STARTS,
    SCHEDULES,
    GridConfig,
    InitialisationConfig,
    OutlierConfig,
    ReconstructionConfig,
    ScheduleConfig,
    SuperResolutionConfig,
)

BACKGROUND = "a tuple (low, high) of finite numbers with 0 <= low <= high"
BAD = [
    (GridConfig, "resolution_mm", 0.0, "a finite number > 0"),
    (GridConfig, "resolution_mm", float("nan"), "a finite number > 0"),
    (InitialisationConfig, "kind", "cnn", f"one of {', '.join(map(repr, INITIALISATIONS))}"),
    (InitialisationConfig, "template", -1, "None or an integer >= 0"),
    (InitialisationConfig, "template", 1.5, "None or an integer >= 0"),
    (InitialisationConfig, "grid_mm", 0.0, "None or a finite number > 0"),
    (InitialisationConfig, "restart_deg", -1.0, "a finite number >= 0"),
    (InitialisationConfig, "slice_trajectory", 1, "a bool"),
    (InitialisationConfig, "slice_max_deviation_deg", 0.0, "a finite number > 0"),
    (InitialisationConfig, "slice_max_deviation_mm", float("inf"), "a finite number > 0"),
    (InitialisationConfig, "slice_min_support", 1.2, "in [0, 1]"),
    (ScheduleConfig, "kind", "fast", f"one of {', '.join(map(repr, SCHEDULES))}"),
    (ScheduleConfig, "rounds", 0, "an integer >= 1"),
    (ScheduleConfig, "rounds", True, "an integer >= 1"),
    (ScheduleConfig, "converged_deg", -0.1, "a finite number >= 0"),
    (ScheduleConfig, "converged_mm", float("nan"), "a finite number >= 0"),
    (ScheduleConfig, "converged_fraction", 1.0, "in [0, 1)"),
    (ScheduleConfig, "polish", 0.0, "in (0, 1]"),
    (ScheduleConfig, "polish", 1.5, "in (0, 1]"),
    (ScheduleConfig, "recapture", 1, "a bool"),
    (ScheduleConfig, "svr_levels", 0, "an integer >= 1"),
    (ScheduleConfig, "svr_iterations", 0, "an integer >= 1"),
    (ScheduleConfig, "min_slice_pixels", -1, "an integer >= 0"),
    (ScheduleConfig, "group_sizes", (4, 0), "a tuple of integers >= 1"),
    (SuperResolutionConfig, "background_mm", (3.0, 2.0), BACKGROUND),
    (SuperResolutionConfig, "background_mm", (2.0,), BACKGROUND),
    (SuperResolutionConfig, "background_mm", [2.0, 5.0], BACKGROUND),
    (SuperResolutionConfig, "iterations", (), "a non-empty tuple of integers >= 1"),
    (SuperResolutionConfig, "iterations", (7, 0), "a non-empty tuple of integers >= 1"),
    (SuperResolutionConfig, "iterations", [7], "a non-empty tuple of integers >= 1"),
    (
        SuperResolutionConfig,
        "regularization",
        (0.1, -0.1),
        "a non-empty tuple of finite numbers >= 0",
    ),
    (SuperResolutionConfig, "regularization", (), "a non-empty tuple of finite numbers >= 0"),
    (SuperResolutionConfig, "edge_delta", 0.0, "a finite number > 0"),
    (OutlierConfig, "robust", 1, "a bool"),
    (OutlierConfig, "ncc_threshold", 1.5, "in [-1, 1]"),
    (OutlierConfig, "ncc_threshold", float("nan"), "in [-1, 1]"),
    (ReconstructionConfig, "packets", 0, "an integer >= 1"),
    (ReconstructionConfig, "seed", -1, "an integer >= 0"),
    (ReconstructionConfig, "schedule", "adaptive", "a ScheduleConfig"),
]


@pytest.mark.parametrize(("owner", "field", "value", "expected"), BAD)
def test_bad_fields_are_named(owner, field, value, expected):
    with pytest.raises(ConfigFieldError) as info:
        owner(**{field: value})
    err = info.value
    assert (err.owner, err.field, err.expected) == (owner.__name__, field, expected)
    assert str(err).startswith(f"{owner.__name__}: '{field}' must be {expected}, got ")
    assert isinstance(err, ValueError)
    again = pickle.loads(pickle.dumps(err))
    assert str(again) == str(err) and again.field == field


def test_defaults_and_edges_are_accepted():
    ReconstructionConfig()
    InitialisationConfig(kind="learned", template=0, slice_min_support=0.0)
    ScheduleConfig(group_sizes=(), min_slice_pixels=0, rounds=1)
    ScheduleConfig(converged_deg=0.0, converged_mm=0.0, converged_fraction=0.0, recapture=False)
    SuperResolutionConfig(regularization=(0.0,), background_mm=(0.0, 0.0))
    OutlierConfig(ncc_threshold=-1.0)


def test_presets_choose_the_schedule_by_start_once():
    assert ReconstructionConfig().schedule.rounds == 16
    assert ReconstructionConfig.preset("stack").schedule == ScheduleConfig()
    assert ReconstructionConfig.preset("scanner").schedule == ScheduleConfig()
    # A start near the final poses keeps paying for more, stricter rounds.
    for kind in LEARNED_STARTS:
        learned = ReconstructionConfig.preset(kind)
        assert learned.initialisation.kind == kind
        assert (learned.schedule.rounds, learned.schedule.converged_deg) == (24, 0.15)
        assert (learned.schedule.converged_mm, learned.schedule.polish) == (0.075, 0.5)
    for kind in INITIALISATIONS:
        fixed = ReconstructionConfig.preset(kind, "fixed").schedule
        assert (fixed.kind, fixed.rounds) == ("fixed", 5)
    with pytest.raises(ConfigFieldError):
        ReconstructionConfig.preset("cnn")
    with pytest.raises(ConfigFieldError):
        ReconstructionConfig.preset("stack", "fast")


def test_the_initialisation_grid_defaults_to_twice_the_output_resolution():
    config = ReconstructionConfig(grid=GridConfig(resolution_mm=1.25))
    assert config.initialisation_grid_mm == 2.5
    given = dataclasses.replace(config, initialisation=InitialisationConfig(grid_mm=3.0))
    assert given.initialisation_grid_mm == 3.0


def test_settings_are_grouped_and_complete():
    settings = ReconstructionConfig().settings()
    assert set(settings) == {f.name for f in dataclasses.fields(ReconstructionConfig)}
    assert settings["schedule"]["rounds"] == 16
    assert settings["outliers"]["ncc_threshold"] == 0.5


def _parser(config_class=ReconstructionConfig):
    parser = argparse.ArgumentParser()
    add_config_options(parser, config_class, {"": "general"})
    return parser


def test_every_option_is_generated_from_its_field():
    parser = _parser()
    flags = {flag for action in parser._actions for flag in action.option_strings}
    declared = {spec.flag for _, _, spec in option_fields(ReconstructionConfig)}
    assert declared <= flags
    assert {"--ncc-threshold", "--iterations", "--no-robust", "--output-resolution"} <= declared
    args = parser.parse_args(
        [
            "--ncc-threshold", "0.3", "--no-robust", "--sr-iterations", "2", "3",
            "--sr-regularization", "0.1", "0.03", "--iterations", "4",
        ]
    )  # fmt: skip
    config = config_from_options(args, ReconstructionConfig.preset("learned"))
    assert config.outliers == OutlierConfig(robust=False, ncc_threshold=0.3)
    assert config.superres.iterations == (2, 3)
    assert config.superres.regularization == (0.1, 0.03)
    assert config.schedule.rounds == 4
    # What was not given keeps the base's (the learned start's preset).
    assert config.schedule.converged_deg == 0.15
    untouched = config_from_options(parser.parse_args([]), ReconstructionConfig())
    assert untouched == ReconstructionConfig()
    values = option_values(config)
    # A flag that turns a field off reads True where it was given (robust is False).
    assert values["--ncc-threshold"] == 0.3 and values["--no-robust"] is True
    assert option_values(untouched)["--no-robust"] is False
    assert values["--sr-iterations"] == [2, 3]
    assert values["--sr-regularization"] == [0.1, 0.03]


def test_a_bad_option_value_is_named_by_its_option():
    names = option_names(ReconstructionConfig)
    assert names["OutlierConfig.ncc_threshold"] == "--ncc-threshold"
    assert names["ScheduleConfig.rounds"] == "--iterations"
    parser = _parser()
    with pytest.raises(ConfigFieldError) as info:
        config_from_options(parser.parse_args(["--ncc-threshold", "2"]), ReconstructionConfig())
    assert names[f"{info.value.owner}.{info.value.field}"] == "--ncc-threshold"


def test_a_new_field_with_an_option_appears_on_the_command_line():
    # Adding a field with its option to a configuration is all it takes.
    @dataclasses.dataclass(frozen=True)
    class Extended(OutlierConfig):
        slice_floor: float = option(0.25, "--slice-floor", "a new setting", metavar="X")

    @dataclasses.dataclass(frozen=True)
    class Config(ReconstructionConfig):
        outliers: Extended = dataclasses.field(default_factory=Extended)

    parser = _parser(Config)
    help_text = parser.format_help()
    assert "--slice-floor X" in help_text and "a new setting (default: 0.25)" in help_text
    config = config_from_options(parser.parse_args(["--slice-floor", "0.5"]), Config())
    assert config.outliers.slice_floor == 0.5
    assert option_names(Config)["Extended.slice_floor"] == "--slice-floor"
    assert option_values(config)["--slice-floor"] == 0.5


def test_a_command_can_change_a_generated_default():
    parser = _parser()
    set_option_default(parser, "--iterations", 1)
    assert parser.parse_args([]).iterations == 1
    assert "(default: 1)" in parser.format_help().replace("\n", " ").replace("  ", " ")
