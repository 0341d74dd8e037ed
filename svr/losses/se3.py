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

from typing import Any, Literal

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from svr.geometry import _cf, _series
from svr.geometry._validation import check_tensor
from svr.geometry.se3 import se3_error
from svr.losses.metric_weights import default_metric_weights, validate_metric_weights

_Ctx = Any
"""The autograd context: the forward stores its own attributes on it, which torch's
``FunctionCtx`` type does not declare."""

Reduction = Literal["mean", "sum", "none"]
Gradient = Literal["exact", "riemannian", "autograd"]

_ONE = torch.ones((), dtype=torch.float64)


def quadratic_form(e: Tensor, weights: Tensor) -> Tensor:
    """``e^T Z e`` for Z given as a (6,) diagonal or a (6, 6) matrix; e is (..., 6) -> (...)."""
    if weights.dim() == 1:
        return (e.square() * weights).sum(-1)
    return ((e @ weights) * e).sum(-1)


def _cpu_diagonal(z: Tensor) -> list[float] | None:
    """The six entries of a diagonal Z as Python floats, or None if Z is a matrix.

    Only read on the CPU, where it costs no device synchronisation (None elsewhere).
    """
    if z.dim() != 1 or z.device.type != "cpu":
        return None
    return z.tolist()


def _block_isotropic(d: list[float] | None) -> tuple[float, float] | None:
    """``(a, b)`` if the diagonal ``d`` is ``(a, a, a, b, b, b)``, else None."""
    if d is None or not (d[0] == d[1] == d[2] and d[3] == d[4] == d[5]):
        return None
    return d[0], d[3]


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

    For any other diagonal Z on the CPU (the data-adaptive weights), its entries are read as
    Python numbers and folded into the row operations, and the products with the prediction's
    quaternion ``(c, v)`` are shared: the forward applies ``M(a) = c a + a x v`` to ``v_target``
    and ``dt`` at once (the error quaternion's vector part is ``M(v_target) - c_target v`` and
    ``e_t = R_pred^T dt = dt + 2 M(dt) x v``), and the backward needs no generic cross product
    with ``g`` (see :func:`_diagonal_backward`). Z of another kind (a matrix, on another device,
    or needing a gradient) takes the general path.
    """

    @staticmethod
    def forward(
        ctx: _Ctx, pred: Tensor, target: Tensor, weights: Tensor, riemannian: bool
    ) -> Tensor:
        n = pred.shape[0]
        x = pred.new_empty((6, 2, n), dtype=torch.float64)  # (component, pred/target, pose)
        x[:, 0].copy_(pred.T)
        x[:, 1].copy_(target.T)
        r = x[:3]
        sq = x.new_empty((3, n))  # phi^2 (error angle), theta_pred^2, theta_target^2
        rows_r = r.unbind(0)
        ctx.diag = None if ctx.needs_input_grad[2] else _cpu_diagonal(weights)
        ctx.iso = _block_isotropic(ctx.diag)
        anisotropic = ctx.diag is not None and ctx.iso is None
        # quaternions (c, v) = (cos(theta/2), s r) of pred and target, then (0, dt) if anisotropic
        q = x.new_empty((4, 3 if anisotropic else 2, n))
        c, s = _series.half_angle(
            _cf.dot(rows_r, rows_r, out=sq[1:]), out=(q[0, :2], sq.new_empty(2, n))
        )
        torch.mul(r, s, out=q[1:, :2])
        vp, vt = q[1:, 0], q[1:, 1]
        cp, ct = c
        rows_vp, rows_vt = vp.unbind(0), vt.unbind(0)
        # Error quaternion conj(q_pred) q_target = (w, u) and e_r = 2 atan(|u| / w) u / |u|
        # (the signed atan gives the angle in [0, pi] whatever the sign of w).
        w = _cf.dot(rows_vp, rows_vt, out=torch.empty_like(cp)).addcmul_(cp, ct)
        if anisotropic:
            # u = M(v_t) - c_t v_p and m = M(dt), with M(a) = c_p a + a x v_p for both at once.
            dt = torch.sub(x[3:, 1], x[3:, 0], out=q[1:, 2])
            stacked = q[1:, 1:]
            m = stacked * cp
            _cf.add_cross_(m.unbind(0), stacked.unbind(0), rows_vp)
            u = torch.addcmul(m[:, 0], vp, ct, value=-1.0)
        else:
            u = vt * cp
            u.addcmul_(vp, ct, value=-1.0)
            _cf.add_cross_(u.unbind(0), rows_vt, rows_vp)
            dt = x[3:, 1].sub_(x[3:, 0])
        rows_u = u.unbind(0)
        norm = _cf.dot(rows_u, rows_u, out=torch.empty_like(cp)).add_(_series.TINY).sqrt()
        tan_half = norm / w
        # atan(tan_half) as atan2(tan_half, 1): the same values to within an ulp, faster, and (a
        # binary operation) not split across threads below 32768 elements.
        half_phi = torch.atan2(tan_half, _ONE if w.is_cpu else w.new_ones(()))
        torch.mul(half_phi, half_phi, out=sq[0]).mul_(4.0)
        scale = torch.div(half_phi, norm).mul_(2.0)
        if ctx.iso is not None:
            a, b = ctx.iso
            e_r = u.mul_(scale)
            rows_dt = dt.unbind(0)
            loss = _cf.dot(rows_dt, rows_dt, out=w).mul_(b).add_(sq[0], alpha=a)
            ctx.save_for_backward(r, c, s, q, sq, e_r, dt)
        elif anisotropic:
            d = ctx.diag
            e = x.new_empty((2, 3, n))  # e_r, e_t
            torch.mul(u, scale, out=e[0])
            # e_t = R_pred^T dt = dt - 2 v_p x M(dt) = dt + 2 M(dt) x v_p.
            e3, e4, e5 = e[1].unbind(0)
            (mx, my, mz), (vx, vy, vz) = m[:, 1].unbind(0), rows_vp
            dx, dy, dz = dt.unbind(0)
            torch.addcmul(dx, my, vz, value=2.0, out=e3).addcmul_(mz, vy, value=-2.0)
            torch.addcmul(dy, mz, vx, value=2.0, out=e4).addcmul_(mx, vz, value=-2.0)
            torch.addcmul(dz, mx, vy, value=2.0, out=e5).addcmul_(my, vx, value=-2.0)
            e0, e1, e2 = e[0].unbind(0)
            # L_r = e_r^T Z_r e_r, kept for the backward pass, and the loss L_r + e_t^T Z_t e_t.
            l_r = torch.mul(e0, e0).mul_(d[0]).addcmul_(e1, e1, value=d[1])
            l_r.addcmul_(e2, e2, value=d[2])
            loss = torch.addcmul(l_r, e3, e3, value=d[3]).addcmul_(e4, e4, value=d[4])
            loss.addcmul_(e5, e5, value=d[5])
            ctx.save_for_backward(r, c, s, q, sq, e, l_r, half_phi, tan_half)
            # Row views for the backward pass, kept to spare re-slicing (they are not outputs).
            ctx.rows = (e0, e1, e2), (e3, e4, e5), rows_vp, r[:, 0].unbind(0)
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
    def backward(ctx: _Ctx, grad: Tensor) -> tuple[Tensor | None, ...]:
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
        elif ctx.diag is not None:
            out = _diagonal_backward(ctx, grad, want_target)
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
        if ctx.diag is None or ctx.iso is not None:
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


def _diagonal_backward(ctx: _Ctx, grad: Tensor, want_target: bool) -> Tensor:
    """Gradients of :class:`_SE3GeodesicLossFunction` for an anisotropic diagonal Z.

    Args:
        ctx: The forward pass's context: its saved tensors, ``ctx.rows`` (row views of ``e_r``,
            ``e_t``, ``v_pred`` and ``r_pred``) and ``ctx.diag`` (the six entries of Z).
        grad: (N,) float64 incoming gradient of the per-pose losses.
        want_target: Whether the target needs its gradient too.

    Returns:
        (k, 6, N) float64 gradients of the prediction (then of the target if ``want_target``,
        k = 2), components first.

    With ``aw = (phi/2) cot(phi/2)``, ``D = (1 - aw) / phi^2``, ``L_r = e_r^T Z_r e_r`` and
    ``B = aw Z_r e_r + D L_r e_r`` (``J_l(-+e_r)^-1 Z_r e_r = B -+ e_r x Z_r e_r / 2``, as
    ``e_r . Z_r e_r = L_r``), the prediction's rotation gradient is ``J_l(r_pred) y`` with
    ``y = -2 grad (B + e_r x Z_r e_r / 2 + e_t x Z_t e_t)`` and the target's ``J_l(r) y_t`` with
    ``y_t = 2 grad (B - e_r x Z_r e_r / 2)``; for diagonal Z, ``(e x Z e)_i = (z_i2 - z_i1)
    e_i1 e_i2`` for ``(i, i1, i2)`` cyclic. The translation gradients are
    ``-+2 grad R_pred Z_t e_t``. ``R_pred g`` and ``J_l(r_pred) y`` share ``M'(a) = c a + v x a``
    (``(c, v = s r)`` the prediction's quaternion), applied to both at once:
    ``R_pred g = g + 2 v x M'(g)`` and ``J_l(r_pred) y = 2 s M'(y) + C (r . y) r`` with
    ``C = (1 - 2 s c) / theta^2``. ``D`` and ``C`` cancel for small angles but only multiply
    terms that vanish like the squared angle (see :func:`_jacobian_coefficients`).
    """
    r, c, s, q, sq, e, l_r, half_phi, tan_half = ctx.saved_tensors
    rows_r, rows_t, rows_v, rows_rp = ctx.rows
    d = ctx.diag
    k = 2 if want_target else 1
    n = e.shape[-1]
    cp, sp = c[0], s[0]
    post = grad * -2.0
    a = e.new_empty((3, 2, n))  # g_t and y_pred (y up to the factor post)
    g_t, y = a.unbind(1)
    rows_g, rows_y = g_t.unbind(0), y.unbind(0)
    for row_g, row_t, z in zip(rows_g, rows_t, d[3:], strict=True):
        torch.mul(row_t, post, out=row_g).mul_(z)  # -2 grad Z_t e_t
    if ctx.riemannian:  # y_pred = -g_r
        for row_y, row_r, z in zip(rows_y, rows_r, d[:3], strict=True):
            torch.mul(row_r, z, out=row_y)
    else:
        aw = half_phi / tan_half  # (phi/2) cot(phi/2)
        # D L_r e_r + aw Z_r e_r with D = (1 - aw) / phi^2 (see _jacobian_coefficients).
        d_lr = torch.rsub(aw, 1.0).mul_(l_r).div_(sq[0] + _series.TINY)
        for row_y, row_r, z in zip(rows_y, rows_r, d[:3], strict=True):
            torch.mul(row_r, d_lr, out=row_y).addcmul_(row_r, aw, value=z)
        if want_target:
            y_target = y.clone()
            rows_target = y_target.unbind(0)
        # + e_r x Z_r e_r / 2 + e_t x Z_t e_t, with (e x Z e)_i = (z_i2 - z_i1) e_i1 e_i2 for
        # (i, i1, i2) cyclic.
        for i, row_y in enumerate(rows_y):
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            half_dr = 0.5 * (d[i2] - d[i1])
            if want_target:
                rows_target[i].addcmul_(rows_r[i1], rows_r[i2], value=-half_dr)
            row_y.addcmul_(rows_r[i1], rows_r[i2], value=half_dr)
            row_y.addcmul_(rows_t[i1], rows_t[i2], value=d[3 + i2] - d[3 + i1])
    m = a * cp
    rows_a, rows_m = a.unbind(0), m.unbind(0)
    _cf.add_cross_(rows_m, rows_v, rows_a)  # M'(g_t), M'(y)
    out = e.new_empty((k, 6, n))
    # R_pred g_t = g_t + 2 v x M'(g_t).
    (vx, vy, vz), (mx, my, mz) = rows_v, m[:, 0].unbind(0)
    (gx, gy, gz), (ox, oy, oz) = rows_g, out[0, 3:].unbind(0)
    torch.addcmul(gx, vy, mz, value=2.0, out=ox).addcmul_(vz, my, value=-2.0)
    torch.addcmul(gy, vz, mx, value=2.0, out=oy).addcmul_(vx, mz, value=-2.0)
    torch.addcmul(gz, vx, my, value=2.0, out=oz).addcmul_(vy, mx, value=-2.0)
    # J_l(r_pred) y = 2 s M'(y) + C (r . y) r, C = (1 - 2 s c) / theta^2.
    jl = torch.mul(m[:, 1], sp * 2.0, out=out[0, :3])
    coef = torch.mul(sp, cp).mul_(-2.0).add_(1.0).div_(sq[1] + _series.TINY)
    r_dot_y = _cf.dot(rows_rp, rows_y, out=torch.empty_like(sp)).mul_(coef)
    jl.addcmul_(r[:, 0], r_dot_y).mul_(post)
    if want_target:
        torch.neg(out[0, 3:], out=out[1, 3:])
        coef = torch.mul(s[1:], c[1:]).mul_(-2.0).add_(1.0).div_(sq[2:] + _series.TINY)
        jl = out[1:, :3].transpose(0, 1)
        _apply_left_jacobian(jl, r[:, 1:], q[1:, 1:2], c[1:], s[1:], coef, y_target[:, None])
        jl.mul_(grad * 2.0)
    return out


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

    weights: Tensor  # the validated Z, a buffer

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
