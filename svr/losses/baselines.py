"""Baseline pose losses, with the calling convention of :func:`svr.losses.se3_geodesic_loss`.

Each takes the network output and the target in the same representation (see
:mod:`svr.geometry.conversions` for the layouts and the converters from pose vectors) and
returns the loss reduced by ``reduction``. Translations are divided by a length scale so that
millimetres and the rotation terms are commensurate, as in the SE(3) loss.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from svr.geometry._validation import check_tensor
from svr.geometry.conversions import ANCHOR_HALF_SIZE_MM
from svr.geometry.so3 import rotation_6d_to_matrix
from svr.losses.metric_weights import DEFAULT_LENGTH_SCALE_MM
from svr.losses.se3 import Reduction, reduce_loss

POSENET_BETA = 500.0
"""Default quaternion weight of :func:`posenet_loss` (the authors' fetal experiments)."""

KENDALL_INITIAL_LOG_VARS = (0.0, -3.0)
"""Initial ``(s_t, s_q)`` of the learned weighting (Kendall & Cipolla 2017)."""


def _check_positive(value: float, func: str, name: str) -> None:
    if not value > 0:
        raise ValueError(f"{func}(): '{name}' must be > 0, got {value}")


def posenet_loss(
    pred: Tensor,
    target: Tensor,
    beta: float = POSENET_BETA,
    reduction: Reduction = "mean",
    squared: bool = True,
    translation_scale_mm: float = DEFAULT_LENGTH_SCALE_MM,
    log_vars: Tensor | None = None,
) -> Tensor:
    """PoseNet loss on quaternion + translation (Kendall et al. 2015).

    With ``dt = (t_pred - t) / L`` and ``dq = q_pred - q / |q|`` (the target quaternion normalised
    and flipped to ``w >= 0``; the prediction is used as it is, not normalised):

    * ``squared=True`` (default, the authors' fetal variant): ``|dt|^2 / 2 + beta |dq|^2 / 2``;
    * ``squared=False`` (the original): ``|dt| + beta |dq|``;
    * with ``log_vars = (s_t, s_q)``, the learned homoscedastic weighting of Kendall & Cipolla
      (2017) replaces ``beta``: ``L_t exp(-s_t) + s_t + L_q exp(-s_q) + s_q``.

    Args:
        pred: (..., 7) predicted ``(w, x, y, z, t_x, t_y, t_z)``, translation in mm.
        target: (..., 7) true quaternion + translation, broadcastable with ``pred``.
        beta: Weight of the quaternion term, > 0 (ignored when ``log_vars`` is given).
        reduction: ``"mean"``, ``"sum"`` or ``"none"``.
        squared: Squared (default) or plain L2 norms.
        translation_scale_mm: Length L (mm) dividing the translation error, > 0.
        log_vars: Optional (2,) tensor ``(s_t, s_q)`` of learned log-variances.

    Returns:
        The loss: a scalar, or (...) for ``reduction="none"``.
    """
    func = "posenet_loss"
    check_tensor(pred, func, "pred", (7,))
    check_tensor(target, func, "target", (7,))
    _check_positive(beta, func, "beta")
    _check_positive(translation_scale_mm, func, "translation_scale_mm")
    q = nn.functional.normalize(target[..., :4], dim=-1)
    q = torch.where(q[..., :1] < 0, -q, q)
    dt = (pred[..., 4:] - target[..., 4:]) / translation_scale_mm
    dq = pred[..., :4] - q
    if squared:
        loss_t, loss_q = 0.5 * dt.square().sum(-1), 0.5 * dq.square().sum(-1)
    else:
        loss_t, loss_q = dt.norm(dim=-1), dq.norm(dim=-1)
    if log_vars is None:
        loss = loss_t + beta * loss_q
    else:
        check_tensor(log_vars, func, "log_vars", (2,))
        s_t, s_q = log_vars.unbind(-1)
        loss = loss_t * torch.exp(-s_t) + s_t + loss_q * torch.exp(-s_q) + s_q
    return reduce_loss(loss, reduction, func)


class PoseNetLoss(nn.Module):
    """Module form of :func:`posenet_loss`; optionally learns ``(s_t, s_q)`` (Kendall & Cipolla).

    Args:
        beta: Quaternion weight when the weighting is not learned.
        reduction: ``"mean"``, ``"sum"`` or ``"none"``.
        squared: Squared or plain L2 norms.
        translation_scale_mm: Length dividing the translation error.
        learn_weights: Learn the log-variances ``(s_t, s_q)``, initialised to ``(0, -3)``; add the
            module's parameters to the optimiser.
    """

    def __init__(
        self,
        beta: float = POSENET_BETA,
        reduction: Reduction = "mean",
        squared: bool = True,
        translation_scale_mm: float = DEFAULT_LENGTH_SCALE_MM,
        learn_weights: bool = False,
    ) -> None:
        super().__init__()
        _check_positive(beta, "PoseNetLoss", "beta")
        _check_positive(translation_scale_mm, "PoseNetLoss", "translation_scale_mm")
        self.beta = beta
        self.reduction = reduction
        self.squared = squared
        self.translation_scale_mm = translation_scale_mm
        self.log_vars = (
            nn.Parameter(torch.tensor(KENDALL_INITIAL_LOG_VARS)) if learn_weights else None
        )

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """Loss of (..., 7) predictions against (..., 7) targets."""
        return posenet_loss(
            pred,
            target,
            self.beta,
            self.reduction,
            self.squared,
            self.translation_scale_mm,
            self.log_vars,
        )

    def extra_repr(self) -> str:
        """Hyper-parameters shown by ``repr``."""
        return (
            f"beta={self.beta}, squared={self.squared}, translation_scale_mm="
            f"{self.translation_scale_mm}, learn_weights={self.log_vars is not None}, "
            f"reduction={self.reduction!r}"
        )


def anchor_point_loss(
    pred: Tensor,
    target: Tensor,
    reduction: Reduction = "mean",
    half_size_mm: float = ANCHOR_HALF_SIZE_MM,
) -> Tensor:
    """Anchor Points loss (Hou et al.): squared distance of three plane points, in units of ``a``.

    ``sum_i |P_i,pred - P_i|^2 / a^2`` over the three points of
    :func:`svr.geometry.pose_to_anchor_points`; the pose is recovered from predicted points by
    :func:`svr.geometry.anchor_points_to_pose`.

    Args:
        pred: (..., 9) predicted points ``(P1, P2, P3)`` in mm.
        target: (..., 9) true points, broadcastable with ``pred``.
        reduction: ``"mean"``, ``"sum"`` or ``"none"``.
        half_size_mm: The triangle's half-size ``a`` in mm, > 0.

    Returns:
        The loss: a scalar, or (...) for ``reduction="none"``.
    """
    func = "anchor_point_loss"
    check_tensor(pred, func, "pred", (9,))
    check_tensor(target, func, "target", (9,))
    _check_positive(half_size_mm, func, "half_size_mm")
    loss = ((pred - target) / half_size_mm).square().sum(-1)
    return reduce_loss(loss, reduction, func)


def rotation_6d_loss(
    pred: Tensor,
    target: Tensor,
    reduction: Reduction = "mean",
    translation_scale_mm: float = DEFAULT_LENGTH_SCALE_MM,
) -> Tensor:
    """Continuous 6D rotation + translation loss (Zhou et al. 2019).

    ``|R(d6_pred) - R(d6)|_F^2 + |t_pred - t|^2 / L^2`` with ``R`` the Gram-Schmidt map
    :func:`svr.geometry.rotation_6d_to_matrix`. Near the identity the rotation term is
    ``4 (1 - cos theta) ~ 2 theta^2``.

    Args:
        pred: (..., 9) predicted 6D rotation then translation (mm).
        target: (..., 9) true values, broadcastable with ``pred``.
        reduction: ``"mean"``, ``"sum"`` or ``"none"``.
        translation_scale_mm: Length L (mm) dividing the translation error, > 0.

    Returns:
        The loss: a scalar, or (...) for ``reduction="none"``.
    """
    func = "rotation_6d_loss"
    check_tensor(pred, func, "pred", (9,))
    check_tensor(target, func, "target", (9,))
    _check_positive(translation_scale_mm, func, "translation_scale_mm")
    d_rot = rotation_6d_to_matrix(pred[..., :6]) - rotation_6d_to_matrix(target[..., :6])
    d_t = (pred[..., 6:] - target[..., 6:]) / translation_scale_mm
    loss = d_rot.square().sum((-1, -2)) + d_t.square().sum(-1)
    return reduce_loss(loss, reduction, func)
