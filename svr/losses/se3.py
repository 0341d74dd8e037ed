"""The SE(3) geodesic pose loss ``e^T Z e`` with ``e = Log_id(pred^-1 o target)``.

With ``Z = diag(a I3, b I3)`` the loss is exactly the squared geodesic distance of the
left-invariant metric (the product metric on SO(3) x R^3): ``a theta^2 + b |t - t_pred|^2``. With
anisotropic (e.g. data-adaptive) Z it is the left-invariant quadratic form on the error, which
agrees with the squared Riemannian distance to second order near the identity (Hou et al. say so
too).

Gradients (``gradient=``):
    * ``"exact"`` (default): the Euclidean gradient of ``e^T Z e`` with respect to the 6-vector
      outputs, in closed form inside one fused autograd node (fast: see
      ``benchmarks/bench_loss.py``).
    * ``"riemannian"``: the paper's explicit gradient ``-2 J^-T Z J^-1 v`` with
      ``v = Log_pred(target)`` and the paper's ``J`` transporting identity to ``pred``. In our
      terms ``J^-1`` is ``L = blockdiag(J_r(r_pred), R_pred^T)`` (chart at ``pred`` -> identity),
      ``e = L v``, so the gradient is ``-2 L^T Z e``. It equals the exact gradient when Z is
      block-isotropic (``diag(a I3, b I3)``): there ``J_l(e_r)^-T Z_r e_r = Z_r e_r`` and the
      rotation-translation cross term ``e_t x Z_t e_t`` vanishes. With anisotropic Z it drops these
      two terms: it is the gradient of the metric with Z frozen along the geodesic, not of
      ``e^T Z e``. The target gets no gradient in this mode.
    * ``"autograd"``: the plain composition through :func:`svr.geometry.se3_error`, slower but
      twice differentiable; use it for higher-order derivatives.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn
from torch.autograd.function import FunctionCtx, once_differentiable

from svr.geometry import _cf, _series
from svr.geometry._validation import check_tensor
from svr.geometry.se3 import se3_error
from svr.losses.metric_weights import default_metric_weights, validate_metric_weights

Reduction = Literal["mean", "sum", "none"]
Gradient = Literal["exact", "riemannian", "autograd"]


def quadratic_form(e: Tensor, weights: Tensor) -> Tensor:
    """``e^T Z e`` for Z given as a (6,) diagonal or a (6, 6) matrix; e is (..., 6) -> (...)."""
    if weights.dim() == 1:
        return (e.square() * weights).sum(-1)
    return ((e @ weights) * e).sum(-1)


def _block_isotropic(z: Tensor) -> tuple[float, float] | None:
    """``(a, b)`` if ``Z = diag(a, a, a, b, b, b)``, else None.

    Only checked on the CPU, where reading Z costs no device synchronisation.
    """
    if z.dim() != 1 or z.device.type != "cpu":
        return None
    d = z.tolist()
    return (d[0], d[3]) if d[0] == d[1] == d[2] and d[3] == d[4] == d[5] else None


def _jacobian_coefficients(sq: Tensor, c: Tensor, s: Tensor, k: int, aw: Tensor | None) -> Tensor:
    """``D`` of ``J_l(-e_r)^-1`` if ``aw`` is given, then ``C`` of ``J_l(r)`` for k rotations.

    With the error angle ``phi`` and ``aw = (phi/2) cot(phi/2)``, ``D = (1 - aw) / phi^2``; with
    ``c = cos(theta/2)`` and ``s = sin(theta/2) / theta``, ``C = (theta - sin theta) / theta^3 =
    (1 - 2 s c) / theta^2``. ``sq`` holds ``phi^2`` then the ``theta^2``; rows are (n,).

    These closed forms cancel for small angles, but no series is needed: ``D`` only multiplies
    ``(e_r . g_r) e_r`` and ``C`` only ``(r . y) r``, which vanish like the squared angle, so the
    absolute error of each term stays at ~1e-16 of ``|g_r|`` or ``|y|`` whatever the angle
    (``TINY`` keeps ``theta = 0`` from giving 0 / 0).
    """
    d = int(aw is not None)
    x2 = sq[1 - d : k + 1]
    coef = torch.empty_like(x2)
    if aw is not None:
        torch.neg(aw, out=coef[0]).add_(1.0)
    torch.mul(s[:k], c[:k], out=coef[d:]).mul_(-2.0).add_(1.0)
    return coef.div_(x2 + _series.TINY)


def _apply_left_jacobian(
    out: Tensor, r: Tensor, v: Tensor, c: Tensor, s: Tensor, coef: Tensor, y: Tensor
) -> None:
    """``out = J_l(r) y = 2 s (c y + v x y) + C (r . y) r``, with ``v = s r``.

    ``out``, ``r``, ``v``, ``y`` are (3, k, n); ``c``, ``s`` and ``coef`` (= C) are (k, n).
    """
    torch.mul(y, c, out=out)
    rows_y = y.unbind(0)
    _cf.add_cross_(out.unbind(0), v.unbind(0), rows_y)
    out.mul_(s * 2.0)
    out.addcmul_(r, _cf.dot(r.unbind(0), rows_y, out=torch.empty_like(coef)).mul_(coef))


class _SE3GeodesicLossFunction(torch.autograd.Function):
    """Fused ``e^T Z e`` with a closed-form backward, in float64 on component-first tensors.

    Inputs are (N, 6) poses of the same shape and a validated Z. With ``g = 2 Z e`` split into
    ``g_r, g_t``, the backward uses ``d e_r/d r_pred = -J_l(e_r)^-1 J_r(r_pred)``,
    ``d e_t/d r_pred = [e_t]x J_r(r_pred)``, ``d e_t/d t_pred = -R_pred^T``,
    ``d e_r/d r = J_r(e_r)^-1 J_r(r)``, ``d e_t/d t = R_pred^T``, ``J_r(x)^T = J_l(x)`` and
    ``J_l(x)^-T = J_l(-x)^-1``. Its coefficients come from values of the forward pass (half-angle
    cosines and sines, the error's ``atan``), and the work is done row by row in place.

    For block-isotropic ``Z = diag(a I3, b I3)`` the loss is ``a phi^2 + b |t - t_pred|^2``
    (``phi`` the error angle, ``|e_t| = |t - t_pred|``), ``g_r`` is parallel to ``e_r`` so that
    ``J_l(-e_r)^-1 g_r = g_r``, and ``e_t x g_t = 0``: the forward skips ``e_t`` and the backward
    these terms (exact and Riemannian gradients coincide).
    """

    @staticmethod
    def forward(
        ctx: FunctionCtx, pred: Tensor, target: Tensor, weights: Tensor, riemannian: bool
    ) -> Tensor:
        n = pred.shape[0]
        x = pred.new_empty((6, 2, n), dtype=torch.float64)  # (component, pred/target, pose)
        x[:, 0].copy_(pred.T)
        x[:, 1].copy_(target.T)
        r = x[:3]
        sq = x.new_empty((3, n))  # phi^2 (error angle), theta_pred^2, theta_target^2
        rows_r = r.unbind(0)
        q = x.new_empty((4, 2, n))  # quaternions (c, v) = (cos(theta/2), s r)
        c, s = _series.half_angle(
            _cf.dot(rows_r, rows_r, out=sq[1:]), out=(q[0], sq.new_empty(2, n))
        )
        torch.mul(r, s, out=q[1:])
        vp, vt = q[1:, 0], q[1:, 1]
        cp, ct = c
        rows_vp, rows_vt = vp.unbind(0), vt.unbind(0)
        # Error quaternion conj(q_pred) q_target = (w, u) and e_r = 2 atan(|u| / w) u / |u|
        # (the signed atan gives the angle in [0, pi] whatever the sign of w).
        w = _cf.dot(rows_vp, rows_vt, out=torch.empty_like(cp)).addcmul_(cp, ct)
        u = vt * cp
        u.addcmul_(vp, ct, value=-1.0)
        rows_u = u.unbind(0)
        _cf.add_cross_(rows_u, rows_vt, rows_vp)
        norm = _cf.dot(rows_u, rows_u, out=torch.empty_like(cp)).add_(_series.TINY).sqrt()
        tan_half = norm / w
        half_phi = tan_half.atan()
        torch.mul(half_phi, half_phi, out=sq[0]).mul_(4.0)
        scale = torch.div(half_phi, norm).mul_(2.0)
        dt = x[3:, 1].sub_(x[3:, 0])
        ctx.iso = None if ctx.needs_input_grad[2] else _block_isotropic(weights)
        if ctx.iso is not None:
            a, b = ctx.iso
            e_r = u.mul_(scale)
            rows_dt = dt.unbind(0)
            loss = _cf.dot(rows_dt, rows_dt, out=w).mul_(b).add_(sq[0], alpha=a)
            ctx.save_for_backward(r, c, s, q, sq, e_r, dt)
        else:
            z = weights.to(device=x.device, dtype=torch.float64)
            e = x.new_empty((6, n))
            torch.mul(u, scale, out=e[:3])
            _cf.quat_rotate(q[:, 0], dt, inverse=True, out=e[3:])
            loss = (e * e).mul_(z[:, None]).sum(0) if z.dim() == 1 else (e * (z @ e)).sum(0)
            ctx.save_for_backward(r, c, s, q, sq, e, z, half_phi, tan_half)
        ctx.riemannian = riemannian
        ctx.dtypes = (pred.dtype, target.dtype, weights.dtype)
        ctx.weights_device = weights.device
        return loss.to(torch.result_type(pred, target))

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad: Tensor) -> tuple[Tensor | None, ...]:
        pred_dtype, target_dtype, weights_dtype = ctx.dtypes
        grad = grad.to(torch.float64)
        want_target = ctx.needs_input_grad[1] and not ctx.riemannian
        k = 2 if want_target else 1
        post = None  # factor of the J_l(r) y rows, if y is given up to one
        if ctx.iso is not None:
            r, c, s, q, sq, e_r, dt = ctx.saved_tensors
            a, b = ctx.iso
            n = dt.shape[1]
            out = dt.new_empty((k, 6, n))
            torch.mul(dt, grad * (-2.0 * b), out=out[0, 3:])
            # y = -g_r for the prediction and g_r for the target, with g_r = 2 a grad e_r.
            y = e_r[:, None].expand(3, k, n)
            post = grad * (2.0 * a)
            post = torch.stack([post.neg(), post]) if want_target else post.neg_()
            coef = _jacobian_coefficients(sq, c, s, k, None)
        else:
            r, c, s, q, sq, e, z, half_phi, tan_half = ctx.saved_tensors
            n = e.shape[1]
            g = (e * z[:, None] if z.dim() == 1 else z @ e).mul_(grad * 2.0)
            e_r, g_r, g_t = e[:3], g[:3], g[3:]
            out = g.new_empty((k, 6, n))
            _cf.quat_rotate(q[:, 0], g_t, out=out[0, 3:]).neg_()  # -R_pred g_t
            if ctx.riemannian:
                y = g_r.neg()[:, None]
                coef = _jacobian_coefficients(sq, c, s, k, None)
            else:
                aw = half_phi / tan_half  # (phi/2) cot(phi/2)
                coef = _jacobian_coefficients(sq, c, s, k, aw)
                rows_er, rows_gr = e_r.unbind(0), g_r.unbind(0)
                kd = _cf.dot(rows_er, rows_gr, out=torch.empty_like(aw)).mul_(coef[0])
                coef = coef[1:]
                # y_pred = -J_l(-e_r)^-1 g_r - e_t x g_t and y_target = J_l(e_r)^-1 g_r, with
                # J_l(-+e_r)^-1 g_r = aw g_r + D (e_r . g_r) e_r +- e_r x g_r / 2.
                y = g.new_empty((3, k, n))
                y_pred = y[:, 0]
                if want_target:
                    y_target = y[:, 1]
                    torch.mul(g_r, aw, out=y_target).addcmul_(e_r, kd)
                    torch.neg(y_target, out=y_pred)
                    _cf.add_cross_(y_target.unbind(0), rows_er, rows_gr, -0.5)
                else:
                    torch.mul(g_r, aw.neg_(), out=y_pred).addcmul_(e_r, kd, value=-1.0)
                rows_y = y_pred.unbind(0)
                _cf.add_cross_(rows_y, rows_er, rows_gr, -0.5)
                _cf.add_cross_(rows_y, e[3:].unbind(0), g_t.unbind(0), -1.0)
        if want_target:
            torch.neg(out[0, 3:], out=out[1, 3:])
        jl = out[:, :3].transpose(0, 1)
        _apply_left_jacobian(jl, r[:, :k], q[1:, :k], c[:k], s[:k], coef, y)
        if post is not None:
            jl.mul_(post)
        grad_pred = grad_target = grad_weights = None
        if ctx.needs_input_grad[0]:
            grad_pred = out[0].T.to(pred_dtype, memory_format=torch.contiguous_format)
        if want_target:
            grad_target = out[1].T.to(target_dtype, memory_format=torch.contiguous_format)
        if ctx.needs_input_grad[2]:
            grad_weights = ((grad * e.square()).sum(1) if z.dim() == 1 else (grad * e) @ e.T).to(
                device=ctx.weights_device, dtype=weights_dtype
            )
        return grad_pred, grad_target, grad_weights, None


def reduce_loss(loss: Tensor, reduction: str, func: str) -> Tensor:
    """Reduce per-pose losses by ``"mean"``, ``"sum"`` or ``"none"`` (error names ``func``)."""
    if reduction == "mean":
        return loss.mean()
    if reduction == "sum":
        return loss.sum()
    if reduction == "none":
        return loss
    raise ValueError(f"{func}(): 'reduction' must be 'mean', 'sum' or 'none', got {reduction!r}")


def resolve_weights(weights: Tensor | None, like: Tensor, func: str) -> Tensor:
    """The default Z (dtype and device of ``like``) for ``None``, else ``weights`` validated."""
    if weights is None:
        return default_metric_weights(dtype=like.dtype, device=like.device)
    return validate_metric_weights(weights, func)


def _se3_loss_unchecked(
    pred: Tensor, target: Tensor, weights: Tensor, reduction: str, gradient: str
) -> Tensor:
    func = "se3_geodesic_loss"
    if gradient == "autograd":
        z = weights.to(device=pred.device, dtype=torch.result_type(pred, target))
        loss = quadratic_form(se3_error(pred, target), z)
    elif gradient in ("exact", "riemannian"):
        riemannian = gradient == "riemannian"
        if riemannian and target.requires_grad:
            raise ValueError(
                f"{func}(): gradient='riemannian' gives no gradient to 'target'; "
                "detach it or use gradient='exact'"
            )
        pred_b, target_b = torch.broadcast_tensors(pred, target)
        loss = _SE3GeodesicLossFunction.apply(
            pred_b.reshape(-1, 6), target_b.reshape(-1, 6), weights, riemannian
        ).reshape(pred_b.shape[:-1])
    else:
        raise ValueError(
            f"{func}(): 'gradient' must be 'exact', 'riemannian' or 'autograd', got {gradient!r}"
        )
    return reduce_loss(loss, reduction, func)


def se3_geodesic_loss(
    pred: Tensor,
    target: Tensor,
    weights: Tensor | None = None,
    reduction: Reduction = "mean",
    gradient: Gradient = "exact",
) -> Tensor:
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
    return _se3_loss_unchecked(
        pred, target, resolve_weights(weights, pred, func), reduction, gradient
    )


class SE3GeodesicLoss(nn.Module):
    """Module form of :func:`se3_geodesic_loss`; Z is validated once and kept as a buffer.

    Args:
        weights: Z as a (6,) diagonal or (6, 6) SPD matrix, or ``None`` for the default.
        reduction: ``"mean"``, ``"sum"`` or ``"none"``.
        gradient: ``"exact"``, ``"riemannian"`` or ``"autograd"``.
    """

    def __init__(
        self,
        weights: Tensor | None = None,
        reduction: Reduction = "mean",
        gradient: Gradient = "exact",
    ) -> None:
        super().__init__()
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(
                f"SE3GeodesicLoss(): 'reduction' must be 'mean', 'sum' or 'none', got {reduction!r}"
            )
        if gradient not in ("exact", "riemannian", "autograd"):
            raise ValueError(
                f"SE3GeodesicLoss(): 'gradient' must be 'exact', 'riemannian' or "
                f"'autograd', got {gradient!r}"
            )
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
