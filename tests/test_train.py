"""Training: the loss falls, checkpoints resume exactly, DDP runs, and the CLI drives it."""

from __future__ import annotations

import copy
import csv
import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from synthetic import ellipsoid_brain

from svr.cli import main
from svr.files import OutputExistsError
from svr.image import Image, save_nifti
from svr.models.backbones import BackboneConfig
from svr.models.checkpoint import latest_checkpoint, load_checkpoint
from svr.models.network import ModelConfig, build_model, loss_function
from svr.models.train import OptimConfig, TrainConfig, train, train_step
from svr.sampling.dataset import EulerGridStream, SliceDatasetConfig, SliceStream
from svr.sampling.poses import EulerGridConfig
from svr.sampling.slicer import SliceConfig
from svr.sampling.volume import canonicalize

COARSE_GRID = EulerGridConfig(angle_step_deg=45.0, tz_step_mm=10.0, tz_range_mm=20.0)
REPRESENTATIONS = {
    "se3": "se3",
    "posenet": "quat_translation",
    "anchor": "anchor_points",
    "rot6d": "rotation6d_translation",
}


@pytest.fixture(scope="module")
def volume():
    return canonicalize(
        *ellipsoid_brain(32, 2.0, (22, 28, 18), seed=11, texture=3.0, smoothing=1.5)
    )


def small_config(out: Path, representation: str = "se3", steps: int = 6, **kw) -> TrainConfig:
    size = (32, 32)
    return TrainConfig(
        output_dir=str(out),
        model=ModelConfig(
            backbone=BackboneConfig(width=8, depth=2),
            representation=representation,
            input_size=size,
            spacing_mm=2.0,
        ),
        data=SliceDatasetConfig(
            slice=SliceConfig(size=size, spacing_mm=2.0),
            batch_size=8,
            angle_range_deg=30.0,
            tz_range_mm=10.0,
            representation=representation,
        ),
        optim=OptimConfig(lr=3e-3, warmup_steps=0),
        steps=steps,
        checkpoint_every=3,
        log_every=1,
        **kw,
    )


def logged(out: Path) -> list[float]:
    with (out / "log.csv").open() as f:
        return [float(r["loss"]) for r in csv.DictReader(f)]


@pytest.mark.parametrize("loss", sorted(REPRESENTATIONS))
def test_training_reduces_each_loss(volume, tmp_path, loss, monkeypatch):
    """The loop optimises: trained on one fixed batch, the loss on that batch falls."""
    import svr.models.train

    monkeypatch.setattr(
        svr.models.train._StepBatches, "__getitem__", lambda self, i: self.stream.batch(0)
    )
    config = small_config(tmp_path / loss, REPRESENTATIONS[loss], steps=30)
    result = train(config, [volume], progress=False)
    assert len(logged(tmp_path / loss)) == 30 and result.steps_done == 30
    batch = SliceStream([volume], config.data).batch(0)
    criterion = loss_function(config.model.representation)
    torch.manual_seed(config.seed)
    untrained, trained = build_model(config.model), build_model(config.model)
    ckpt = load_checkpoint(result.checkpoint)
    trained.load_state_dict(ckpt.state_dict)
    assert ckpt.config["representation"] == REPRESENTATIONS[loss]
    with torch.no_grad():  # train-mode normalisation, as during the steps
        before = criterion(untrained(batch["slices"]), batch["labels"])
        after = criterion(trained(batch["slices"]), batch["labels"])
    assert after < 0.75 * before


@pytest.mark.parametrize("pose_sampling", ["random", "grid"])
def test_resume_after_a_kill_reproduces_the_run(volume, tmp_path, pose_sampling):
    kw = {"pose_sampling": pose_sampling, "grid": COARSE_GRID}
    straight = train(small_config(tmp_path / "a", **kw), [volume], progress=False)
    # b: the same run, killed after its step-3 checkpoint (the step-6 one never written)
    train(small_config(tmp_path / "b", **kw), [volume], progress=False)
    shutil.rmtree(tmp_path / "b" / "checkpoints" / "step_000000006")
    assert latest_checkpoint(tmp_path / "b" / "checkpoints").name == "step_000000003"
    resumed = train(small_config(tmp_path / "b", **kw), [volume], progress=False)
    a, b = load_checkpoint(straight.checkpoint), load_checkpoint(resumed.checkpoint)
    assert resumed.checkpoint.name == "step_000000006"
    for name, tensor in a.state_dict.items():
        torch.testing.assert_close(b.state_dict[name], tensor, rtol=0, atol=0)


def test_grid_sampling_trains_on_the_shuffled_grid(volume, tmp_path, monkeypatch):
    """With pose_sampling="grid" step s trains on batch s - 1 of the EulerGridStream."""
    import svr.models.train

    trained_on = []
    original = svr.models.train._StepBatches.__getitem__

    def record(self, i):
        batch = original(self, i)
        trained_on.append((type(self.stream), batch["poses"]))
        return batch

    monkeypatch.setattr(svr.models.train._StepBatches, "__getitem__", record)
    config = small_config(tmp_path / "grid", steps=4, pose_sampling="grid", grid=COARSE_GRID)
    result = train(config, [volume], progress=False)
    assert result.steps_done == 4 and len(logged(tmp_path / "grid")) == 4
    stream = EulerGridStream([volume], config.data, COARSE_GRID)
    assert stream.batches_per_pass >= 4
    for step, (kind, poses) in enumerate(trained_on):
        assert kind is EulerGridStream
        torch.testing.assert_close(poses, stream.batch(step)["poses"], rtol=0, atol=0)
    run = load_checkpoint(result.checkpoint).config["training"]["run"]
    assert run["pose_sampling"] == "grid" and run["grid"]["angle_step_deg"] == 45.0


def test_existing_run_is_not_silently_restarted(volume, tmp_path):
    train(small_config(tmp_path / "r", steps=3), [volume], progress=False)
    with pytest.raises(OutputExistsError, match="holds checkpoints of an earlier run") as info:
        train(small_config(tmp_path / "r", steps=3), [volume], resume=False, progress=False)
    assert "--" not in str(info.value)  # the library names no command-line option
    fresh = train(
        small_config(tmp_path / "r", steps=3),
        [volume],
        resume=False,
        overwrite=True,
        progress=False,
    )
    assert fresh.steps_done == 3


def test_train_step_is_one_gradient_step(volume):
    """One step of plain SGD: the loss before the step, parameters moved by -lr x gradient."""
    config = small_config(Path("unused"))
    batch = SliceStream([volume], config.data).batch(0)
    criterion = loss_function(config.model.representation)
    torch.manual_seed(0)
    model = build_model(config.model).train()
    reference = copy.deepcopy(model)
    expected_loss = criterion(reference(batch["slices"]), batch["labels"])
    parameters = list(reference.parameters())
    gradients = torch.autograd.grad(expected_loss, parameters, allow_unused=True)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 0.5**step)
    scaler = torch.amp.GradScaler("cuda", enabled=False)

    loss = train_step(
        model, criterion, optimizer, scaler, batch["slices"], batch["labels"], scheduler
    )
    assert not loss.requires_grad and loss.shape == ()
    torch.testing.assert_close(loss, expected_loss.detach(), rtol=0, atol=0)
    moved = 0
    for after, before, gradient in zip(model.parameters(), parameters, gradients, strict=True):
        if gradient is None:
            assert torch.equal(after, before)
        else:
            torch.testing.assert_close(after, before - 0.1 * gradient)
            moved += int(bool((gradient != 0).any()))
    assert moved > 0
    assert scheduler.get_last_lr() == [0.05]  # the schedule advanced by one step
    train_step(model, criterion, optimizer, scaler, batch["slices"], batch["labels"])
    assert scheduler.get_last_lr() == [0.05]  # no schedule given: left alone


def test_config_validation(tmp_path):
    with pytest.raises(
        ValueError, match=r"'data\.representation' must be equal to 'model\.representation'"
    ):
        TrainConfig(
            output_dir=str(tmp_path),
            model=ModelConfig(representation="se3"),
            data=SliceDatasetConfig(representation="anchor_points"),
        )
    with pytest.raises(
        ValueError, match="'metric_weights' must be None unless the representation is 'se3'"
    ):
        TrainConfig(
            output_dir=str(tmp_path),
            model=ModelConfig(representation="anchor_points"),
            data=SliceDatasetConfig(representation="anchor_points"),
            metric_weights=(1.0,) * 6,
        )
    with pytest.raises(ValueError, match="'steps'"):
        TrainConfig(output_dir=str(tmp_path), steps=0)
    with pytest.raises(ValueError, match="'pose_sampling' must be one of 'random', 'grid'"):
        TrainConfig(output_dir=str(tmp_path), pose_sampling="lattice")
    with pytest.raises(ValueError, match=r"'data\.rotation' must be 'euler'"):
        TrainConfig(
            output_dir=str(tmp_path),
            data=SliceDatasetConfig(rotation="uniform"),
            pose_sampling="grid",
        )


@pytest.fixture(scope="module")
def volume_files(volume, tmp_path_factory):
    folder = tmp_path_factory.mktemp("vol")
    save_nifti(volume.image, folder / "v.nii.gz")
    save_nifti(Image(volume.mask.float(), volume.image.affine), folder / "m.nii.gz")
    return ["--input-volumes", str(folder / "v.nii.gz"), "--input-masks", str(folder / "m.nii.gz")]


TINY = [
    "--size",
    "32",
    "--spacing",
    "2",
    "--width",
    "8",
    "--depth",
    "2",
    "--batch-size",
    "4",
    "--warmup-steps",
    "0",
    "--device",
    "cpu",
    "--quiet",
]


def test_cli_trains_and_resumes(volume_files, tmp_path, capsys):
    out = tmp_path / "run"
    args = [
        "train",
        "--output-dir",
        str(out),
        *volume_files,
        *TINY,
        "--steps",
        "4",
        "--checkpoint-every",
        "2",
        "--loss",
        "anchor",
    ]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["steps"] == 4 and Path(summary["checkpoint"]).name == "step_000000004"
    assert main([*args[:-4], "--steps", "6", "--checkpoint-every", "2", "--loss", "anchor"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["steps"] == 6


@pytest.mark.parametrize(
    ("mode", "planes"),
    [("sagittal", [{"normal": [1.0, 0.0, 0.0], "offset_mm": 0.0}]), ("none", [])],
)
def test_cli_symmetry_is_recorded_in_the_checkpoint(volume_files, tmp_path, capsys, mode, planes):
    out = tmp_path / mode
    args = ["train", "--output-dir", str(out), *volume_files, *TINY, "--steps", "2"]
    assert main([*args, "--symmetry", mode, "--scale-range", "0.9", "1.1"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["symmetry_planes"] == planes
    checkpoint = load_checkpoint(Path(summary["checkpoint"]))
    assert checkpoint.config["model"]["symmetry_planes"] == planes
    assert checkpoint.config["symmetry"]["mode"] == mode
    config = ModelConfig.from_dict(checkpoint.config["model"])
    assert [p.to_dict() for p in config.symmetry_planes] == planes


def test_cli_symmetry_auto_measures_the_volumes(volume_files, tmp_path, capsys):
    out = tmp_path / "auto"
    args = ["train", "--output-dir", str(out), *volume_files, *TINY, "--steps", "1"]
    assert main([*args, "--symmetry", "auto"]) == 0
    captured = capsys.readouterr()
    report = load_checkpoint(Path(json.loads(captured.out.strip().splitlines()[-1])["checkpoint"]))
    volumes = report.config["symmetry"]["volumes"]
    assert len(volumes) == 1
    assert all(0.0 <= v["correlation"] <= 1.0 for v in volumes.values())


def test_scale_augmentation_scales_the_brain(volume):
    config = SliceDatasetConfig(
        slice=SliceConfig(size=(32, 32), spacing_mm=1.5), batch_size=6, min_brain_fraction=0.0
    )
    plain = SliceStream([volume], config).batch(0)
    scaled = SliceStream([volume], dataclasses.replace(config, scale_range=(1.3, 1.4))).batch(0)
    assert not torch.equal(plain["slices"], scaled["slices"])
    with pytest.raises(ValueError, match="scale_range"):
        SliceDatasetConfig(scale_range=(0.0, 1.0))


def test_cli_trains_on_the_paper_grid(volume_files, tmp_path, capsys):
    out = tmp_path / "grid"
    args = ["train", "--output-dir", str(out), *volume_files, *TINY, "--steps", "2"]
    assert main([*args, "--pose-sampling", "grid"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["steps"] == 2
    run = json.loads((out / "train_config.json").read_text())
    assert run["pose_sampling"] == "grid" and run["grid"] == dataclasses.asdict(EulerGridConfig())
    uniform = [*args, "--pose-sampling", "grid", "--rotation", "uniform", "--overwrite"]
    assert main(uniform) == 1
    err = capsys.readouterr().err
    assert "--rotation must be 'euler' for grid pose sampling, got uniform" in err


def test_cli_errors(tmp_path, capsys):
    assert (
        main(["train", "--output-dir", str(tmp_path / "o"), "--input-volumes", "a.nii.gz", *TINY])
        == 1
    )
    assert "must pair up" in capsys.readouterr().err
    assert (
        main(
            [
                "train",
                "--output-dir",
                str(tmp_path / "o"),
                "--atlas-dir",
                str(tmp_path / "none"),
                *TINY,
            ]
        )
        == 1
    )
    assert "is not a folder" in capsys.readouterr().err


def test_cli_says_how_to_restart_a_run(volume_files, tmp_path, capsys):
    args = ["train", "--output-dir", str(tmp_path / "run"), *volume_files, *TINY, "--steps", "1"]
    assert main(args) == 0
    capsys.readouterr()
    assert main([*args, "--no-resume"]) == 1
    err = capsys.readouterr().err
    assert "holds checkpoints; resume, or pass --overwrite" in err and "--no-resume" in err
    assert main([*args, "--no-resume", "--overwrite"]) == 0


def test_ddp_with_two_cpu_processes(volume_files, tmp_path):
    torchrun = Path(sys.executable).parent / "torchrun"
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [
            str(torchrun),
            "--nproc_per_node",
            "2",
            "--master_port",
            "29517",
            "-m",
            "svr",
            "train",
            "--output-dir",
            str(out),
            *volume_files,
            *TINY,
            "--steps",
            "3",
            "--checkpoint-every",
            "3",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert latest_checkpoint(out / "checkpoints").name == "step_000000003"
    assert len(list(out.glob("events.out.tfevents.*"))) == 1  # only rank 0 logs
