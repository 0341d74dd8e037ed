"""Baseline losses: PoseNet (with learned weighting), Anchor Points and 6D rotation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from oracles import random_poses
from scipy.spatial.transform import Rotation

from svr.geometry import (
    anchor_points_to_pose,
    pose_to_anchor_points,
    pose_to_quat_translation,
    pose_to_rotation_6d_translation,
)
from svr.losses import PoseNetLoss, anchor_point_loss, posenet_loss, rotation_6d_loss

F64 = torch.float64


def poses(rng: np.random.Generator, n: int) -> torch.Tensor:
    return torch.from_numpy(random_poses(rng, n))


def test_posenet_squared_matches_formula(rng):
    pred_q = torch.from_numpy(rng.normal(size=(20, 7)))
    target = pose_to_quat_translation(poses(rng, 20))
    got = posenet_loss(pred_q, target, beta=250.0, reduction="none", translation_scale_mm=10.0)
    q = target[:, :4].numpy()
    expected = (0.5 * ((pred_q[:, 4:] - target[:, 4:]).numpy() / 10.0) ** 2).sum(
        1
    ) + 250.0 * 0.5 * ((pred_q[:, :4].numpy() - q) ** 2).sum(1)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12)


def test_posenet_l2_variant_and_target_normalisation(rng):
    pred = pose_to_quat_translation(poses(rng, 10))
    target = pose_to_quat_translation(poses(rng, 10))
    scaled = target.clone()
    scaled[:, :4] *= -3.0  # same rotation: -3 q normalises and flips back to q
    torch.testing.assert_close(
        posenet_loss(pred, scaled, squared=False, reduction="none"),
        posenet_loss(pred, target, squared=False, reduction="none"),
    )
    expected = ((pred[:, 4:] - target[:, 4:]) / 30.0).norm(dim=1) + 500.0 * (
        pred[:, :4] - target[:, :4]
    ).norm(dim=1)
    torch.testing.assert_close(
        posenet_loss(pred, target, squared=False, reduction="none"), expected
    )


def test_posenet_is_zero_at_the_target(rng):
    t = pose_to_quat_translation(poses(rng, 5))
    assert posenet_loss(t, t).item() == pytest.approx(0.0, abs=1e-20)


def test_posenet_learned_weighting(rng):
    pred = torch.from_numpy(rng.normal(size=(8, 7)))
    target = pose_to_quat_translation(poses(rng, 8))
    log_vars = torch.tensor([0.3, -1.2], dtype=F64, requires_grad=True)
    got = posenet_loss(pred, target, reduction="none", log_vars=log_vars)
    lt = 0.5 * (((pred[:, 4:] - target[:, 4:]) / 30.0) ** 2).sum(1)
    lq = 0.5 * ((pred[:, :4] - target[:, :4]) ** 2).sum(1)
    expected = lt * math.exp(-0.3) + 0.3 + lq * math.exp(1.2) - 1.2
    torch.testing.assert_close(got, expected.detach())
    got.sum().backward()
    assert torch.isfinite(log_vars.grad).all() and log_vars.grad.abs().min() > 0

    module = PoseNetLoss(learn_weights=True).to(F64)
    names = [n for n, _ in module.named_parameters()]
    assert names == ["log_vars"]
    np.testing.assert_allclose(module.log_vars.detach().numpy(), [0.0, -3.0])
    module(pred, target).backward()
    assert module.log_vars.grad is not None
    assert list(PoseNetLoss().parameters()) == []


def test_anchor_loss_is_scaled_point_distance(rng):
    p = poses(rng, 12)
    shift = torch.tensor([3.0, -4.0, 12.0], dtype=F64)
    q = p.clone()
    q[:, 3:] += shift  # pure translation moves all three points by the same vector
    loss = anchor_point_loss(
        pose_to_anchor_points(q), pose_to_anchor_points(p), reduction="none", half_size_mm=60.0
    )
    np.testing.assert_allclose(loss.numpy(), 3 * 13.0**2 / 60.0**2, rtol=1e-12)
    assert anchor_point_loss(pose_to_anchor_points(p), pose_to_anchor_points(p)).item() == 0.0


def test_anchor_points_recover_the_pose(rng):
    p = poses(rng, 12)
    recovered = anchor_points_to_pose(pose_to_anchor_points(p, 40.0), 40.0)
    rel = Rotation.from_rotvec(recovered[:, :3].numpy()).inv() * Rotation.from_rotvec(p[:, :3])
    assert rel.magnitude().max() < 1e-10
    np.testing.assert_allclose(recovered[:, 3:].numpy(), p[:, 3:].numpy(), atol=1e-10)


def test_rotation6d_loss_closed_form(rng):
    p = poses(rng, 16)
    q = torch.from_numpy(random_poses(rng, 16))
    loss = rotation_6d_loss(
        pose_to_rotation_6d_translation(p), pose_to_rotation_6d_translation(q), reduction="none"
    )
    theta = (
        Rotation.from_rotvec(p[:, :3].numpy()).inv() * Rotation.from_rotvec(q[:, :3])
    ).magnitude()
    dt = np.linalg.norm((p[:, 3:] - q[:, 3:]).numpy(), axis=1)
    np.testing.assert_allclose(loss.numpy(), 4 * (1 - np.cos(theta)) + dt**2 / 900.0, rtol=1e-10)


def test_rotation6d_loss_accepts_unnormalised_predictions(rng):
    target = pose_to_rotation_6d_translation(poses(rng, 4))
    pred = target.clone()
    pred[:, :3] *= 5.0
    pred[:, 3:6] += 2.0 * target[:, :3]  # still the same Gram-Schmidt frame
    assert rotation_6d_loss(pred, target).item() == pytest.approx(0.0, abs=1e-20)


@pytest.mark.parametrize(
    ("func", "shape", "kwargs", "message"),
    [
        (posenet_loss, (3, 6), {}, "'pred' must have shape"),
        (posenet_loss, (3, 7), {"beta": 0.0}, "'beta' must be > 0"),
        (posenet_loss, (3, 7), {"log_vars": torch.zeros(3)}, "'log_vars'"),
        (anchor_point_loss, (3, 7), {}, "'pred' must have shape"),
        (anchor_point_loss, (3, 9), {"half_size_mm": -1.0}, "'half_size_mm'"),
        (rotation_6d_loss, (3, 6), {}, "'pred' must have shape"),
        (rotation_6d_loss, (3, 9), {"translation_scale_mm": 0.0}, "'translation_scale_mm'"),
        (rotation_6d_loss, (3, 9), {"reduction": "max"}, "'reduction'"),
    ],
)
def test_bad_arguments(func, shape, kwargs, message):
    x = torch.ones(shape)
    with pytest.raises((ValueError, TypeError), match=message) as info:
        func(x, x, **kwargs)
    assert str(info.value).startswith(func.__name__ + "()")
