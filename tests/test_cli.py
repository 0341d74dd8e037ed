"""The ``svr`` command line: help, the demo, and one-line errors with non-zero exits."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from svr import __version__
from svr.cli import SUBCOMMANDS, build_parser, main

SMALL = ["--loss-only", "--num-poses", "32", "--steps", "150", "--device", "cpu", "--quiet"]


def test_help_lists_subcommands(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert (
        all(c in out for c in ("demo", "simulate", "sample", "train", "predict", "evaluate"))
        and "usage: svr" in out
    )


def test_demo_help_describes_options(capsys):
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    out = capsys.readouterr().out
    for option in (
        "--num-poses",
        "--steps",
        "--learning-rate",
        "--output",
        "--overwrite",
        "--device",
        "--seed",
        "(default: 200)",
    ):
        assert option in out


def test_version(capsys):
    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.strip() == f"svr {__version__}"


def test_demo_recovers_poses_and_writes_json(tmp_path, capsys):
    out = tmp_path / "demo.json"
    assert main(["demo", *SMALL, "--output", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "se3" in printed and "posenet" in printed
    payload = json.loads(out.read_text())
    methods = {r["method"]: r for r in payload["results"]}
    assert set(methods) == {"se3", "posenet", "anchor", "rot6d"}
    assert methods["se3"]["recovered_fraction"] > 0.9
    assert methods["se3"]["median_rotation_deg"] < 0.5
    assert payload["config"]["num_poses"] == 32
    assert [p.name for p in tmp_path.iterdir()] == ["demo.json"]  # no temporary files left


def test_demo_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "demo.json"
    out.write_text("keep me")
    assert main(["demo", *SMALL, "--output", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"svr demo: error: {out}: output exists; pass --overwrite to replace it"
    assert out.read_text() == "keep me"
    assert main(["demo", *SMALL, "--output", str(out), "--overwrite"]) == 0
    assert json.loads(out.read_text())["results"]


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--num-poses", "0"], 1, "argument --num-poses: must be > 0"),
        (["--learning-rate", "nan"], 1, "argument --learning-rate: must be a finite number"),
        (["--steps", "x"], 1, "argument --steps: invalid positive_int value"),
        (["--device", "tpu"], 1, "--device: unknown device 'tpu'"),
        (["--output", "/nonexistent-dir/out.json"], 1, "output folder /nonexistent-dir does not"),
    ],
)
def test_bad_arguments_give_one_line_errors(args, code, message, capsys):
    # Bad usage too: one line and exit status 1, like every other error (no usage dump).
    assert main(["demo", *SMALL, *args]) == code
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and err.startswith("svr demo: error: ")
    assert "Traceback" not in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_cuda_request_without_cuda(capsys):
    assert main(["demo", *SMALL, "--device", "cuda"]) == 1
    assert capsys.readouterr().err.strip() == (
        "svr demo: error: --device cuda: CUDA is not available on this machine (use cpu)"
    )


def test_console_script_and_module_entry_points(tmp_path):
    exe = shutil.which("svr", path=str(Path(sys.executable).parent))
    assert exe is not None, "the svr console script is not installed"
    result = subprocess.run([exe, "demo", *SMALL], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "recovered" in result.stdout
    result = subprocess.run(
        [sys.executable, "-m", "svr", "--version"], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and __version__ in result.stdout


def _help_examples(text: str, command: str) -> list[list[str]]:
    """The ``svr COMMAND ...`` example lines of a help text, continuation lines joined."""
    import shlex

    examples, current = [], None
    for line in text.splitlines():
        stripped = line.strip()
        if current is not None:
            current += " " + stripped.rstrip("\\")
            if not stripped.endswith("\\"):
                examples.append(current)
                current = None
        elif stripped.startswith(f"svr {command} "):
            current = stripped.rstrip("\\")
            if not stripped.endswith("\\"):
                examples.append(current)
                current = None
    return [shlex.split(e)[1:] for e in examples]


@pytest.mark.parametrize("command", sorted(SUBCOMMANDS))
def test_every_subcommand_help_is_accurate(command, capsys):
    """--help works, lists every option, and every example in it parses with the parser."""
    import argparse

    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith(f"usage: svr {command}")
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[
        command
    ]
    for action in sub._actions:
        for option in action.option_strings:
            assert option in text, f"svr {command} --help does not mention {option}"
    examples = _help_examples(text, command)
    assert examples, f"svr {command} --help has no example"
    for argv in examples:
        parser.parse_args(argv)  # exits with status 2 if an example is out of date
