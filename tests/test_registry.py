"""The registry of pose representations is the single source of the representations.

Oracles: the persisted and command-line names and label sizes written out by hand (they are
stored in checkpoint configs and scripts, so they must not change), the :mod:`svr.geometry`
converters and :mod:`svr.losses` for the entries, and a fake representation registered only in
the registry (``monkeypatch``), which every consumer must then accept without other changes.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
from typing import get_args

import pytest
import torch
from torch import Tensor

import svr.cli.train as train_cli
import svr.geometry as g
from svr.cli import build_parser
from svr.geometry.mirror import SAGITTAL, mirror_twin
from svr.losses import anchor_point_loss, posenet_loss, rotation_6d_loss, se3_geodesic_loss
from svr.models import heads
from svr.models.backbones import BackboneConfig
from svr.models.heads import PoseHead
from svr.models.network import ModelConfig, build_model, loss_function
from svr.representation_registry import (
    REPRESENTATIONS,
    PoseRepresentation,
    Representation,
    get_representation,
    representations_by_cli_name,
)
from svr.sampling import dataset, poses
from svr.sampling.dataset import SliceDatasetConfig
from svr.sampling.poses import pose_labels, random_slice_poses

F64 = torch.float64
PERSISTED = {  # name: (CLI name, label size)
    "se3": ("se3", 6),
    "quat_translation": ("posenet", 7),
    "anchor_points": ("anchor", 9),
    "rotation6d_translation": ("rot6d", 9),
}
LOSSES = {
    "se3": se3_geodesic_loss,
    "quat_translation": posenet_loss,
    "anchor_points": anchor_point_loss,
    "rotation6d_translation": rotation_6d_loss,
}


def random_poses(n: int, seed: int) -> Tensor:
    return random_slice_poses(n, torch.Generator().manual_seed(seed), rotation="uniform")


# ----------------------------------------------------------------------------- the entries


def test_names_sizes_and_cli_names_are_the_persisted_ones():
    assert {n: (e.cli_name, e.size) for n, e in REPRESENTATIONS.items()} == PERSISTED
    assert list(REPRESENTATIONS) == list(PERSISTED)  # order (parametrisations, messages)
    assert all(name == entry.name for name, entry in REPRESENTATIONS.items())
    assert get_args(Representation) == tuple(REPRESENTATIONS)
    by_cli = representations_by_cli_name()
    assert {cli: e.name for cli, e in by_cli.items()} == {c: n for n, (c, _) in PERSISTED.items()}


@pytest.mark.parametrize("name", list(PERSISTED))
def test_encode_decode_scale_and_loss_of_each_entry(name):
    entry = REPRESENTATIONS[name]
    p = random_poses(64, seed=1).reshape(8, 8, 6)
    for a in (60.0, 25.0):
        labels = entry.encode(p, a)
        assert labels.shape == (8, 8, entry.size) and labels.dtype == F64
        back = entry.decode(labels, a)
        assert back.shape == p.shape and (back[..., :3].norm(dim=-1) <= torch.pi + 1e-12).all()
        torch.testing.assert_close(g.vector_to_se3(back), g.vector_to_se3(p))
    scale = entry.output_scale(30.0, 60.0)
    assert scale.shape == (entry.size,) and (scale > 0).all()
    torch.testing.assert_close(
        entry.decode(entry.encode(torch.zeros(6, dtype=F64), 60.0), 60.0), torch.zeros(6, dtype=F64)
    )
    pred, target = entry.encode(random_poses(16, 2), 60.0), entry.encode(random_poses(16, 3), 60.0)
    loss = entry.loss(None, 60.0)
    torch.testing.assert_close(loss(pred, target), LOSSES[name](pred, target))
    assert loss(pred, target, reduction="none").shape == (16,)
    assert entry.metric_weights == (name == "se3")


def test_unknown_names_are_rejected_with_the_valid_names():
    for bad in ("euler", "SE3", ["se3"], None):
        with pytest.raises(ValueError, match=r"Owner: 'representation' must be one of se3, quat"):
            get_representation(bad, "Owner")


@pytest.mark.parametrize(
    ("changes", "field"),
    [({"name": ""}, "name"), ({"cli_name": 3}, "cli_name"), ({"size": 0}, "size")],
)
def test_entry_validation(changes, field):
    with pytest.raises(ValueError, match=f"PoseRepresentation: '{field}'"):
        dataclasses.replace(REPRESENTATIONS["se3"], **changes)


def test_the_old_lists_are_gone():
    """One home: no copy of the list, the sizes or the CLI names is left in the consumers."""
    assert not hasattr(poses, "REPRESENTATIONS")
    assert not hasattr(heads, "OUTPUT_SIZES") and not hasattr(heads, "check_representation")
    assert not hasattr(dataset, "_check_representation")
    assert not hasattr(train_cli, "LOSSES")


def test_cli_loss_choices_come_from_the_registry():
    parser = build_parser()
    train = next(
        a for a in parser._subparsers._group_actions if isinstance(a, argparse._SubParsersAction)
    ).choices["train"]
    loss = next(a for a in train._actions if a.dest == "loss")
    # Read from the registry when the option is parsed (no copy of the names in the CLI).
    for name, _ in PERSISTED.values():
        assert loss.type(name) == name
    with pytest.raises(argparse.ArgumentTypeError, match="choose from 'anchor', 'posenet'"):
        loss.type("matrix")


# ----------------------------------------------------------------------------- a fake entry


def _matrix_encode(p: Tensor, a: float) -> Tensor:
    return torch.cat([g.so3_exp(p[..., :3]).flatten(-2), p[..., 3:] / 10.0], dim=-1)


def _matrix_decode(labels: Tensor, a: float) -> Tensor:
    columns = labels[..., :9].unflatten(-1, (3, 3)).transpose(-1, -2)  # rows: the columns of R
    R = g.rotation_6d_to_matrix(columns[..., :2, :].flatten(-2))
    return torch.cat([g.so3_log(R), labels[..., 9:] * 10.0], dim=-1)


def _matrix_loss(pred: Tensor, target: Tensor, reduction: str = "mean") -> Tensor:
    loss = (pred - target).square().sum(-1)
    return {"mean": loss.mean, "sum": loss.sum, "none": lambda: loss}[reduction]()


FAKE = PoseRepresentation(
    name="matrix_cm",
    cli_name="matrix",
    size=12,
    encode=_matrix_encode,  # the rotation matrix (row-major) and the translation in cm
    decode=_matrix_decode,
    loss=lambda weights, a: _matrix_loss,
    output_scale=lambda translation_scale_mm, a: torch.ones(12),
)


@pytest.fixture
def fake(monkeypatch):
    monkeypatch.setitem(REPRESENTATIONS, FAKE.name, FAKE)
    return FAKE


def test_a_registered_representation_gives_labels_and_a_head(fake):
    p = random_poses(20, seed=4)
    labels = pose_labels(p, "matrix_cm")
    torch.testing.assert_close(labels, _matrix_encode(p, 60.0))
    head = PoseHead(8, "matrix_cm").double()
    assert head.linear.out_features == 12
    torch.testing.assert_close(head(torch.randn(3, 8, dtype=F64)), _matrix_encode(0 * p[:3], 60.0))
    torch.testing.assert_close(g.vector_to_se3(head.to_pose(labels)), g.vector_to_se3(p))
    with pytest.raises(ValueError, match=r"\(\.\.\., 12\)"):
        head.to_pose(torch.zeros(2, 9, dtype=F64))
    model = build_model(
        ModelConfig(
            backbone=BackboneConfig(width=8, depth=2, blocks=1),
            representation="matrix_cm",
            input_size=(32, 32),
        )
    )
    x = torch.randn(2, 1, 32, 32)
    assert model(x).shape == (2, 12)
    torch.testing.assert_close(model.predict_poses(x), torch.zeros(2, 6), atol=1e-6, rtol=0)
    assert SliceDatasetConfig(representation="matrix_cm").representation == "matrix_cm"
    with pytest.raises(ValueError, match="matrix_cm"):  # the valid names now include it
        SliceDatasetConfig(representation="matrix")


def test_a_registered_representation_gets_its_loss_and_the_orbit_loss(fake):
    p, q = random_poses(16, seed=5), random_poses(16, seed=6)
    pred, labels = _matrix_encode(q, 0.0).float(), _matrix_encode(p, 0.0).float()
    torch.testing.assert_close(loss_function("matrix_cm")(pred, labels), _matrix_loss(pred, labels))
    twin_labels = _matrix_encode(mirror_twin(p), 0.0).float()
    nearer = torch.minimum(
        _matrix_loss(pred, labels, reduction="none"),
        _matrix_loss(pred, twin_labels, reduction="none"),
    )
    orbit = loss_function("matrix_cm", planes=(SAGITTAL,))(pred, labels)
    torch.testing.assert_close(orbit, nearer.mean(), atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="'weights' apply to the 'se3' loss only"):
        loss_function("matrix_cm", torch.ones(6))


def test_a_registered_representation_is_a_cli_loss(fake, monkeypatch, tmp_path):
    seen = {}

    def fake_train(config, volumes, **kwargs):
        seen["config"] = config
        return types.SimpleNamespace(checkpoint="c", steps_done=0, last_loss=0.0)

    monkeypatch.setattr("svr.models.train.train", fake_train)
    monkeypatch.setattr(train_cli, "_volumes", lambda args: ([], []))
    out = str(tmp_path / "run")
    args = build_parser().parse_args(
        ["train", "--output-dir", out, "--loss", "matrix", "--symmetry", "none", "--quiet"]
    )
    assert train_cli.run(args) == 0
    assert seen["config"].model.representation == "matrix_cm"
    assert seen["config"].data.representation == "matrix_cm"
