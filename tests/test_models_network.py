"""Slice-pose networks: backbones, pose heads, configuration and losses."""

from __future__ import annotations

import json

import pytest
import torch

from svr.geometry import rotation_6d_to_matrix, so3_exp, so3_log, vector_to_se3
from svr.losses import anchor_point_loss, posenet_loss, rotation_6d_loss, se3_geodesic_loss
from svr.models.backbones import BackboneConfig, build_backbone
from svr.models.heads import PoseHead
from svr.models.network import ModelConfig, SlicePoseNet, build_model, loss_function
from svr.representation_registry import REPRESENTATIONS
from svr.sampling.poses import pose_labels, random_slice_poses

BACKBONES = ("resnet", "inception")


def small_config(name: str = "resnet", representation: str = "se3", depth: int = 2) -> ModelConfig:
    return ModelConfig(
        backbone=BackboneConfig(name=name, width=8, depth=depth, blocks=1),
        representation=representation,
        input_size=(32, 32),
    )


def random_poses(n: int, seed: int = 1, rotation: str = "euler") -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return random_slice_poses(n, g, rotation=rotation)


def test_output_sizes_match_the_labels():
    for rep, entry in REPRESENTATIONS.items():
        assert pose_labels(torch.zeros(6, dtype=torch.float64), rep).shape == (entry.size,)
        assert PoseHead(4, rep).linear.out_features == entry.size


@pytest.mark.parametrize("name", BACKBONES)
@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_output_shapes(name, representation):
    model = build_model(small_config(name, representation, depth=3))
    assert isinstance(model, SlicePoseNet)
    for size in ((32, 32), (64, 48)):
        x = torch.randn(3, 1, *size)
        assert model(x).shape == (3, REPRESENTATIONS[representation].size)
        assert model.predict_poses(x).shape == (3, 6)


@pytest.mark.parametrize("name", BACKBONES)
def test_backbone_features_for_any_input_size(name):
    config = BackboneConfig(name=name, width=8, depth=3, blocks=2)
    backbone = build_backbone(config).eval()
    assert backbone.out_features == config.out_features == 32
    for size in ((32, 32), (37, 70), (128, 96)):
        features = backbone(torch.randn(2, 1, *size))
        assert features.shape == (2, 32)
        assert torch.isfinite(features).all()


@pytest.mark.parametrize("name", BACKBONES)
@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_untrained_model_predicts_the_identity_pose(name, representation):
    model = build_model(small_config(name, representation))
    x = torch.randn(4, 1, 32, 32)
    for mode in (True, False):
        model.train(mode)
        poses = model.predict_poses(x)
        torch.testing.assert_close(poses, torch.zeros(4, 6), atol=1e-5, rtol=0)


@pytest.mark.parametrize("representation", REPRESENTATIONS)
@pytest.mark.parametrize("rotation", ["euler", "uniform"])
def test_to_pose_inverts_the_labels(representation, rotation):
    poses = random_poses(200, seed=3, rotation=rotation)
    for half_size in (60.0, 25.0):
        head = PoseHead(16, representation, anchor_half_size_mm=half_size).double()
        labels = pose_labels(poses, representation, anchor_half_size_mm=half_size)
        recovered = head.to_pose(labels)
        assert recovered.shape == (200, 6)
        assert (recovered[:, :3].norm(dim=1) <= torch.pi + 1e-12).all()
        torch.testing.assert_close(vector_to_se3(recovered), vector_to_se3(poses))


def test_se3_to_pose_regularises_the_rotation_angle():
    head = PoseHead(4, "se3").double()
    r = torch.tensor([[0.0, 0.0, 1.5 * torch.pi, 1.0, 2.0, 3.0]], dtype=torch.float64)
    expected = torch.tensor([[0.0, 0.0, -0.5 * torch.pi, 1.0, 2.0, 3.0]], dtype=torch.float64)
    torch.testing.assert_close(head.to_pose(r), expected)


@pytest.mark.parametrize(
    ("representation", "scale"),
    [
        ("se3", [1.0, 1.0, 1.0, 30.0, 30.0, 30.0]),
        ("quat_translation", [1.0, 1.0, 1.0, 1.0, 30.0, 30.0, 30.0]),
        ("anchor_points", [60.0] * 9),
        ("rotation6d_translation", [1.0] * 6 + [30.0] * 3),
    ],
)
def test_raw_outputs_are_scaled_to_label_units(representation, scale):
    head = PoseHead(5, representation)
    with torch.no_grad():
        head.linear.bias.fill_(1.0)
    torch.testing.assert_close(head(torch.randn(2, 5)), torch.tensor([scale, scale]))
    head = PoseHead(5, representation, translation_scale_mm=10.0, anchor_half_size_mm=20.0)
    expected = torch.tensor([10.0 if s == 30.0 else 20.0 if s == 60.0 else s for s in scale])
    torch.testing.assert_close(head.scale, expected)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"in_features": 0}, "in_features"),
        ({"representation": "euler"}, "representation"),
        ({"translation_scale_mm": 0.0}, "translation_scale_mm"),
        ({"anchor_half_size_mm": float("nan")}, "anchor_half_size_mm"),
    ],
)
def test_pose_head_validation(kwargs, field):
    args = {"in_features": 8, "representation": "se3", **kwargs}
    with pytest.raises(ValueError, match=field):
        PoseHead(**args)


def test_se3_head_with_6d_rotation():
    """The 6D head outputs the pose vector of its Gram-Schmidt rotation, differentiably."""
    head = PoseHead(8, "se3", rotation="6d").double()
    assert head.linear.out_features == 9
    x = torch.randn(5, 8, dtype=torch.float64)
    torch.testing.assert_close(head(x), torch.zeros(5, 6, dtype=torch.float64))  # identity
    torch.nn.init.normal_(head.linear.weight, generator=torch.Generator().manual_seed(0))
    raw = head.linear(x) * head.scale
    out = head(x)
    expected = so3_log(rotation_6d_to_matrix(raw[:, :6]))  # independent: log of the matrix
    torch.testing.assert_close(so3_exp(out[:, :3]), so3_exp(expected))
    torch.testing.assert_close(out[:, 3:], raw[:, 6:])
    # a 180-degree rotation: the loss through the conversion stays finite and differentiable
    with torch.no_grad():
        head.linear.weight.zero_()
        head.linear.bias.copy_(torch.tensor([-1.0, 0, 0, 0, -1.0, 0, 0, 0, 0]))
    loss = se3_geodesic_loss(head(x), torch.zeros(5, 6, dtype=torch.float64))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(head.linear.weight.grad).all()
    with pytest.raises(ValueError, match="'rotation' must be one of"):
        PoseHead(8, "quat_translation", rotation="6d")
    with pytest.raises(ValueError, match="'se3_rotation' must be one of"):
        ModelConfig(representation="anchor_points", se3_rotation="6d")
    config = ModelConfig(se3_rotation="6d", input_size=(32, 32))
    assert ModelConfig.from_dict(config.to_dict()) == config
    model = build_model(config)
    torch.testing.assert_close(model.predict_poses(torch.randn(2, 1, 32, 32)), torch.zeros(2, 6))


def test_se3_to_pose_checks_the_shape():
    with pytest.raises(ValueError, match=r"\(\.\.\., 6\)"):
        PoseHead(4, "se3").to_pose(torch.zeros(2, 7))


def train_losses(config: ModelConfig, steps: int = 30) -> tuple[float, float]:
    model = build_model(config)
    g = torch.Generator().manual_seed(5)
    x = torch.randn(8, 1, 32, 32, generator=g)
    labels = pose_labels(random_poses(8, seed=6).float(), config.representation)
    loss_fn = loss_function(config.representation)
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(steps + 1):
        optimiser.zero_grad()
        loss = loss_fn(model(x), labels)
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    return losses[0], losses[-1]


@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_a_few_adam_steps_reduce_the_loss(representation):
    before, after = train_losses(small_config("resnet", representation))
    assert after <= 0.5 * before


def test_a_few_adam_steps_reduce_the_loss_inception():
    before, after = train_losses(small_config("inception", "se3"))
    assert after <= 0.5 * before


@pytest.mark.parametrize("name", BACKBONES)
@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_gradients_are_finite(name, representation):
    model = build_model(small_config(name, representation))
    x = torch.randn(4, 1, 32, 32)
    labels = pose_labels(random_poses(4, rotation="uniform").float(), representation)
    loss_fn = loss_function(representation)
    optimiser = torch.optim.SGD(model.parameters(), lr=1e-3)
    for _ in range(2):  # the zero-initialised head passes no gradient to the backbone at first
        optimiser.zero_grad()
        loss_fn(model(x), labels).backward()
        grads = [p.grad for p in model.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)
        optimiser.step()
    assert model.head.linear.weight.grad.abs().sum() > 0
    assert model.backbone.stem[0].weight.grad.abs().sum() > 0


def test_state_dict_round_trip_reproduces_the_outputs():
    config = small_config("inception", "anchor_points")
    model = build_model(config).eval()
    with torch.no_grad():
        model.head.linear.weight.normal_()
    copy = build_model(config).eval()
    copy.load_state_dict(model.state_dict())
    assert "head.scale" not in model.state_dict()
    x = torch.randn(2, 1, 32, 32)
    torch.testing.assert_close(copy(x), model(x))


@pytest.mark.parametrize("shape", [(2, 3, 32, 32), (1, 32, 32)])
def test_forward_rejects_bad_shapes(shape):
    with pytest.raises(ValueError, match="slices"):
        build_model(small_config())(torch.zeros(shape))


def test_forward_rejects_integer_images():
    with pytest.raises(ValueError, match="floating-point"):
        build_model(small_config())(torch.zeros(1, 1, 32, 32, dtype=torch.int64))


def test_model_config_round_trip_through_json():
    config = ModelConfig(
        backbone=BackboneConfig(name="inception", width=16, depth=3, blocks=1, dropout=0.2),
        representation="anchor_points",
        input_size=(96, 112),
        spacing_mm=0.8,
        translation_scale_mm=40.0,
        anchor_half_size_mm=50.0,
    )
    d = config.to_dict()
    assert d == json.loads(json.dumps(d))
    assert d["backbone"]["name"] == "inception" and d["input_size"] == [96, 112]
    assert ModelConfig.from_dict(json.loads(json.dumps(d))) == config
    assert ModelConfig.from_dict(ModelConfig().to_dict()) == ModelConfig()
    assert ModelConfig.from_dict({}) == ModelConfig()


def test_model_config_defaults_and_number_normalisation():
    config = ModelConfig(spacing_mm=1, backbone=BackboneConfig(dropout=0))
    assert config.spacing_mm == 1.0 and isinstance(config.spacing_mm, float)
    assert isinstance(config.backbone.dropout, float)
    assert config.input_size == (128, 128) and config.representation == "se3"
    assert config.backbone == BackboneConfig("resnet", 32, 4, 2, 0.0)
    assert ModelConfig(input_size=[64, 64]).input_size == (64, 64)


@pytest.mark.parametrize(
    ("d", "key"),
    [
        ({"depth": 3}, "'depth'"),
        ({"backbone": {"widht": 8}}, "'backbone.widht'"),
        ({"backbone": [8]}, "'backbone'"),
        ({"backbone": {"width": 4}}, "'width'"),
        ({"backbone": {"name": "vgg"}}, "'name'"),
        ({"representation": "euler"}, "'representation'"),
        ({"input_size": [16, 16]}, "'input_size'"),
        ({"input_size": [64]}, "'input_size'"),
        ({"input_size": [64.0, 64.0]}, "'input_size'"),
        ({"spacing_mm": -1.0}, "'spacing_mm'"),
        ({"spacing_mm": True}, "'spacing_mm'"),
        ({"translation_scale_mm": "30"}, "'translation_scale_mm'"),
        ({"anchor_half_size_mm": float("inf")}, "'anchor_half_size_mm'"),
    ],
)
def test_model_config_from_dict_is_strict(d, key):
    with pytest.raises(ValueError, match=key):
        ModelConfig.from_dict(d)


def test_model_config_from_dict_needs_a_dict():
    with pytest.raises(ValueError, match="dict"):
        ModelConfig.from_dict([("representation", "se3")])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"name": "vgg"}, "name"),
        ({"width": 4}, "width"),
        ({"width": 16.0}, "width"),
        ({"depth": 0}, "depth"),
        ({"depth": True}, "depth"),
        ({"blocks": 0}, "blocks"),
        ({"dropout": 1.0}, "dropout"),
        ({"dropout": -0.1}, "dropout"),
        ({"dropout": "0.1"}, "dropout"),
    ],
)
def test_backbone_config_validation(kwargs, field):
    with pytest.raises(ValueError, match=f"'{field}'"):
        BackboneConfig(**kwargs)


def test_backbone_dropout_acts_in_training_mode_only():
    backbone = build_backbone(BackboneConfig(width=8, depth=2, dropout=0.5))
    x = torch.randn(4, 1, 32, 32)
    backbone.eval()
    torch.testing.assert_close(backbone(x), backbone(x))
    backbone.train()
    assert (backbone(x) == 0).float().mean() > 0.2


def test_loss_function_matches_the_svr_losses():
    poses = random_poses(16, seed=8)
    pred = random_poses(16, seed=9)
    z = torch.tensor([1.0, 2.0, 3.0, 0.01, 0.02, 0.03], dtype=torch.float64)
    torch.testing.assert_close(loss_function("se3")(pred, poses), se3_geodesic_loss(pred, poses))
    torch.testing.assert_close(
        loss_function("se3", z)(pred, poses), se3_geodesic_loss(pred, poses, z)
    )
    baselines = {
        "quat_translation": posenet_loss,
        "anchor_points": anchor_point_loss,
        "rotation6d_translation": rotation_6d_loss,
    }
    for rep, loss in baselines.items():
        p, t = pose_labels(pred, rep), pose_labels(poses, rep)
        value = loss_function(rep)(p, t)
        assert value.shape == ()
        torch.testing.assert_close(value, loss(p, t, reduction="mean"))


def test_loss_function_errors():
    with pytest.raises(ValueError, match="representation"):
        loss_function("euler")
    with pytest.raises(ValueError, match="weights"):
        loss_function("anchor_points", torch.ones(6))
    with pytest.raises(ValueError, match="weights"):
        loss_function("se3", -torch.ones(6))
