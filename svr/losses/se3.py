"""The SE(3) geodesic pose loss ``e^T Z e`` with ``e = Log_id(pred^-1 o target)``.

With ``Z = diag(a I3, b I3)`` the loss is exactly the squared geodesic distance of the left-invariant
metric (the product metric on SO(3) x R^3): ``a theta^2 + b |t - t_pred|^2``. With anisotropic
(e.g. data-adaptive) Z it is the left-invariant quadratic form on the error, which agrees with the
squared Riemannian distance to second order near the identity (Hou et al. say so too).

Gradients (``gradient=``):
    * ``"exact"`` (default): the Euclidean gradient of ``e^T Z e`` with respect to the 6-vector
      outputs, in closed form inside one fused autograd node (fast: see ``benchmarks/bench_loss.py``).
    * ``"riemannian"``: the paper's explicit gradient ``-2 J^-T Z J^-1 v`` with ``v = Log_pred(target)``
      and the paper's ``J`` transporting identity to ``pred``. In our terms ``J^-1`` is
      ``L = blockdiag(J_r(r_pred), R_pred^T)`` (chart at ``pred`` -> identity), ``e = L v``, so the
      gradient is ``-2 L^T Z e``. It equals the exact gradient when Z is block-isotropic
      (``diag(a I3, b I3)``): there ``J_l(e_r)^-T Z_r e_r = Z_r e_r`` and the rotation-translation
      cross term ``e_t x Z_t e_t`` vanishes. With anisotropic Z it drops these two terms: it is the
      gradient of the metric with Z frozen along the geodesic, not of ``e^T Z e``. The target gets no
      gradient in this mode.
    * ``"autograd"``: the plain composition through :func:`svr.geometry.se3_error`, slower but twice
      differentiable; use it for higher-order derivatives.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn
from torch.autograd.function import FunctionCtx, once_differentiable

from svr.geometry import _cf, _series
from svr.geometry._validation import check_tensor
from svr.geometry.se3 import error_cf, se3_error
from svr.losses.metric_weights import default_metric_weights, validate_metric_weights

Reduction = Literal["mean", "sum", "none"]
Gradient = Literal["exact", "riemannian", "autograd"]


def quadratic_form(e: Tensor, weights: Tensor) -> Tensor:
    """``e^T Z e`` for Z given as a (6,) diagonal or a (6, 6) matrix; e is (..., 6) -> (...)."""
    if weights.dim() == 1:
        return (e.square() * weights).sum(-1)
    return ((e @ weights) * e).sum(-1)


class _SE3GeodesicLossFunction(torch.autograd.Function):
    """Fused ``e^T Z e`` with a closed-form backward, in float64 on component-first tensors.

    Inputs are (N, 6) poses of the same shape and a validated Z. With ``g = 2 Z e`` split into
    ``g_r, g_t`` and ``u`` the quaternion vector part of ``R_pred``, the backward uses
    ``d e_r/d r_pred = -J_l(e_r)^-1 J_r(r_pred)``, ``d e_t/d r_pred = [e_t]x J_r(r_pred)``,
    ``d e_t/d t_pred = -R_pred^T``, ``d e_r/d r = J_r(e_r)^-1 J_r(r)``, ``d e_t/d t = R_pred^T``,
    ``J_r(x)^T = J_l(x)`` and ``J_l(x)^-T = J_l(-x)^-1``.
    """

    @staticmethod
    def forward(ctx: FunctionCtx, pred: Tensor, target: Tensor, weights: Tensor,
                riemannian: bool) -> Tensor:
        x = torch.stack([pred, target]).to(torch.float64).permute(2, 0, 1).contiguous()
        z = weights.to(torch.float64)
        e, q_pred_inv = error_cf(x)
        ze = e * z[:, None] if z.dim() == 1 else z @ e
        ctx.save_for_backward(x[:3], q_pred_inv, e, ze, z)
        ctx.riemannian = riemannian
        ctx.dtypes = (pred.dtype, target.dtype, weights.dtype)
        return (e * ze).sum(0).to(torch.result_type(pred, target))

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad: Tensor) -> tuple[Tensor | None, ...]:
        rotvecs, q_pred_inv, e, ze, z = ctx.saved_tensors
        pred_dtype, target_dtype, weights_dtype = ctx.dtypes
        grad64 = grad.to(torch.float64)
        g = 2.0 * grad64 * ze
        g_r, g_t, e_r, e_t = g[:3], g[3:], e[:3], e[3:]
        w, u = q_pred_inv[:1], -q_pred_inv[1:]
        want_target = ctx.needs_input_grad[1] and not ctx.riemannian
        # Independent cross products are stacked along axis 1, so that each level is one call.
        if ctx.riemannian:
            c1 = _cf.cross(u[:, None], g_t[:, None])
            c2 = _cf.cross(u[:, None], c1)
            ys = [-g_r]
        else:
            c1 = _cf.cross(torch.stack([u, e_r, e_t], 1), torch.stack([g_t, g_r, g_t], 1))
            c2 = _cf.cross(torch.stack([u, e_r], 1), c1[:, :2])
            d = _series.inverse_jacobian_coefficient(_cf.dot(e_r, e_r))
            ys = [-(g_r + 0.5 * c1[:, 1] + d * c2[:, 1]) - c1[:, 2]]  # -J_l(-e)^-1 g_r - e_t x g_t
            if want_target:
                ys.append(g_r - 0.5 * c1[:, 1] + d * c2[:, 1])  # J_l(e)^-1 g_r
        grad_t_pred = -(g_t + 2.0 * (w * c1[:, 0] + c2[:, 0]))  # -R_pred g_t
        # J_l(r) y for the prediction and, when wanted, the target.
        y = torch.stack(ys, 1)
        r = rotvecs[:, : len(ys)]
        theta2 = _cf.dot(r, r)
        ry = _cf.cross(r, y)
        jl_y = (y + _series.one_minus_cos_over_theta2(theta2) * ry
                + _series.theta_minus_sin_over_theta3(theta2) * _cf.cross(r, ry))
        grad_pred = grad_target = grad_weights = None
        if ctx.needs_input_grad[0]:
            grad_pred = torch.cat([jl_y[:, 0], grad_t_pred]).T.to(pred_dtype)
        if want_target:
            grad_target = torch.cat([jl_y[:, 1], -grad_t_pred]).T.to(target_dtype)
        if ctx.needs_input_grad[2]:
            grad_weights = ((grad64 * e.square()).sum(1) if z.dim() == 1
                            else (grad64 * e) @ e.T).to(weights_dtype)
        return grad_pred, grad_target, grad_weights, None


def _reduce(loss: Tensor, reduction: str, func: str) -> Tensor:
    if reduction == "mean":
        return loss.mean()
    if reduction == "sum":
        return loss.sum()
    if reduction == "none":
        return loss
    raise ValueError(f"{func}(): 'reduction' must be 'mean', 'sum' or 'none', got {reduction!r}")


def _resolve_weights(weights: Tensor | None, like: Tensor, func: str) -> Tensor:
    if weights is None:
        return default_metric_weights(dtype=like.dtype, device=like.device)
    return validate_metric_weights(weights, func)


def _se3_loss_unchecked(pred: Tensor, target: Tensor, weights: Tensor, reduction: str,
                        gradient: str) -> Tensor:
    func = "se3_geodesic_loss"
    if gradient == "autograd":
        loss = quadratic_form(se3_error(pred, target), weights.to(torch.result_type(pred, target)))
    elif gradient in ("exact", "riemannian"):
        riemannian = gradient == "riemannian"
        if riemannian and target.requires_grad:
            raise ValueError(f"{func}(): gradient='riemannian' gives no gradient to 'target'; "
                             "detach it or use gradient='exact'")
        pred_b, target_b = torch.broadcast_tensors(pred, target)
        loss = _SE3GeodesicLossFunction.apply(pred_b.reshape(-1, 6), target_b.reshape(-1, 6),
                                              weights, riemannian).reshape(pred_b.shape[:-1])
    else:
        raise ValueError(f"{func}(): 'gradient' must be 'exact', 'riemannian' or 'autograd', "
                         f"got {gradient!r}")
    return _reduce(loss, reduction, func)


def se3_geodesic_loss(pred: Tensor, target: Tensor, weights: Tensor | None = None,
                      reduction: Reduction = "mean", gradient: Gradient = "exact") -> Tensor:
    """SE(3) geodesic loss ``e^T Z e`` with ``e = Log_id(pred^-1 o target)`` (rad, mm).

    Args:
        pred: (..., 6) predicted pose vectors ``(r, t)``: rotation vector (rad), translation (mm).
        target: (..., 6) true pose vectors, broadcastable with ``pred``.
        weights: Z as a (6,) positive diagonal or a (6, 6) symmetric positive definite matrix, in
            the error's units (rad, mm). ``None`` uses :func:`default_metric_weights`,
            ``(1, 1, 1, 1/L^2, 1/L^2, 1/L^2)`` with L = 30 mm, so that the loss is
            ``theta^2 + |dt|^2 / L^2``.
        reduction: ``"mean"`` or ``"sum"`` over all poses, or ``"none"`` for the (...) losses.
        gradient: ``"exact"``, ``"riemannian"`` or ``"autograd"`` (see the module docstring).

    Returns:
        The loss in the dtype of the inputs: a scalar, or (...) for ``reduction="none"``.

    Raises:
        ValueError: For bad shapes, weights that are not a valid inner product, or unknown options.
    """
    func = "se3_geodesic_loss"
    check_tensor(pred, func, "pred", (6,))
    check_tensor(target, func, "target", (6,))
    return _se3_loss_unchecked(pred, target, _resolve_weights(weights, pred, func), reduction,
                               gradient)


class SE3GeodesicLoss(nn.Module):
    """Module form of :func:`se3_geodesic_loss`; Z is validated once and kept as a buffer.

    Args:
        weights: Z as a (6,) diagonal or (6, 6) SPD matrix, or ``None`` for the default.
        reduction: ``"mean"``, ``"sum"`` or ``"none"``.
        gradient: ``"exact"``, ``"riemannian"`` or ``"autograd"``.
    """

    def __init__(self, weights: Tensor | None = None, reduction: Reduction = "mean",
                 gradient: Gradient = "exact") -> None:
        super().__init__()
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"SE3GeodesicLoss(): 'reduction' must be 'mean', 'sum' or 'none', "
                             f"got {reduction!r}")
        if gradient not in ("exact", "riemannian", "autograd"):
            raise ValueError(f"SE3GeodesicLoss(): 'gradient' must be 'exact', 'riemannian' or "
                             f"'autograd', got {gradient!r}")
        w = default_metric_weights() if weights is None else weights.detach().clone()
        self.register_buffer("weights", validate_metric_weights(w, "SE3GeodesicLoss"))
        self.reduction = reduction
        self.gradient = gradient

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """Loss of (..., 6) predictions against (..., 6) targets."""
        check_tensor(pred, "SE3GeodesicLoss", "pred", (6,))
        check_tensor(target, "SE3GeodesicLoss", "target", (6,))
        return _se3_loss_unchecked(pred, target, self.weights, self.reduction, self.gradient)

    def extra_repr(self) -> str:
        """Hyper-parameters shown by ``repr``."""
        w = [round(v, 6) for v in self.weights.flatten().tolist()]
        return f"weights={w}, reduction={self.reduction!r}, gradient={self.gradient!r}"
