"""The registry of pose representations: the one place that lists them.

A representation is the form of a slice pose that a network outputs and a loss compares: its
labels are made from pose vectors ``(r, t)`` (rad, mm) by ``encode`` and turned back into pose
vectors by ``decode``. Everything that depends on the representation reads
:data:`REPRESENTATIONS`: the training labels (:func:`svr.sampling.poses.pose_labels`), the dataset
and model configurations, the pose heads (:class:`svr.models.heads.PoseHead`: output size, raw
output scale, identity initialisation, ``to_pose``), the losses
(:func:`svr.models.network.loss_function`) and ``svr train --loss``. Adding a representation
means adding one :class:`PoseRepresentation` below (and its name to :data:`Representation`).

The representations (``name`` is stored in checkpoint configs, ``cli_name`` is ``svr train
--loss``; D is ``size``):

====================== ======== === ==========================================================
name                   CLI name  D  label (units)
====================== ======== === ==========================================================
se3                    se3       6  the pose vector ``(r, t)`` itself (rad, mm)
quat_translation       posenet   7  ``(w, x, y, z, t)``, ``w >= 0`` (unit quaternion, mm)
anchor_points          anchor    9  ``(P1, P2, P3)``: three slice-plane points in the target
                                    frame, ``P1 = T(-a, -a, 0)``, ``P2 = t``, ``P3 = T(a, -a, 0)``
                                    for the half-size ``a`` (mm)
rotation6d_translation rot6d     9  the first two columns of ``R``, then ``t`` (unitless, mm)
====================== ======== === ==========================================================

The losses are :func:`svr.losses.se3_geodesic_loss` (with metric weights Z),
:func:`svr.losses.posenet_loss`, :func:`svr.losses.anchor_point_loss` and
:func:`svr.losses.rotation_6d_loss`, each with its default parameters; the converters are those of
:mod:`svr.geometry.conversions`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from svr.geometry import (
    anchor_points_to_pose,
    pose_to_anchor_points,
    pose_to_quat_translation,
    pose_to_rotation_6d_translation,
    quat_translation_to_pose,
    regularize_rotvec,
    rotation_6d_translation_to_pose,
)
from svr.geometry._validation import check_tensor
from svr.geometry.mirror import ReflectionPlane
from svr.losses.baselines import anchor_point_loss, posenet_loss, rotation_6d_loss
from svr.losses.orbit import symmetric_se3_geodesic_loss
from svr.losses.se3 import se3_geodesic_loss
from svr.validation import check_bool, check_callable, check_int, check_str

Representation = Literal["se3", "quat_translation", "anchor_points", "rotation6d_translation"]
"""Names of the registered representations, for type hints (the same as :data:`REPRESENTATIONS`'s
keys, in order)."""

Converter = Callable[[Tensor, float], Tensor]
"""``convert(x, anchor_half_size_mm) -> y``: the second argument is the half-size (mm) of the
anchor-point triangle, which representations without anchor points ignore."""

PoseLoss = Callable[..., Tensor]
"""``loss(pred, target, reduction="mean") -> Tensor``: (..., D) outputs and (..., D) labels to a
scalar (``"mean"``, ``"sum"``) or (...) losses (``"none"``)."""

LossFactory = Callable[[Tensor | None, float], PoseLoss]
"""``make(weights, anchor_half_size_mm) -> loss``: ``weights`` is the SE(3) metric Z or ``None``."""

OrbitLossFactory = Callable[[Tensor | None, tuple[ReflectionPlane, ...]], PoseLoss]
"""``make(weights, planes) -> loss``: a loss to the nearest member of the label's mirror orbit."""

ScaleFactory = Callable[[float, float], Tensor]
"""``scale(translation_scale_mm, anchor_half_size_mm) -> (D,)``: label units per raw output."""


@dataclass(frozen=True)
class PoseRepresentation:
    """One pose representation: its names, label size, converters and loss.

    Attributes:
        name: The persisted name (checkpoint configs, ``representation`` fields).
        cli_name: The name ``svr train --loss`` takes.
        size: Number D >= 1 of label components (the last dimension of the labels).
        encode: ``encode(poses, anchor_half_size_mm)``: (..., 6) pose vectors (rad, mm), slice
            plane -> target frame, to (..., D) labels in the dtype and device of ``poses``.
        decode: ``decode(labels, anchor_half_size_mm)``: (..., D) labels or network outputs to
            (..., 6) pose vectors, rotation angle in ``[0, pi]`` (rad), translation (mm).
        loss: ``loss(weights, anchor_half_size_mm)``: the training loss ``f(pred, target,
            reduction="mean")`` of (..., D) outputs and labels; ``weights`` (the SE(3) metric Z,
            already validated) is ``None`` unless ``metric_weights``.
        output_scale: ``output_scale(translation_scale_mm, anchor_half_size_mm)``: a (D,)
            float tensor of label units per raw output of a linear pose head, which keeps the
            raw outputs O(1).
        metric_weights: Whether ``loss`` takes the SE(3) metric weights Z.
        orbit_loss: ``orbit_loss(weights, planes)``: a fused loss to the nearest member of the
            label's mirror orbit, or ``None`` to build it from ``loss``, ``decode`` and
            ``encode`` with :func:`svr.losses.orbit.orbit_min_loss`.

    Raises:
        ConfigFieldError: On construction, naming the field, for an empty name, a size < 1 or a
            converter that is not callable.
    """

    name: Representation
    cli_name: str
    size: int
    encode: Converter
    decode: Converter
    loss: LossFactory
    output_scale: ScaleFactory
    metric_weights: bool = False
    orbit_loss: OrbitLossFactory | None = None

    def __post_init__(self) -> None:
        owner = "PoseRepresentation"
        check_str(owner, "name", self.name)
        check_str(owner, "cli_name", self.cli_name)
        check_int(owner, "size", self.size, minimum=1)
        for name in ("encode", "decode", "loss", "output_scale"):
            check_callable(owner, name, getattr(self, name))
        check_bool(owner, "metric_weights", self.metric_weights)
        if self.orbit_loss is not None:
            check_callable(owner, "orbit_loss", self.orbit_loss)


def _translation_scale(size: int) -> ScaleFactory:
    """Scale of labels whose last three components are a translation in mm, the rest unitless."""

    def scale(translation_scale_mm: float, anchor_half_size_mm: float) -> Tensor:
        out = torch.ones(size)
        out[-3:] = translation_scale_mm
        return out

    return scale


def _anchor_scale(translation_scale_mm: float, anchor_half_size_mm: float) -> Tensor:
    """Scale of anchor-point labels: every component in units of the half-size ``a`` (mm)."""
    return torch.full((9,), anchor_half_size_mm)


def _se3_decode(labels: Tensor, anchor_half_size_mm: float) -> Tensor:
    """Pose vectors of ``"se3"`` labels: the rotation angle brought into ``[0, pi]``."""
    check_tensor(labels, "REPRESENTATIONS['se3'].decode", "labels", (6,))
    return torch.cat([regularize_rotvec(labels[..., :3]), labels[..., 3:]], dim=-1)


_ENTRIES = (
    PoseRepresentation(
        name="se3",
        cli_name="se3",
        size=6,
        encode=lambda poses, a: poses,
        decode=_se3_decode,
        loss=lambda weights, a: functools.partial(se3_geodesic_loss, weights=weights),
        output_scale=_translation_scale(6),
        metric_weights=True,
        orbit_loss=lambda weights, planes: functools.partial(
            symmetric_se3_geodesic_loss, planes=planes, weights=weights
        ),
    ),
    PoseRepresentation(
        name="quat_translation",
        cli_name="posenet",
        size=7,
        encode=lambda poses, a: pose_to_quat_translation(poses),
        decode=lambda labels, a: quat_translation_to_pose(labels),
        loss=lambda weights, a: posenet_loss,
        output_scale=_translation_scale(7),
    ),
    PoseRepresentation(
        name="anchor_points",
        cli_name="anchor",
        size=9,
        encode=pose_to_anchor_points,
        decode=anchor_points_to_pose,
        loss=lambda weights, a: functools.partial(anchor_point_loss, half_size_mm=a),
        output_scale=_anchor_scale,
    ),
    PoseRepresentation(
        name="rotation6d_translation",
        cli_name="rot6d",
        size=9,
        encode=lambda poses, a: pose_to_rotation_6d_translation(poses),
        decode=lambda labels, a: rotation_6d_translation_to_pose(labels),
        loss=lambda weights, a: rotation_6d_loss,
        output_scale=_translation_scale(9),
    ),
)

REPRESENTATIONS: dict[str, PoseRepresentation] = {entry.name: entry for entry in _ENTRIES}
"""The registered representations by persisted name, in order (treat as read-only)."""


def get_representation(name: object, owner: str) -> PoseRepresentation:
    """The registered representation called ``name``.

    Args:
        name: A persisted name, one of :data:`REPRESENTATIONS`' keys.
        owner: The function or class asking, named in the error message.

    Returns:
        Its registry entry.

    Raises:
        ValueError: Naming ``owner`` and listing the valid names, if ``name`` is not registered.
    """
    if not isinstance(name, str) or name not in REPRESENTATIONS:
        raise ValueError(
            f"{owner}: 'representation' must be one of {', '.join(REPRESENTATIONS)}, got {name!r}"
        )
    return REPRESENTATIONS[name]


def representations_by_cli_name() -> dict[str, PoseRepresentation]:
    """The registered representations by their command-line name (``svr train --loss``).

    Returns:
        A new dict from ``cli_name`` to the entry, in registry order.
    """
    return {entry.cli_name: entry for entry in REPRESENTATIONS.values()}
