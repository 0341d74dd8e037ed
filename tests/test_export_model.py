"""``svr export-model``: a slice-pose or stack-pose checkpoint (told apart by its config) becomes
a float16 model folder with its provenance; bad inputs are one-line errors, before any work."""

from __future__ import annotations

import json

import pytest
import torch
from synthetic import ellipsoid_brain

from svr.cli import main
from svr.models.backbones import BackboneConfig
from svr.models.checkpoint import load_checkpoint
from svr.models.network import ModelConfig
from svr.models.stack_pose import StackPoseConfig, load_stack_pose_model
from svr.models.stack_pose_train import StackPoseTrainingConfig, train_stack_pose
from svr.models.train import OptimConfig, TrainConfig, train
from svr.sampling.dataset import SliceDatasetConfig
from svr.sampling.slicer import SliceConfig
from svr.sampling.volume import canonicalize

DATA = "a synthetic ellipsoid brain (made by the tests, no licence)"


@pytest.fixture(scope="module")
def volume():
    return canonicalize(*ellipsoid_brain(32, 2.0, (22, 28, 18), seed=11, texture=3.0))


@pytest.fixture(scope="module")
def slice_pose_run(volume, tmp_path_factory):
    """A slice-pose training run folder of two steps."""
    out = tmp_path_factory.mktemp("slice-pose")
    size = (32, 32)
    config = TrainConfig(
        output_dir=str(out),
        model=ModelConfig(backbone=BackboneConfig(width=8, depth=2), input_size=size),
        data=SliceDatasetConfig(slice=SliceConfig(size=size, spacing_mm=2.0), batch_size=4),
        optim=OptimConfig(warmup_steps=0),
        steps=2,
    )
    train(config, [volume], progress=False)
    return out


def _one_line_error(capsys, *words: str) -> None:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for word in words:
        assert word in err, err


def test_a_slice_pose_run_exports_as_a_float16_model(slice_pose_run, tmp_path, capsys):
    out = tmp_path / "model"
    command = "svr train --output-dir run --steps 2"
    args = ["export-model", "--checkpoint", str(slice_pose_run), "--output-model", str(out)]
    assert main([*args, "--data", DATA, "--training-command", command]) == 0
    assert "slice-pose model from" in capsys.readouterr().out
    source = load_checkpoint(slice_pose_run / "checkpoints" / "step_000000002")
    exported = load_checkpoint(out)
    for name, value in source.state_dict.items():
        torch.testing.assert_close(exported.state_dict[name], value, rtol=1e-3, atol=1e-3)
    assert exported.config["checkpoint"]["half_precision"]
    assert exported.config["export"]["weights_dtype"] == "float16"
    provenance = exported.config["provenance"]
    assert provenance["training_command"] == command
    assert provenance["data"]["description"] == DATA
    assert exported.config["export"]["source_step"] == 2
    assert command in (out / "README.md").read_text()
    # Not replaced without --overwrite; with it, the same weights.
    assert main([*args, "--data", DATA, "--training-command", command]) == 1
    _one_line_error(capsys, "--overwrite")
    assert main([*args, "--data", DATA, "--training-command", command, "--overwrite"]) == 0


def test_a_stack_pose_run_exports_with_the_command_it_recorded(volume, tmp_path, capsys):
    training = StackPoseTrainingConfig(
        steps=1, fine_tune_steps=0, stacks_per_step=1, samples_per_stack=2, checkpoint_every=1
    )
    run = tmp_path / "run"
    recorded = "svr train-stack-pose --atlas-dir atlas --output-dir run"
    net = train_stack_pose(
        [volume],
        None,
        StackPoseConfig(width=4),
        training,
        folder=run,
        extra_config={"command": recorded, "data": {"volumes": ["GA28"]}},
    )
    out = tmp_path / "model"
    args = ["export-model", "--checkpoint", str(run), "--output-model", str(out), "--data", DATA]
    assert main(args) == 0
    assert "stack-pose model from" in capsys.readouterr().out
    config = json.loads((out / "config.json").read_text())
    assert config["architecture"] == "stack_pose"
    assert config["provenance"]["training_command"] == recorded
    assert config["provenance"]["data"]["recorded"] == {"volumes": ["GA28"]}
    loaded = load_stack_pose_model(out)
    for name, value in net.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[name], value, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"--training-command": None}, ["--training-command", "records no training command"]),
        ({"--data": " "}, ["--data: empty"]),
        ({"--checkpoint": "MISSING"}, ["--checkpoint", "does not exist"]),
        ({"--output-model": "RUN"}, ["--output-model", "--checkpoint"]),
    ],
)
def test_bad_inputs_are_one_line_errors(slice_pose_run, tmp_path, capsys, change, words):
    options = {
        "--checkpoint": str(slice_pose_run),
        "--output-model": str(tmp_path / "model"),
        "--data": DATA,
        "--training-command": "svr train",
    }
    replaced = {"MISSING": str(tmp_path / "missing"), "RUN": str(slice_pose_run)}
    options.update({k: replaced.get(v, v) if v else v for k, v in change.items()})
    args = [w for k, v in options.items() if v is not None for w in (k, v)]
    assert main(["export-model", *args]) == 1
    _one_line_error(capsys, *words)
    assert not (tmp_path / "model").exists()
