"""The shipped model: float16 export with provenance, loading by name, and safe loading."""

from __future__ import annotations

import hashlib
import json
import pickle
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from synthetic import ellipsoid_brain

import svr
import svr.models.pretrained
import svr.models.pretrained.export
from svr.cli import main
from svr.files import OutputExistsError
from svr.image import Image, save_nifti
from svr.metrics import pose_errors
from svr.models.backbones import BackboneConfig
from svr.models.checkpoint import (
    CHECKPOINT_CONFIG,
    CHECKPOINT_WEIGHTS,
    TRAINING_STATE,
    CheckpointError,
    resolve_model_path,
    save_checkpoint,
)
from svr.models.network import ModelConfig, build_model, checkpoint_model_config
from svr.models.predict import load_pose_model
from svr.models.pretrained import DEFAULT_MODEL, MAX_MODEL_BYTES, default_model_path
from svr.models.pretrained.export import export_model

CONFIG = ModelConfig(backbone=BackboneConfig(width=8, depth=2), input_size=(32, 32), spacing_mm=2.0)
PROVENANCE = {
    "training_command": "svr train --output-dir runs/tiny --steps 2",
    "data": {"name": "ellipsoid", "licence": "CC0 1.0"},
    "steps": 2,
}


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A tiny float32 checkpoint as svr train writes it, whose head predicts varied poses."""
    torch.manual_seed(3)
    model = build_model(CONFIG)
    torch.nn.init.normal_(model.head.linear.weight, std=0.5)
    config = {
        **checkpoint_model_config(CONFIG),
        "metric_weights": None,
        "training": {"step": 2, "steps": 2, "data_sources": ["ellipsoid"]},
    }
    folder = tmp_path_factory.mktemp("run") / "step_000000002"
    return save_checkpoint(folder, model.state_dict(), config, training_state={"step": 2})


@pytest.fixture(scope="module")
def exported(checkpoint, tmp_path_factory) -> Path:
    return export_model(
        checkpoint, tmp_path_factory.mktemp("export") / "tiny", provenance=PROVENANCE
    )


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_export_writes_a_small_float16_model_with_its_provenance(checkpoint, exported):
    assert sorted(p.name for p in exported.iterdir()) == [CHECKPOINT_CONFIG, CHECKPOINT_WEIGHTS]
    weights = exported / CHECKPOINT_WEIGHTS
    total = weights.stat().st_size + (exported / CHECKPOINT_CONFIG).stat().st_size
    assert total <= MAX_MODEL_BYTES
    assert weights.stat().st_size < 0.6 * (checkpoint / CHECKPOINT_WEIGHTS).stat().st_size
    with safe_open(weights, framework="pt") as f:
        dtypes = {f.get_tensor(name).dtype for name in f.keys()}  # noqa: SIM118
    assert torch.float16 in dtypes and torch.float32 not in dtypes
    config = json.loads((exported / CHECKPOINT_CONFIG).read_text())
    source = json.loads((checkpoint / CHECKPOINT_CONFIG).read_text())
    assert config["model"] == source["model"] == CONFIG.to_dict()
    assert config["provenance"] == PROVENANCE
    assert config["training"] == source["training"]
    export = config["export"]
    assert export["source_step"] == 2 and export["weights_dtype"] == "float16"
    assert export["source_weights_sha256"] == source["checkpoint"]["weights_sha256"]
    assert set(export["versions"]) == {"fetal_svr", "torch", "safetensors", "numpy", "python"}
    assert config["checkpoint"]["half_precision"] is True
    assert not (exported / TRAINING_STATE).exists()


def test_round_trip_matches_the_float32_model_to_float16_precision(checkpoint, exported):
    full = load_pose_model(checkpoint)
    half = load_pose_model(exported)
    assert half.config == full.config == CONFIG and not half.training
    for (name, a), b in zip(half.state_dict().items(), full.state_dict().values(), strict=True):
        assert a.dtype == b.dtype, name  # cast back to float32 on loading
        if a.is_floating_point():  # the weights are the float32 ones rounded to float16
            torch.testing.assert_close(a, b.half().float(), rtol=0, atol=0)
    slices = torch.rand(16, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    errors = pose_errors(half.predict_poses(slices), full.predict_poses(slices))
    assert float(errors["rotation_deg"].max()) < 0.5
    assert float(errors["translation_mm"].max()) < 0.5


def test_export_refuses_to_overwrite(checkpoint, exported):
    before = sha256(exported / CHECKPOINT_WEIGHTS)
    with pytest.raises(OutputExistsError, match="output exists"):
        export_model(checkpoint, exported, provenance=PROVENANCE)
    assert sha256(exported / CHECKPOINT_WEIGHTS) == before
    with pytest.raises(ValueError, match="is the checkpoint folder itself"):
        export_model(checkpoint, checkpoint, provenance=PROVENANCE, overwrite=True)


def test_export_overwrites_when_asked(checkpoint, tmp_path):
    out = tmp_path / "model"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    assert export_model(checkpoint, out, provenance=PROVENANCE, overwrite=True) == out
    assert not (out / "stale.txt").exists() and (out / CHECKPOINT_WEIGHTS).is_file()


@pytest.mark.parametrize(
    ("provenance", "message"),
    [
        ({"data": "x"}, "missing or empty: training_command"),
        ({"training_command": "svr train", "data": ""}, "missing or empty: data"),
        ([("training_command", "x")], "provenance must be a dict"),
        ({**PROVENANCE, "when": object()}, "not JSON-serialisable"),
    ],
)
def test_export_needs_provenance(checkpoint, tmp_path, provenance, message):
    with pytest.raises(CheckpointError, match=message):
        export_model(checkpoint, tmp_path / "model", provenance=provenance)
    assert not (tmp_path / "model").exists()


def test_export_refuses_a_model_over_the_size_limit(checkpoint, tmp_path, monkeypatch):
    monkeypatch.setattr(svr.models.pretrained.export, "MAX_MODEL_BYTES", 20_000)
    with pytest.raises(CheckpointError, match=r"must stay within 0\.02 MB"):
        export_model(checkpoint, tmp_path / "model", provenance=PROVENANCE)
    assert not (tmp_path / "model").exists()


def test_export_refuses_a_checkpoint_without_a_model(tmp_path):
    source = save_checkpoint(tmp_path / "other", {"w": torch.zeros(2)}, {"name": "not a model"})
    with pytest.raises(CheckpointError, match='no "model" section'):
        export_model(source, tmp_path / "model", provenance=PROVENANCE)


def test_a_pickle_in_the_weights_file_is_refused_without_running_it(exported, tmp_path):
    """A weights file replaced by a pickle (its hash updated to match) is not unpickled."""
    folder = tmp_path / "evil"
    folder.mkdir()
    marker = tmp_path / "code_ran"

    class Payload:
        def __reduce__(self):
            return open, (str(marker), "w")

    weights = folder / CHECKPOINT_WEIGHTS
    weights.write_bytes(pickle.dumps({"backbone.stem.0.weight": Payload()}))
    config = json.loads((exported / CHECKPOINT_CONFIG).read_text())
    config["checkpoint"]["weights_sha256"] = sha256(weights)
    (folder / CHECKPOINT_CONFIG).write_text(json.dumps(config))
    with pytest.raises(CheckpointError, match="corrupted safetensors file") as info:
        load_pose_model(folder)
    assert info.value.path == weights
    assert not marker.exists()


def test_default_names_the_shipped_folder_and_paths_stay_paths(tmp_path, monkeypatch):
    folder = default_model_path()
    assert folder.parent == Path(svr.models.pretrained.__file__).parent
    assert folder.name == DEFAULT_MODEL
    assert resolve_model_path(DEFAULT_MODEL) == folder
    monkeypatch.chdir(tmp_path)
    (tmp_path / "default").mkdir()
    (tmp_path / "default" / "config.json").write_text("{}")
    assert resolve_model_path("./default") == Path("default")
    assert resolve_model_path(Path("default")) == Path("default")


def test_default_without_shipped_weights_is_a_clear_error(tmp_path, monkeypatch):
    empty = tmp_path / "default"
    empty.mkdir()
    monkeypatch.setattr(svr.models.pretrained, "default_model_path", lambda: empty)
    with pytest.raises(CheckpointError, match="default model is not installed") as info:
        load_pose_model(DEFAULT_MODEL)
    assert info.value.path == empty


def test_default_loads_the_folder_it_resolves_to(exported, monkeypatch):
    monkeypatch.setattr(svr.models.pretrained, "default_model_path", lambda: exported)
    model = load_pose_model(DEFAULT_MODEL)
    assert model.config == CONFIG and not model.training


def test_the_shipped_model_loads():
    if not (default_model_path() / CHECKPOINT_WEIGHTS).is_file():
        pytest.skip(
            f"no shipped weights in {default_model_path()} (export them with "
            "benchmarks/export_default_model.py)"
        )
    model = load_pose_model(DEFAULT_MODEL)
    assert all(p.dtype == torch.float32 for p in model.parameters())
    size = sum(p.stat().st_size for p in default_model_path().iterdir() if p.suffix != ".md")
    assert size <= MAX_MODEL_BYTES
    provenance = json.loads((default_model_path() / CHECKPOINT_CONFIG).read_text())["provenance"]
    assert "sb-fidon2021" in json.dumps(provenance["data"]) and provenance["training_command"]
    slices = torch.rand(2, 1, *model.config.input_size)
    assert model.predict_poses(slices).shape == (2, 6)


def test_cli_predict_and_evaluate_take_default(exported, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(svr.models.pretrained, "default_model_path", lambda: exported)
    volume, mask = ellipsoid_brain(24, 2.0, (16, 18, 14), seed=5)
    save_nifti(volume, tmp_path / "brain.nii.gz")
    save_nifti(mask, tmp_path / "mask.nii.gz")
    stack = tmp_path / "stack.nii.gz"
    save_nifti(Image(volume.data[:, :, ::3].contiguous(), volume.affine), stack)
    poses = tmp_path / "poses.csv"
    args = ["predict", "--model", "default", "--input-stacks", str(stack), "--quiet"]
    assert main([*args, "--output-poses", str(poses)]) == 0
    assert len(poses.read_text().splitlines()) == 1 + 8
    report = tmp_path / "report"
    evaluate = ["evaluate", "--checkpoints", "default", "--output-dir", str(report)]
    volumes = ["--input-volumes", str(tmp_path / "brain.nii.gz")]
    masks = ["--input-masks", str(tmp_path / "mask.nii.gz")]
    assert main([*evaluate, *volumes, *masks, "--num-slices", "4", "--device", "cpu", "-q"]) == 0
    info = json.loads((report / "evaluation.json").read_text())
    assert info["checkpoints"] == {"default": str(exported)}
    capsys.readouterr()
    monkeypatch.setattr(svr.models.pretrained, "default_model_path", lambda: tmp_path / "none")
    assert main([*args, "--output-poses", str(tmp_path / "other.csv")]) == 1
    err = capsys.readouterr().err
    assert "default model is not installed" in err and err.count("\n") == 1


def test_stack_pose_export_round_trip_and_size_limit(tmp_path, monkeypatch):
    from svr.models.pretrained.export import export_stack_pose_model
    from svr.models.stack_pose import StackPoseConfig, StackPoseNet, load_stack_pose_model

    torch.manual_seed(5)
    net = StackPoseNet(StackPoseConfig(width=4, grid_size=16))
    torch.nn.init.normal_(net.pose.linear.weight, std=0.1)
    config = {"architecture": "stack_pose", "model": net.config.to_dict()}
    source = save_checkpoint(tmp_path / "step_000000001", net.state_dict(), config)
    out = export_stack_pose_model(source, tmp_path / "model", provenance=PROVENANCE)
    exported = json.loads((out / CHECKPOINT_CONFIG).read_text())
    assert exported["provenance"] == PROVENANCE
    assert exported["export"]["weights_dtype"] == "float16"
    assert exported["export"]["versions"]["fetal_svr"] == svr.__version__
    loaded = load_stack_pose_model(out)
    for a, b in zip(net.state_dict().values(), loaded.state_dict().values(), strict=True):
        assert torch.allclose(a.float(), b.float(), atol=2e-3, rtol=1e-3)
    monkeypatch.setattr(svr.models.pretrained.export, "MAX_MODEL_BYTES", 20_000)
    with pytest.raises(CheckpointError, match=r"must stay within 0\.02 MB"):
        export_stack_pose_model(source, tmp_path / "too-big", provenance=PROVENANCE)
    assert not (tmp_path / "too-big").exists()
