"""Symmetry-aware pose losses: the loss to the nearest member of the target's symmetry orbit.

For a (nearly) mirror-symmetric brain a slice at pose ``T`` and one at its mirror twin
(:func:`svr.geometry.mirror.mirror_twin`) are the same image, so a network cannot tell them
apart, and any unimodal loss trains it towards the average of the two, which is far from both.
The orbit loss

    ``L(pred, T) = min_k loss(pred, O_k(T))``,  ``O(T) = {T, twin_p(T) for each plane p}``

asks only for one of the poses the slice is consistent with. Which one is settled later, by a
stack's slice order (:mod:`svr.reconstruction.cnn_init`).

Gradients: each pose's loss is the loss to its selected orbit member ``k* = argmin_k``, so the
gradient is that member's loss gradient, exact wherever the minimum is unique. On the switching
set (two members at exactly the same loss) ``argmin`` takes the first, i.e. the target itself
before its twins: the gradient is the one-sided gradient of that member, an element of the
Clarke subdifferential of the minimum. Values and gradients are finite everywhere the wrapped
loss's are.

The SE(3) form evaluates all orbit members in one fused call of
:func:`svr.losses.se3_geodesic_loss`; the baselines are wrapped by :func:`orbit_min_loss` with
their own label encoders, so that the comparison of losses stays fair.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal, overload

from torch import Tensor

from svr.geometry._validation import check_tensor
from svr.geometry.mirror import SAGITTAL, ReflectionPlane, check_planes, orbit_poses
from svr.losses.se3 import Gradient, Reduction, reduce_loss, resolve_weights, se3_geodesic_loss


@overload
def orbit_min_loss(
    loss: Callable[[Tensor, Tensor], Tensor],
    pred: Tensor,
    target_poses: Tensor,
    planes: Sequence[ReflectionPlane] = ...,
    encode: Callable[[Tensor], Tensor] | None = ...,
    reduction: Reduction = ...,
    return_index: Literal[False] = ...,
) -> Tensor: ...
@overload
def orbit_min_loss(
    loss: Callable[[Tensor, Tensor], Tensor],
    pred: Tensor,
    target_poses: Tensor,
    planes: Sequence[ReflectionPlane] = ...,
    encode: Callable[[Tensor], Tensor] | None = ...,
    reduction: Reduction = ...,
    *,
    return_index: Literal[True],
) -> tuple[Tensor, Tensor]: ...
@overload
def orbit_min_loss(
    loss: Callable[[Tensor, Tensor], Tensor],
    pred: Tensor,
    target_poses: Tensor,
    planes: Sequence[ReflectionPlane] = ...,
    encode: Callable[[Tensor], Tensor] | None = ...,
    reduction: Reduction = ...,
    return_index: bool = ...,
) -> Tensor | tuple[Tensor, Tensor]: ...
def orbit_min_loss(
    loss: Callable[[Tensor, Tensor], Tensor],
    pred: Tensor,
    target_poses: Tensor,
    planes: Sequence[ReflectionPlane] = (SAGITTAL,),
    encode: Callable[[Tensor], Tensor] | None = None,
    reduction: Reduction = "mean",
    return_index: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """Loss of each prediction to the nearest member of its target's symmetry orbit.

    Args:
        loss: Per-pose loss ``loss(pred, labels) -> (...)`` (no reduction), e.g.
            ``functools.partial(posenet_loss, reduction="none")``.
        pred: (..., D) network outputs in the loss's representation.
        target_poses: (..., 6) true pose vectors (rad, mm), slice plane -> canonical frame.
        planes: The canonical-frame reflection planes; empty gives the plain loss.
        encode: Pose vectors (K, ..., 6) -> labels (K, ..., D) of the representation
            (e.g. :func:`svr.geometry.pose_to_quat_translation`); ``None`` for the pose vectors
            themselves.
        reduction: ``"mean"``, ``"sum"`` or ``"none"``.
        return_index: Also return the (...) int64 index of the selected orbit member
            (0: the target itself, ``k``: its twin under ``planes[k - 1]``).

    Returns:
        The reduced loss (a scalar, or (...) for ``"none"``), and the indices if asked for.

    Raises:
        ValueError: For a bad shape, plane or reduction.
    """
    func = "orbit_min_loss"
    check_tensor(target_poses, func, "target_poses", (6,))
    planes = check_planes(planes, func)
    orbit = orbit_poses(target_poses.detach(), planes)
    labels = orbit if encode is None else encode(orbit)
    per_member = loss(pred.unsqueeze(0).expand(labels.shape[:-1] + pred.shape[-1:]), labels)
    index = per_member.detach().argmin(0)
    selected = per_member.gather(0, index.unsqueeze(0)).squeeze(0)
    reduced = reduce_loss(selected, reduction, func)
    return (reduced, index) if return_index else reduced


def symmetric_se3_geodesic_loss(
    pred: Tensor,
    target: Tensor,
    planes: Sequence[ReflectionPlane] = (SAGITTAL,),
    weights: Tensor | None = None,
    reduction: Reduction = "mean",
    gradient: Gradient = "exact",
) -> Tensor:
    """SE(3) geodesic loss ``e^T Z e`` to the nearest member of the target's mirror orbit.

    ``min(L(pred, T), L(pred, twin(T)))`` for one plane (module docstring for the gradient on
    the switching set). All orbit members go through one fused call of
    :func:`svr.losses.se3_geodesic_loss`.

    Args:
        pred: (..., 6) predicted pose vectors ``(r, t)`` (rad, mm).
        target: (..., 6) true pose vectors, same shape as ``pred``; gets no gradient.
        planes: Canonical-frame reflection planes (default: the sagittal plane ``x = 0``).
        weights: Z as for :func:`svr.losses.se3_geodesic_loss` (``None``: the default).
        reduction: ``"mean"``, ``"sum"`` or ``"none"``.
        gradient: ``"exact"``, ``"riemannian"`` or ``"autograd"``.

    Returns:
        The loss in the inputs' dtype: a scalar, or (...) for ``reduction="none"``.

    Raises:
        ValueError: For bad shapes, weights, planes or options.
    """
    func = "symmetric_se3_geodesic_loss"
    check_tensor(pred, func, "pred", (6,))
    check_tensor(target, func, "target", (6,))
    if pred.shape != target.shape:
        raise ValueError(
            f"{func}(): 'pred' and 'target' must have the same shape, got "
            f"{tuple(pred.shape)} and {tuple(target.shape)}"
        )
    z = resolve_weights(weights, pred, func)

    def per_pose(p: Tensor, t: Tensor) -> Tensor:
        return se3_geodesic_loss(p, t, z, reduction="none", gradient=gradient)

    return orbit_min_loss(per_pose, pred, target, planes, reduction=reduction)
