"""The SE(3) geodesic loss: values, invariances, gradients (exact, Riemannian, autograd), errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import quadratic_form_np, random_poses, right_jacobian_np, se3_error_np
from scipy.spatial.transform import Rotation
from torch.autograd import gradcheck, gradgradcheck

from svr.geometry import se3_compose, se3_to_vector, vector_to_se3
from svr.losses import SE3GeodesicLoss, default_metric_weights, se3_geodesic_loss

F64 = torch.float64
DIAG_ANISO = torch.tensor([0.5, 1.5, 3.0, 0.01, 0.002, 0.05], dtype=F64)
ISO = torch.tensor([2.0, 2.0, 2.0, 0.01, 0.01, 0.01], dtype=F64)


def spd_matrix(rng: np.random.Generator) -> torch.Tensor:
    a = rng.normal(size=(6, 6))
    return torch.from_numpy(a @ a.T + 0.5 * np.eye(6))


def compose_vec(g: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    return se3_to_vector(se3_compose(vector_to_se3(g), vector_to_se3(p)))


def poses(rng: np.random.Generator, n: int, **kw: float) -> torch.Tensor:
    return torch.from_numpy(random_poses(rng, n, **kw))


def near_pi_pair(rng: np.random.Generator, n: int, gap: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Pred/target pairs whose relative rotation has angle pi - gap."""
    pred = random_poses(rng, n)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    rel = Rotation.from_rotvec(axis * (math.pi - gap))
    target = pred.copy()
    target[:, :3] = (Rotation.from_rotvec(pred[:, :3]) * rel).as_rotvec()
    target[:, 3:] += rng.normal(size=(n, 3))
    return torch.from_numpy(pred), torch.from_numpy(target)


@pytest.mark.parametrize("gradient", ["exact", "riemannian", "autograd"])
@pytest.mark.parametrize("weights_kind", ["default", "diag", "full"])
def test_value_matches_numpy_oracle(rng, gradient, weights_kind):
    pred, target = poses(rng, 64), poses(rng, 64)
    weights = {"default": None, "diag": DIAG_ANISO, "full": spd_matrix(rng)}[weights_kind]
    z = default_metric_weights(dtype=F64) if weights is None else weights
    expected = quadratic_form_np(se3_error_np(pred.numpy(), target.numpy()), z.numpy())
    got = se3_geodesic_loss(pred, target, weights, reduction="none", gradient=gradient)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12, atol=1e-12)


def test_default_weights_balance_rad_and_30mm():
    z = default_metric_weights(dtype=F64)
    np.testing.assert_allclose(z.numpy(), [1, 1, 1, 1 / 900, 1 / 900, 1 / 900])
    one_rad = torch.tensor([1.0, 0, 0, 0, 0, 0], dtype=F64)
    thirty_mm = torch.tensor([0.0, 0, 0, 0, 30.0, 0], dtype=F64)
    zero = torch.zeros(6, dtype=F64)
    assert se3_geodesic_loss(one_rad, zero).item() == pytest.approx(1.0)
    assert se3_geodesic_loss(thirty_mm, zero).item() == pytest.approx(1.0)


def test_block_isotropic_loss_is_squared_geodesic_distance(rng):
    pred, target = poses(rng, 50), poses(rng, 50)
    rel = Rotation.from_rotvec(pred[:, :3].numpy()).inv() * Rotation.from_rotvec(target[:, :3])
    theta = rel.magnitude()
    dt = np.linalg.norm(target[:, 3:].numpy() - pred[:, 3:].numpy(), axis=1)
    expected = 2.0 * theta**2 + 0.01 * dt**2
    got = se3_geodesic_loss(pred, target, ISO, reduction="none")
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12)


@pytest.mark.parametrize("weights_kind", ["iso", "diag", "full"])
def test_left_invariance(rng, weights_kind):
    pred, target, g = poses(rng, 40), poses(rng, 40), poses(rng, 40)
    weights = {"iso": ISO, "diag": DIAG_ANISO, "full": spd_matrix(rng)}[weights_kind]
    before = se3_geodesic_loss(pred, target, weights, reduction="none")
    after = se3_geodesic_loss(
        compose_vec(g, pred), compose_vec(g, target), weights, reduction="none"
    )
    torch.testing.assert_close(after, before, rtol=1e-9, atol=1e-10)


def test_not_right_invariant_in_translation(rng):
    """Conjugation rotates the translation error, so right-translation changes the loss."""
    pred, target, g = poses(rng, 40), poses(rng, 40), poses(rng, 40)
    before = se3_geodesic_loss(pred, target, DIAG_ANISO, reduction="none")
    after = se3_geodesic_loss(
        se3_to_vector(se3_compose(vector_to_se3(pred), vector_to_se3(g))),
        se3_to_vector(se3_compose(vector_to_se3(target), vector_to_se3(g))),
        DIAG_ANISO,
        reduction="none",
    )
    assert (after - before).abs().max() > 1e-3


def test_symmetric_for_block_isotropic_weights(rng):
    a, b = poses(rng, 30), poses(rng, 30)
    torch.testing.assert_close(
        se3_geodesic_loss(a, b, ISO, reduction="none"),
        se3_geodesic_loss(b, a, ISO, reduction="none"),
    )


def test_zero_at_equal_poses_and_equivalent_rotation_vectors(rng):
    p = poses(rng, 10)
    assert se3_geodesic_loss(p, p, reduction="none").abs().max() < 1e-24
    # r and r - 2 pi r/|r| are the same rotation.
    q = p.clone()
    theta = q[:, :3].norm(dim=1, keepdim=True)
    q[:, :3] = q[:, :3] * (1 - 2 * math.pi / theta)
    assert se3_geodesic_loss(p, q, reduction="none").abs().max() < 1e-20


def _gradcheck_cases(rng):
    pred, target = poses(rng, 6), poses(rng, 6)
    same_rot = target.clone()
    same_rot[:, :3] = pred[:, :3]
    zero_rot_pred = pred.clone()
    zero_rot_pred[:, :3] = 0.0
    near_pi = near_pi_pair(rng, 6, gap=1e-3)
    return {
        "generic": (pred, target),
        "equal": (pred, pred.clone()),
        "zero_relative_rotation": (pred, same_rot),
        "identity_rotations": (
            zero_rot_pred,
            torch.cat([torch.zeros(6, 3, dtype=F64), target[:, 3:]], 1),
        ),
        "near_pi": near_pi,
    }


@pytest.mark.parametrize(
    "case", ["generic", "equal", "zero_relative_rotation", "identity_rotations", "near_pi"]
)
@pytest.mark.parametrize("weights_kind", ["default", "diag", "full"])
def test_exact_gradient_gradcheck(rng, case, weights_kind):
    pred, target = _gradcheck_cases(rng)[case]
    weights = {"default": None, "diag": DIAG_ANISO.clone(), "full": spd_matrix(rng)}[weights_kind]
    pred.requires_grad_(True)
    target.requires_grad_(True)
    if weights is None:
        assert gradcheck(lambda a, b: se3_geodesic_loss(a, b, reduction="none"), (pred, target))
    else:
        # Symmetrised so that gradcheck's one-entry perturbations keep Z a valid inner product.
        weights.requires_grad_(True)
        assert gradcheck(
            lambda a, b, z: se3_geodesic_loss(
                a, b, (z + z.T) / 2 if z.dim() == 2 else z, reduction="none"
            ),
            (pred, target, weights),
        )


@pytest.mark.parametrize("weights", [ISO, DIAG_ANISO], ids=["iso", "aniso"])
def test_exact_and_autograd_gradients_agree(rng, weights):
    pred, target = poses(rng, 32), poses(rng, 32)
    grads = []
    for gradient in ("exact", "autograd"):
        p, t = pred.clone().requires_grad_(True), target.clone().requires_grad_(True)
        se3_geodesic_loss(p, t, weights, reduction="sum", gradient=gradient).backward()
        grads.append((p.grad, t.grad))
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-9, atol=1e-10)


def test_riemannian_gradient_matches_autograd_for_block_isotropic_weights(rng):
    pred, target = poses(rng, 32), poses(rng, 32)
    grads = []
    for gradient in ("riemannian", "autograd"):
        p = pred.clone().requires_grad_(True)
        se3_geodesic_loss(p, target, ISO, reduction="sum", gradient=gradient).backward()
        grads.append(p.grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-9, atol=1e-10)


def test_riemannian_gradient_is_minus_two_Lt_Z_e(rng):
    """With anisotropic Z the Riemannian gradient is -2 L^T Z e, L = blockdiag(J_r, R^T)."""
    pred, target = poses(rng, 8), poses(rng, 8)
    p = pred.clone().requires_grad_(True)
    se3_geodesic_loss(p, target, DIAG_ANISO, reduction="sum", gradient="riemannian").backward()
    e = se3_error_np(pred.numpy(), target.numpy())
    ze = e * DIAG_ANISO.numpy()
    for i in range(8):
        jr = right_jacobian_np(pred[i, :3].numpy())
        rot = Rotation.from_rotvec(pred[i, :3].numpy()).as_matrix()
        expected = -2.0 * np.concatenate([jr.T @ ze[i, :3], rot @ ze[i, 3:]])
        np.testing.assert_allclose(p.grad[i].numpy(), expected, rtol=1e-6, atol=1e-8)
    # ... which is not the gradient of e^T Z e when Z is anisotropic.
    q = pred.clone().requires_grad_(True)
    se3_geodesic_loss(q, target, DIAG_ANISO, reduction="sum", gradient="autograd").backward()
    assert (q.grad - p.grad).abs().max() > 1e-3


def test_riemannian_rejects_target_requiring_grad(rng):
    pred, target = poses(rng, 4), poses(rng, 4).requires_grad_(True)
    with pytest.raises(ValueError, match="riemannian"):
        se3_geodesic_loss(pred, target, gradient="riemannian")


def test_autograd_mode_is_twice_differentiable_and_exact_mode_says_so(rng):
    pred = poses(rng, 4).requires_grad_(True)
    target = poses(rng, 4)
    assert gradgradcheck(lambda a: se3_geodesic_loss(a, target, gradient="autograd"), (pred,))
    (g,) = torch.autograd.grad(se3_geodesic_loss(pred, target), pred, create_graph=True)
    with pytest.raises(RuntimeError):
        g.sum().backward()


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("gradient", ["exact", "riemannian", "autograd"])
def test_finite_gradients_at_singular_points(rng, dtype, gradient):
    pred, target = poses(rng, 4), poses(rng, 4)
    cases = [
        (pred, pred.clone()),  # pred == target
        (torch.zeros(4, 6, dtype=F64), torch.zeros(4, 6, dtype=F64)),  # identity, theta = 0
        near_pi_pair(rng, 4, gap=0.0),  # relative rotation exactly pi
        near_pi_pair(rng, 4, gap=1e-9),
    ]
    big = pred.clone()
    big[:, :3] *= (2 * math.pi - 1e-3) / big[:, :3].norm(dim=1, keepdim=True)  # |r| near 2 pi
    cases.append((big, target))
    for p, t in cases:
        p = p.to(dtype).requires_grad_(True)
        loss = se3_geodesic_loss(p, t.to(dtype), gradient=gradient)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(p.grad).all()


def test_float32_inputs_give_float32_outputs_and_accurate_values(rng):
    pred, target = poses(rng, 100), poses(rng, 100)
    p32 = pred.float().requires_grad_(True)
    loss = se3_geodesic_loss(p32, target.float(), reduction="none")
    assert loss.dtype == torch.float32
    loss.sum().backward()
    assert p32.grad.dtype == torch.float32
    expected = quadratic_form_np(
        se3_error_np(p32.detach().double().numpy(), target.float().double().numpy()),
        default_metric_weights(dtype=F64).numpy(),
    )
    np.testing.assert_allclose(loss.detach().numpy(), expected, rtol=1e-6)


def test_batch_shapes_broadcasting_and_reductions(rng):
    pred = poses(rng, 6).reshape(2, 3, 6)
    target = poses(rng, 1)[0]
    none = se3_geodesic_loss(pred, target, reduction="none")
    assert none.shape == (2, 3)
    flat = se3_geodesic_loss(pred.reshape(6, 6), target.expand(6, 6), reduction="none")
    torch.testing.assert_close(none.reshape(6), flat)
    torch.testing.assert_close(se3_geodesic_loss(pred, target, reduction="sum"), none.sum())
    torch.testing.assert_close(se3_geodesic_loss(pred, target), none.mean())
    # target broadcasting also yields a correctly summed gradient
    t = target.clone().requires_grad_(True)
    se3_geodesic_loss(pred, t, reduction="sum").backward()
    t2 = target.expand(6, 6).clone().requires_grad_(True)
    se3_geodesic_loss(pred.reshape(6, 6), t2, reduction="sum").backward()
    torch.testing.assert_close(t.grad, t2.grad.sum(0))


@pytest.mark.parametrize(
    ("weights", "message"),
    [
        (torch.ones(5), "shape"),
        (torch.ones(6, 5), "shape"),
        (torch.tensor([1.0, 1, 1, 1, 1, 0]), "> 0"),
        (torch.tensor([1.0, 1, 1, 1, 1, float("nan")]), "finite"),
        (torch.eye(6) + torch.triu(torch.ones(6, 6), 1), "symmetric"),
        (torch.diag(torch.tensor([1.0, 1, 1, 1, 1, -1])), "positive definite"),
        (torch.ones(6, dtype=torch.int64), "floating-point"),
        ([1.0] * 6, "torch.Tensor"),
    ],
)
def test_invalid_weights_raise_clear_errors(weights, message):
    p = torch.zeros(3, 6)
    with pytest.raises((ValueError, TypeError), match=message) as info:
        se3_geodesic_loss(p, p, weights)
    assert "se3_geodesic_loss(): 'weights'" in str(info.value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"reduction": "avg"}, "'reduction'"),
        ({"gradient": "numeric"}, "'gradient'"),
    ],
)
def test_invalid_options_raise(kwargs, message):
    p = torch.zeros(3, 6)
    with pytest.raises(ValueError, match=message):
        se3_geodesic_loss(p, p, **kwargs)


@pytest.mark.parametrize(
    ("pred", "target", "message"),
    [
        (torch.zeros(3, 7), torch.zeros(3, 6), "'pred' must have shape"),
        (torch.zeros(3, 6), torch.zeros(3, 3), "'target' must have shape"),
        (torch.zeros(3, 6, dtype=torch.int64), torch.zeros(3, 6), "floating-point"),
    ],
)
def test_bad_pose_arguments(pred, target, message):
    with pytest.raises((ValueError, TypeError), match=message):
        se3_geodesic_loss(pred, target)


def test_module_wrapper(rng):
    pred, target = poses(rng, 16), poses(rng, 16)
    z = spd_matrix(rng)
    module = SE3GeodesicLoss(z, reduction="sum").to(F64)
    torch.testing.assert_close(
        module(pred, target), se3_geodesic_loss(pred, target, z, reduction="sum")
    )
    assert "weights" in module.state_dict()
    assert "reduction='sum'" in repr(module)
    assert SE3GeodesicLoss().weights.shape == (6,)
    with pytest.raises(ValueError, match="'weights'"):
        SE3GeodesicLoss(torch.ones(3))
    with pytest.raises(ValueError, match="'reduction'"):
        SE3GeodesicLoss(reduction="avg")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("gradient", ["exact", "riemannian", "autograd"])
def test_cuda_matches_cpu(rng, gradient):
    pred, target = poses(rng, 256).float(), poses(rng, 256).float()
    results = []
    for device in ("cpu", "cuda"):
        p = pred.to(device).detach().requires_grad_(True)
        loss = se3_geodesic_loss(
            p,
            target.to(device),
            DIAG_ANISO.float(),
            gradient=gradient,  # Z moved to the device by the loss
        )
        loss.backward()
        results.append((loss.detach().cpu(), p.grad.cpu()))
    torch.testing.assert_close(results[0], results[1], rtol=1e-5, atol=1e-6)


_finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
_rotvec = st.lists(st.floats(-4 * math.pi, 4 * math.pi, allow_nan=False), min_size=3, max_size=3)
_pose = st.tuples(_rotvec, st.lists(_finite, min_size=3, max_size=3)).map(
    lambda rt: torch.tensor(rt[0] + rt[1], dtype=F64)
)


@settings(max_examples=60, deadline=None)
@given(pred=_pose, target=_pose, g=_pose)
def test_property_nonnegative_left_invariant_finite_gradients(pred, target, g):
    p = pred.clone().requires_grad_(True)
    loss = se3_geodesic_loss(p, target, DIAG_ANISO)
    loss.backward()
    assert loss.item() >= 0.0
    assert torch.isfinite(p.grad).all()
    moved = se3_geodesic_loss(compose_vec(g, pred), compose_vec(g, target), DIAG_ANISO)
    assert moved.item() == pytest.approx(loss.item(), rel=1e-7, abs=1e-9)
    # The rotation part of the error is a rotation vector of angle at most pi.
    e_rot = se3_error_np(pred[None].numpy(), target[None].numpy())[0, :3]
    assert np.linalg.norm(e_rot) <= math.pi + 1e-12


def test_weights_follow_the_predictions_dtype(rng):
    """float32 Z with float64 poses (and vice versa) work, with Z's gradient in Z's dtype."""
    pred, target = poses(rng, 8).requires_grad_(True), poses(rng, 8)
    z = DIAG_ANISO.float().requires_grad_(True)
    se3_geodesic_loss(pred, target, z).backward()
    assert z.grad.dtype == torch.float32 and pred.grad.dtype == F64


def _diagonal_path_cases(rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose pairs with relative angles near 0 (down to exactly 0) and near pi (down to pi)."""
    pred, target = poses(rng, 40), poses(rng, 40)
    tiny = pred[:8] + torch.from_numpy(rng.normal(scale=1e-9, size=(8, 6)))  # angle ~1e-9
    small = pred[:8].clone()
    small[:, :3] += torch.from_numpy(rng.normal(scale=1e-4, size=(8, 3)))
    equal_rotation = target[:8].clone()
    equal_rotation[:, :3] = pred[:8, :3]
    identity = torch.zeros(4, 6, dtype=F64)
    identity[:, 3:] = poses(rng, 4)[:, 3:]
    near_pi = [near_pi_pair(rng, 6, gap) for gap in (0.0, 1e-9, 1e-6, 1e-3)]
    big = pred[:6].clone()  # |r_pred| near 2 pi
    big[:, :3] *= (2 * math.pi - 1e-3) / big[:, :3].norm(dim=1, keepdim=True)
    preds = [pred, pred[:8], pred[:8], pred[:8], identity, *(p for p, _ in near_pi), big]
    targets = [target, tiny, small, equal_rotation, identity.flip(0)]
    targets += [t for _, t in near_pi] + [target[:6]]
    return torch.cat(preds), torch.cat(targets)


@pytest.mark.parametrize("gradient", ["exact", "riemannian"])
def test_anisotropic_diagonal_fast_path_matches_general_formula(rng, gradient):
    """The fused path for a diagonal anisotropic Z (Z read on the CPU) equals, in float64, the
    general path taken by the same Z as a (6, 6) matrix and by a Z that needs a gradient."""
    pred, target = _diagonal_path_cases(rng)
    want_target = gradient == "exact"
    results = []
    for weights in (DIAG_ANISO, torch.diag(DIAG_ANISO), DIAG_ANISO.clone().requires_grad_(True)):
        p, t = pred.clone().requires_grad_(True), target.clone().requires_grad_(want_target)
        loss = se3_geodesic_loss(p, t, weights, reduction="none", gradient=gradient)
        (loss * torch.linspace(0.5, 2.0, len(loss), dtype=F64)).sum().backward()
        results.append((loss.detach(), p.grad, t.grad))
    fast, *general = results
    for other in general:
        torch.testing.assert_close(fast, other, rtol=1e-10, atol=1e-11)
    assert all(torch.isfinite(g).all() for g in fast if g is not None)


@pytest.mark.parametrize(
    "case", ["generic", "equal", "zero_relative_rotation", "identity_rotations", "near_pi"]
)
def test_anisotropic_diagonal_fast_path_gradcheck(rng, case):
    """gradcheck of the fused diagonal path itself (Z without gradient: no fallback)."""
    pred, target = _gradcheck_cases(rng)[case]
    pred.requires_grad_(True)
    target.requires_grad_(True)
    assert gradcheck(
        lambda a, b: se3_geodesic_loss(a, b, DIAG_ANISO, reduction="none"), (pred, target)
    )


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("gradient", ["exact", "riemannian"])
def test_anisotropic_diagonal_fast_path_finite_at_singular_points(rng, dtype, gradient):
    """Finite loss and gradients (prediction and target) at angle 0, pi and |r| near 2 pi."""
    pred, target = poses(rng, 4), poses(rng, 4)
    big = pred.clone()
    big[:, :3] *= (2 * math.pi - 1e-3) / big[:, :3].norm(dim=1, keepdim=True)  # |r| near 2 pi
    cases = [
        (pred, pred.clone()),
        (torch.zeros(4, 6, dtype=F64), torch.zeros(4, 6, dtype=F64)),
        near_pi_pair(rng, 4, gap=0.0),
        near_pi_pair(rng, 4, gap=1e-9),
        (big, target),
    ]
    for p, t in cases:
        p = p.to(dtype).requires_grad_(True)
        t = t.to(dtype).requires_grad_(gradient == "exact")
        loss = se3_geodesic_loss(p, t, DIAG_ANISO.to(dtype), gradient=gradient)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(p.grad).all()
        assert t.grad is None or torch.isfinite(t.grad).all()
