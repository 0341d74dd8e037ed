"""Tests of svr.models.checkpoint: round trips, resuming, atomic writes, refusing unsafe files."""

from __future__ import annotations

import copy
import enum
import hashlib
import json
import os
import pickle
import random
import shlex
from collections.abc import Callable
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

import svr
from svr.files import OutputExistsError
from svr.models.checkpoint import (
    CHECKPOINT_CONFIG,
    CHECKPOINT_WEIGHTS,
    FORMAT_VERSION,
    TRAINING_STATE,
    CheckpointError,
    checkpoint_name,
    latest_checkpoint,
    load_checkpoint,
    prune_checkpoints,
    resolve_model_path,
    save_checkpoint,
)

CONFIG = {
    "architecture": {"name": "tiny", "channels": [4, 8]},
    "representation": "se3",
    "input_size": [6, 6],
    "spacing_mm": 0.8,
    "metric_weights": [1.0, 1.0, 1.0, 0.01, 0.01, 0.01],
    "training_data": ["atlas_30wk.nii.gz"],
}


def _model() -> nn.Module:
    """A small CNN with float weights, BatchNorm buffers (incl. int64) and RNG-driven dropout."""
    return nn.Sequential(
        nn.Conv2d(1, 4, 3),
        nn.BatchNorm2d(4),
        nn.ReLU(),
        nn.Dropout(0.3),
        nn.Flatten(),
        nn.Linear(4 * 4 * 4, 3),
    )


def _trained_model() -> nn.Module:
    model = _model()
    model(torch.randn(5, 1, 6, 6))  # update the BatchNorm running stats and num_batches_tracked
    return model


def _train_steps(
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler,
    steps: int,
) -> None:
    model.train()
    for _ in range(steps):
        x, y = torch.randn(8, 1, 6, 6), torch.randn(8, 3)
        loss = nn.functional.mse_loss(model(x), y)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        scheduler.step()


def _rewrite_config(folder: Path, edit: Callable[[dict], None]) -> None:
    file = folder / CHECKPOINT_CONFIG
    config = json.loads(file.read_text())
    edit(config)
    file.write_text(json.dumps(config))


def _rehash(folder: Path, file_name: str, key: str) -> None:
    """Record a tampered file's new hash, so that loading goes past the hash check."""
    digest = hashlib.sha256((folder / file_name).read_bytes()).hexdigest()
    _rewrite_config(folder, lambda c: c["checkpoint"].__setitem__(key, digest))


def _assert_one_line_naming(error: pytest.ExceptionInfo[CheckpointError], path: Path) -> None:
    message = str(error.value)
    assert "\n" not in message
    assert str(path) in message


# --- round trips -----------------------------------------------------------------------------


def test_round_trip_float32(tmp_path: Path) -> None:
    model = _trained_model()
    path = save_checkpoint(tmp_path / "ckpt", model.state_dict(), CONFIG)
    assert path == tmp_path / "ckpt"
    assert sorted(p.name for p in path.iterdir()) == [CHECKPOINT_CONFIG, CHECKPOINT_WEIGHTS]

    ckpt = load_checkpoint(path)
    assert ckpt.path == path
    assert ckpt.training_state is None
    original = model.state_dict()
    assert list(ckpt.state_dict) == list(original)
    for name, tensor in original.items():
        assert ckpt.state_dict[name].dtype == tensor.dtype
        assert torch.equal(ckpt.state_dict[name], tensor), name
    assert ckpt.state_dict["1.num_batches_tracked"].item() == 1
    fresh = _model()
    fresh.load_state_dict(ckpt.state_dict)


def test_half_precision_restores_dtypes(tmp_path: Path) -> None:
    model = _trained_model()
    state = {**model.state_dict(), "double": torch.randn(7, dtype=torch.float64)}
    state["integers"] = torch.arange(5, dtype=torch.int32)
    path = save_checkpoint(tmp_path / "ckpt", state, CONFIG, half_precision=True)

    ckpt = load_checkpoint(path)
    for name, tensor in state.items():
        loaded = ckpt.state_dict[name]
        assert loaded.dtype == tensor.dtype, name
        if tensor.is_floating_point():
            # Exactly float16 rounding, which is within float16's relative precision.
            assert torch.equal(loaded, tensor.to(torch.float16).to(tensor.dtype)), name
            torch.testing.assert_close(loaded, tensor, rtol=2.0**-11, atol=1e-7)
        else:
            assert torch.equal(loaded, tensor), name
    assert ckpt.state_dict["1.num_batches_tracked"].dtype == torch.int64
    assert ckpt.config["checkpoint"]["half_precision"] is True
    assert ckpt.config["checkpoint"]["dtypes"]["double"] == "float64"


def test_half_precision_halves_the_weights_file(tmp_path: Path) -> None:
    state = nn.Linear(256, 256).state_dict()
    full = save_checkpoint(tmp_path / "full", state, CONFIG)
    half = save_checkpoint(tmp_path / "half", state, CONFIG, half_precision=True)
    ratio = (half / CHECKPOINT_WEIGHTS).stat().st_size / (full / CHECKPOINT_WEIGHTS).stat().st_size
    assert 0.48 < ratio < 0.52


def test_half_precision_refuses_float16_overflow(tmp_path: Path) -> None:
    state = {"big": torch.tensor([1.0, 1e5])}
    with pytest.raises(CheckpointError, match="overflows float16") as error:
        save_checkpoint(tmp_path / "ckpt", state, CONFIG, half_precision=True)
    _assert_one_line_naming(error, tmp_path / "ckpt")
    assert list(tmp_path.iterdir()) == []


def test_tied_and_non_contiguous_weights_are_saved(tmp_path: Path) -> None:
    weight = torch.randn(4, 6)
    state = {"encoder": weight, "decoder": weight, "transposed": weight.t(), "row": weight[1]}
    ckpt = load_checkpoint(save_checkpoint(tmp_path / "ckpt", state, CONFIG))
    for name, tensor in state.items():
        assert torch.equal(ckpt.state_dict[name], tensor), name
        assert ckpt.state_dict[name].is_contiguous()


def test_config_round_trip_and_checkpoint_section(tmp_path: Path) -> None:
    before = datetime.now(timezone.utc).replace(microsecond=0)
    path = save_checkpoint(tmp_path / "ckpt", _trained_model().state_dict(), CONFIG)
    ckpt = load_checkpoint(path)

    config = dict(ckpt.config)
    section = config.pop("checkpoint")
    assert config == CONFIG
    assert section["format_version"] == FORMAT_VERSION
    assert section["svr_version"] == svr.__version__
    assert section["torch_version"] == torch.__version__
    created = datetime.strptime(section["created_utc"], "%Y-%m-%dT%H:%M:%SZ")
    created = created.replace(tzinfo=timezone.utc)
    assert before <= created <= datetime.now(timezone.utc) + timedelta(seconds=1)
    assert section["half_precision"] is False
    assert section["dtypes"]["0.weight"] == "float32"
    assert section["dtypes"]["1.num_batches_tracked"] == "int64"
    weights = (path / CHECKPOINT_WEIGHTS).read_bytes()
    assert section["weights_sha256"] == hashlib.sha256(weights).hexdigest()
    assert section["training_state_sha256"] is None


# --- training state and resuming -------------------------------------------------------------


def _lambda_lr(optimizer: torch.optim.Optimizer) -> torch.optim.lr_scheduler.LRScheduler:
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: min(1.0, (step + 1) / 4))


def _warmup_cosine(optimizer: torch.optim.Optimizer) -> torch.optim.lr_scheduler.LRScheduler:
    warmup = torch.optim.lr_scheduler.LinearLR(optimizer, 0.1, total_iters=2)
    cosine = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=10)
    return torch.optim.lr_scheduler.SequentialLR(optimizer, [warmup, cosine], milestones=[2])


@pytest.mark.parametrize("make_scheduler", [_lambda_lr, _warmup_cosine])
def test_resuming_continues_exactly_as_uninterrupted_training(
    tmp_path: Path,
    make_scheduler: Callable[[torch.optim.Optimizer], torch.optim.lr_scheduler.LRScheduler],
) -> None:
    model = _model()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.1)
    scheduler = make_scheduler(optimizer)
    _train_steps(model, optimizer, scheduler, 3)
    numpy_rng = np.random.default_rng(7)
    state = {
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict(),
        "step": 3,
        "epoch": 0,
        "rng": {
            "torch": torch.get_rng_state(),
            "python": random.getstate(),
            "numpy": numpy_rng.bit_generator.state,
        },
    }
    path = save_checkpoint(tmp_path / "ckpt", model.state_dict(), CONFIG, training_state=state)
    assert (path / TRAINING_STATE).is_file()
    _train_steps(model, optimizer, scheduler, 2)  # the uninterrupted run
    expected_weights = copy.deepcopy(model.state_dict())
    expected_lr = scheduler.get_last_lr()

    torch.manual_seed(12345)  # a different RNG state: resuming must restore it
    ckpt = load_checkpoint(path, with_training_state=True)
    assert ckpt.training_state is not None
    assert ckpt.training_state["step"] == 3
    assert ckpt.training_state["rng"]["python"] == state["rng"]["python"]
    assert ckpt.training_state["rng"]["numpy"] == numpy_rng.bit_generator.state
    resumed = _model()
    resumed.load_state_dict(ckpt.state_dict)
    resumed_optimizer = torch.optim.AdamW(resumed.parameters(), lr=1e-2, weight_decay=0.1)
    resumed_scheduler = make_scheduler(resumed_optimizer)
    resumed_optimizer.load_state_dict(ckpt.training_state["optimizer"])
    resumed_scheduler.load_state_dict(ckpt.training_state["scheduler"])
    torch.set_rng_state(ckpt.training_state["rng"]["torch"])
    _train_steps(resumed, resumed_optimizer, resumed_scheduler, 2)

    assert resumed_scheduler.get_last_lr() == expected_lr
    for name, tensor in expected_weights.items():
        assert torch.equal(resumed.state_dict()[name], tensor), name


class _Colour(enum.IntEnum):
    RED = 1


@pytest.mark.parametrize(
    ("bad_state", "where"),
    [
        ({"rng": {"numpy": np.random.get_state()}}, "training_state['rng']['numpy'][1]"),
        ({"schedule": lambda step: step}, "training_state['schedule']"),
        ({"model": nn.Linear(2, 2)}, "training_state['model']"),
        ({"seen": {1, 2}}, "training_state['seen']"),
        ({"colour": _Colour.RED}, "training_state['colour']"),
        ({"history": [1.0, np.float64(2.0)]}, "training_state['history'][1]"),
        ({(1, 2): 3}, "training_state has a key of type tuple"),
    ],
)
def test_save_refuses_other_objects_in_the_training_state(
    tmp_path: Path, bad_state: dict, where: str
) -> None:
    with pytest.raises(CheckpointError) as error:
        save_checkpoint(tmp_path / "ckpt", {"w": torch.ones(2)}, CONFIG, training_state=bad_state)
    assert where in str(error.value)
    _assert_one_line_naming(error, tmp_path / "ckpt")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("state_dict", "config", "match"),
    [
        ({"w": torch.ones(2)}, {"checkpoint": 1}, "reserved"),
        ({"w": torch.ones(2)}, {"output": Path("x")}, "not JSON-serialisable"),
        ({"w": torch.ones(2)}, {"loss": float("nan")}, "not JSON-serialisable"),
        ({"w": [1.0, 2.0]}, CONFIG, "'w' is a list, not a tensor"),
        ({"w": torch.eye(2).to_sparse()}, CONFIG, "not dense"),
    ],
)
def test_save_refuses_invalid_weights_and_configs(
    tmp_path: Path, state_dict: dict, config: dict, match: str
) -> None:
    with pytest.raises(CheckpointError, match=match) as error:
        save_checkpoint(tmp_path / "ckpt", state_dict, config)
    _assert_one_line_naming(error, tmp_path / "ckpt")
    assert list(tmp_path.iterdir()) == []


# --- atomic writes ---------------------------------------------------------------------------


def test_refuses_to_overwrite_and_leaves_no_temporary_folder(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "ckpt", {"w": torch.zeros(3)}, CONFIG)
    with pytest.raises(OutputExistsError):
        save_checkpoint(path, {"w": torch.ones(3)}, CONFIG)
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt"]
    assert torch.equal(load_checkpoint(path).state_dict["w"], torch.zeros(3))

    save_checkpoint(path, {"w": torch.ones(3)}, CONFIG, overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt"]
    assert torch.equal(load_checkpoint(path).state_dict["w"], torch.ones(3))


# --- resuming: latest and pruning ------------------------------------------------------------


def _save_steps(folder: Path, steps: list[int]) -> None:
    folder.mkdir(exist_ok=True)
    for step in steps:
        state = {"w": torch.full((3,), float(step))}
        save_checkpoint(
            folder / checkpoint_name(step), state, CONFIG, training_state={"step": step}
        )


def test_checkpoint_name() -> None:
    assert checkpoint_name(0) == "step_000000000"
    assert checkpoint_name(123) == "step_000000123"
    assert checkpoint_name(10**10) == "step_10000000000"
    with pytest.raises(ValueError, match=">= 0"):
        checkpoint_name(-1)


def test_latest_checkpoint_skips_corrupt_partial_and_temporary_folders(tmp_path: Path) -> None:
    folder = tmp_path / "checkpoints"
    assert latest_checkpoint(folder) is None  # no run yet
    folder.mkdir()
    assert latest_checkpoint(folder) is None
    _save_steps(folder, [1, 5, 10, 10**9])
    assert latest_checkpoint(folder) == folder / checkpoint_name(10**9)  # numeric, not by name

    (folder / checkpoint_name(10**9) / TRAINING_STATE).unlink()
    weights = folder / checkpoint_name(10) / CHECKPOINT_WEIGHTS
    weights.write_bytes(weights.read_bytes()[:-10])  # truncated
    (folder / checkpoint_name(20)).mkdir()  # a folder with nothing in it
    (folder / f".{checkpoint_name(30)}.x1y2z3").mkdir()  # an interrupted atomic write
    (folder / "notes").mkdir()
    (folder / checkpoint_name(40)).write_text("not a folder")
    assert latest_checkpoint(folder) == folder / checkpoint_name(5)

    with pytest.raises(CheckpointError, match="not a folder") as error:
        latest_checkpoint(folder / checkpoint_name(40))
    _assert_one_line_naming(error, folder / checkpoint_name(40))


def test_prune_checkpoints_keeps_the_newest_complete_ones(tmp_path: Path) -> None:
    folder = tmp_path / "checkpoints"
    _save_steps(folder, [1, 2, 3, 4, 5, 6])
    temporary = folder / f".{checkpoint_name(7)}.abc123"
    temporary.mkdir()  # possibly a write in progress: never touched
    (folder / checkpoint_name(6) / CHECKPOINT_CONFIG).write_text("{")  # corrupt newest

    prune_checkpoints(folder, keep=2)
    names = {checkpoint_name(step) for step in (4, 5, 6)} | {temporary.name}
    assert {p.name for p in folder.iterdir()} == names
    assert latest_checkpoint(folder) == folder / checkpoint_name(5)

    prune_checkpoints(folder, keep=5)  # fewer complete ones than that: nothing removed
    assert {p.name for p in folder.iterdir()} == names
    prune_checkpoints(tmp_path / "missing", keep=1)
    with pytest.raises(ValueError, match="keep"):
        prune_checkpoints(folder, keep=0)


# --- loading errors --------------------------------------------------------------------------


def _truncate_weights_keeping_hash(folder: Path) -> None:
    file = folder / CHECKPOINT_WEIGHTS
    file.write_bytes(file.read_bytes()[:-16])
    _rehash(folder, CHECKPOINT_WEIGHTS, "weights_sha256")


def _garble_weights_header_keeping_hash(folder: Path) -> None:
    file = folder / CHECKPOINT_WEIGHTS
    data = file.read_bytes()
    file.write_bytes(data[:8] + b"#" * 16 + data[24:])
    _rehash(folder, CHECKPOINT_WEIGHTS, "weights_sha256")


def _flip_a_weight_byte(folder: Path) -> None:
    file = folder / CHECKPOINT_WEIGHTS
    data = bytearray(file.read_bytes())
    data[-1] ^= 0xFF
    file.write_bytes(bytes(data))


def _garble_training_state_keeping_hash(folder: Path) -> None:
    (folder / TRAINING_STATE).write_bytes(b"not a torch file")
    _rehash(folder, TRAINING_STATE, "training_state_sha256")


def _truncate_training_state_keeping_hash(folder: Path) -> None:
    file = folder / TRAINING_STATE
    file.write_bytes(file.read_bytes()[:100])
    _rehash(folder, TRAINING_STATE, "training_state_sha256")


LOAD_ERRORS = {
    "missing config": (lambda f: (f / CHECKPOINT_CONFIG).unlink(), "missing config.json"),
    "missing weights": (lambda f: (f / CHECKPOINT_WEIGHTS).unlink(), "missing model.safetensors"),
    "missing training state": (lambda f: (f / TRAINING_STATE).unlink(), "missing training_state"),
    "config not JSON": (lambda f: (f / CHECKPOINT_CONFIG).write_text("{'a': 1"), "not valid JSON"),
    "config not UTF-8": (lambda f: (f / CHECKPOINT_CONFIG).write_bytes(b"\xff\xfe\xfa"), "JSON"),
    "config a list": (lambda f: (f / CHECKPOINT_CONFIG).write_text("[1]"), 'no "checkpoint"'),
    "no section": (
        lambda f: _rewrite_config(f, lambda c: c.pop("checkpoint")),
        'no "checkpoint" section',
    ),
    "newer format": (
        lambda f: _rewrite_config(f, lambda c: c["checkpoint"].update(format_version=99)),
        "format version 99 is not supported",
    ),
    "no weights hash": (
        lambda f: _rewrite_config(f, lambda c: c["checkpoint"].pop("weights_sha256")),
        "no SHA-256 for model.safetensors",
    ),
    "weights modified": (_flip_a_weight_byte, "model.safetensors: does not match its SHA-256"),
    "weights truncated": (_truncate_weights_keeping_hash, "corrupted safetensors file"),
    "weights header garbled": (_garble_weights_header_keeping_hash, "corrupted safetensors file"),
    "training state modified": (
        lambda f: (f / TRAINING_STATE).write_bytes(b"x"),
        "training_state.pt: does not match its SHA-256",
    ),
    "training state garbled": (_garble_training_state_keeping_hash, "refused by the safe"),
    "training state truncated": (_truncate_training_state_keeping_hash, "unreadable training"),
}


@pytest.mark.parametrize("case", list(LOAD_ERRORS))
def test_load_reports_damaged_checkpoints(tmp_path: Path, case: str) -> None:
    damage, match = LOAD_ERRORS[case]
    path = save_checkpoint(
        tmp_path / "ckpt", _model().state_dict(), CONFIG, training_state={"step": 3}
    )
    damage(path)
    with pytest.raises(CheckpointError, match=match) as error:
        load_checkpoint(path, with_training_state=True)
    _assert_one_line_naming(error, path)


def test_load_reports_missing_folders_and_files(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="does not exist") as error:
        load_checkpoint(tmp_path / "nowhere")
    _assert_one_line_naming(error, tmp_path / "nowhere")
    file = tmp_path / "model.pt"
    file.write_bytes(b"")
    with pytest.raises(CheckpointError, match="not a checkpoint folder") as error:
        load_checkpoint(file)
    _assert_one_line_naming(error, file)


def test_load_without_a_saved_training_state(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "ckpt", {"w": torch.ones(2)}, CONFIG)
    assert load_checkpoint(path).training_state is None
    with pytest.raises(CheckpointError, match="saved without a training state") as error:
        load_checkpoint(path, with_training_state=True)
    _assert_one_line_naming(error, path)


class _Payload:
    """Unpickling this runs a shell command that creates ``marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Callable[[str], int], tuple[str]]:
        return os.system, (f"touch {shlex.quote(str(self.marker))}",)


@pytest.mark.parametrize("zip_format", [True, False])
@pytest.mark.parametrize("hash_updated", [True, False])
def test_training_state_with_code_is_refused_and_not_run(
    tmp_path: Path, zip_format: bool, hash_updated: bool
) -> None:
    control = tmp_path / "control_marker"
    pickle.loads(pickle.dumps(_Payload(control)))  # an ordinary unpickler runs the payload
    assert control.exists()

    path = save_checkpoint(
        tmp_path / "ckpt", {"w": torch.ones(2)}, CONFIG, training_state={"step": 3}
    )
    marker = tmp_path / "marker"
    torch.save(
        {"step": 3, "optimizer": _Payload(marker)},
        path / TRAINING_STATE,
        _use_new_zipfile_serialization=zip_format,
    )
    if hash_updated:  # an attacker who also rewrote config.json: the unpickler must refuse
        _rehash(path, TRAINING_STATE, "training_state_sha256")
    match = "refused by the safe unpickler" if hash_updated else "does not match its SHA-256"
    with pytest.raises(CheckpointError, match=match) as error:
        load_checkpoint(path, with_training_state=True)
    _assert_one_line_naming(error, path)
    assert not marker.exists()
    assert load_checkpoint(path).training_state is None  # the state is not read unless asked
    assert not marker.exists()


@pytest.mark.parametrize("device", ["gpu", "cuda:abc", "cpu:x", 3.5])
def test_load_rejects_invalid_devices(tmp_path: Path, device: object) -> None:
    path = save_checkpoint(tmp_path / "ckpt", {"w": torch.ones(2)}, CONFIG)
    with pytest.raises(CheckpointError, match="not a usable device") as error:
        load_checkpoint(path, map_location=device)  # type: ignore[arg-type]
    _assert_one_line_naming(error, path)


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_load_rejects_an_unavailable_device(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "ckpt", {"w": torch.ones(2)}, CONFIG)
    with pytest.raises(CheckpointError, match="'cuda' is not a usable device") as error:
        load_checkpoint(path, map_location="cuda")
    _assert_one_line_naming(error, path)


def test_load_accepts_device_objects(tmp_path: Path) -> None:
    path = save_checkpoint(tmp_path / "ckpt", {"w": torch.ones(2)}, CONFIG)
    ckpt = load_checkpoint(path, map_location=torch.device("cpu"))
    assert ckpt.state_dict["w"].device == torch.device("cpu")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_load_onto_cuda_restores_half_precision(tmp_path: Path) -> None:
    state = {"w": torch.randn(5), "n": torch.tensor(3)}
    path = save_checkpoint(
        tmp_path / "ckpt", state, CONFIG, half_precision=True, training_state={"t": torch.ones(1)}
    )
    ckpt = load_checkpoint(path, map_location="cuda", with_training_state=True)
    assert ckpt.state_dict["w"].is_cuda and ckpt.state_dict["w"].dtype == torch.float32
    assert ckpt.training_state is not None and ckpt.training_state["t"].is_cuda


def test_checkpoint_error_pickles() -> None:
    error = CheckpointError("/runs/a/step_000000001", "missing config.json")
    copy_ = pickle.loads(pickle.dumps(error))
    assert (copy_.path, copy_.problem, str(copy_)) == (error.path, error.problem, str(error))
    assert isinstance(copy_, ValueError)


def test_resolve_model_path_has_one_meaning(tmp_path: Path) -> None:
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    _save_steps(run / "checkpoints", [3, 12])
    newest = run / "checkpoints" / checkpoint_name(12)
    assert resolve_model_path(run) == newest  # a training run: its newest checkpoint
    assert resolve_model_path(run / "checkpoints") == newest  # a folder of step_*/
    assert resolve_model_path(str(newest)) == newest  # a checkpoint itself
    with pytest.raises(CheckpointError, match="checkpoint folder does not exist") as info:
        resolve_model_path(tmp_path / "missing")
    assert info.value.path == tmp_path / "missing"
    (tmp_path / "file").write_text("x")
    with pytest.raises(CheckpointError, match="not a checkpoint folder"):
        resolve_model_path(tmp_path / "file")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match=r"missing config\.json, and no step_"):
        resolve_model_path(tmp_path / "empty")
