"""Pose heads: a linear layer from backbone features to the labels of one pose representation.

A head's output is in the units of :func:`svr.sampling.poses.pose_labels` (rad, mm), so that it goes
straight into the representation's loss and :meth:`PoseHead.to_pose` recovers pose vectors with
the :mod:`svr.geometry` converters. The linear layer's raw outputs are kept O(1): its millimetre
outputs are multiplied by ``translation_scale_mm`` (by ``anchor_half_size_mm`` for the anchor
points), the others (rotation vector, quaternion, 6D columns) are used as they are.

Initialisation: zero weights and a bias equal to the scaled label of the identity pose, so that an
untrained network predicts the identity pose at the origin for every input: ``0`` for ``"se3"``,
``(1, 0, 0, 0, 0, 0, 0)`` for ``"quat_translation"``, ``(-1, -1, 0, 0, 0, 0, 1, -1, 0)`` for
``"anchor_points"`` and ``(1, 0, 0, 0, 1, 0, 0, 0, 0)`` for ``"rotation6d_translation"``.

``"se3"`` heads have two rotation parameterisations (``rotation=``): ``"rotvec"``, the rotation
vector itself, and ``"6d"``, two 3-vectors turned into a rotation by Gram-Schmidt (Zhou et al.
2019) and then into its rotation vector, so that the output is still the pose vector the SE(3)
geodesic loss takes. No continuous map from rotations to rotation vectors exists (the vector
jumps at angle pi), so a network regressing rotation vectors over all of SO(3) must learn a
discontinuous function; the 6D columns are a continuous function of the rotation, and the loss,
a function of the rotation only, stays smooth through the conversion.

The ``"se3"`` rotation-vector output is not bounded: the zero initialisation keeps it small, as
``reference/se3_loss.md`` advises (the map ``r -> R`` loses gain only as ``|r| -> 2 pi``), and a
bound such as ``pi tanh(r / pi)`` would slow learning of the rotations by nearly ``pi`` that random
+-90 degree Euler poses contain. :meth:`PoseHead.to_pose` brings the angle into ``[0, pi]``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from svr.geometry import (
    ANCHOR_HALF_SIZE_MM,
    anchor_points_to_pose,
    matrix_to_quat,
    quat_to_rotvec,
    quat_translation_to_pose,
    regularize_rotvec,
    rotation_6d_to_matrix,
    rotation_6d_translation_to_pose,
)
from svr.losses import DEFAULT_LENGTH_SCALE_MM
from svr.sampling.poses import REPRESENTATIONS, Representation, pose_labels

OUTPUT_SIZES: dict[str, int] = {
    "se3": 6,
    "quat_translation": 7,
    "anchor_points": 9,
    "rotation6d_translation": 9,
}
"""Number of outputs of each representation (the last dimension of its labels)."""

SE3_ROTATIONS = ("rotvec", "6d")
"""Rotation parameterisations of the ``"se3"`` head's linear layer."""


def check_representation(representation: object, owner: str) -> None:
    """Check that ``representation`` is one of :data:`svr.sampling.poses.REPRESENTATIONS`.

    Raises:
        ValueError: Naming ``owner`` and listing the valid names.
    """
    if representation not in REPRESENTATIONS:
        raise ValueError(
            f"{owner}: 'representation' must be one of {', '.join(REPRESENTATIONS)}, "
            f"got {representation!r}"
        )


def check_length(value: object, owner: str, name: str) -> None:
    """Check that ``value`` is a finite number > 0 (a length in mm, not a bool).

    Raises:
        ValueError: Naming ``owner`` and the field ``name``.
    """
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not (ok and math.isfinite(value) and value > 0):
        raise ValueError(f"{owner}: '{name}' must be a finite number > 0, got {value!r}")


class PoseHead(nn.Module):
    """Linear pose head whose outputs are labels of ``representation`` (rad, mm).

    Args:
        in_features: Number of input features, >= 1.
        representation: One of :data:`svr.sampling.poses.REPRESENTATIONS`.
        translation_scale_mm: Millimetres per unit of the raw translation outputs, > 0.
        anchor_half_size_mm: Half-size ``a`` (mm) of the anchor-point triangle and millimetres per
            unit of the raw anchor-point outputs, > 0 (``"anchor_points"`` only).
        rotation: ``"se3"`` only: ``"rotvec"`` (the linear layer gives the rotation vector) or
            ``"6d"`` (it gives two 3-vectors, turned into the rotation vector; module docstring).

    Attributes:
        linear: The ``(in_features -> OUTPUT_SIZES[representation])`` layer of raw outputs.
        scale: (D,) buffer multiplying the raw outputs.

    Raises:
        ValueError: For an unknown representation or a bad size or length.
    """

    def __init__(
        self,
        in_features: int,
        representation: Representation,
        translation_scale_mm: float = DEFAULT_LENGTH_SCALE_MM,
        anchor_half_size_mm: float = ANCHOR_HALF_SIZE_MM,
        rotation: str = "rotvec",
    ) -> None:
        super().__init__()
        if isinstance(in_features, bool) or not isinstance(in_features, int) or in_features < 1:
            raise ValueError(
                f"PoseHead: 'in_features' must be an integer >= 1, got {in_features!r}"
            )
        check_representation(representation, "PoseHead")
        check_length(translation_scale_mm, "PoseHead", "translation_scale_mm")
        check_length(anchor_half_size_mm, "PoseHead", "anchor_half_size_mm")
        if rotation not in SE3_ROTATIONS or (rotation != "rotvec" and representation != "se3"):
            raise ValueError(
                f"PoseHead: 'rotation' must be one of {', '.join(SE3_ROTATIONS)} ('6d' for the "
                f"'se3' representation only), got {rotation!r} for {representation!r}"
            )
        self.rotation = rotation
        self.representation = representation
        self.translation_scale_mm = float(translation_scale_mm)
        self.anchor_half_size_mm = float(anchor_half_size_mm)
        size = OUTPUT_SIZES[representation] + (3 if rotation == "6d" else 0)
        self.linear = nn.Linear(in_features, size)
        if representation == "anchor_points":
            scale = torch.full((size,), self.anchor_half_size_mm)
        else:
            scale = torch.ones(size)
            scale[-3:] = self.translation_scale_mm
        self.register_buffer("scale", scale, persistent=False)
        identity = pose_labels(
            torch.zeros(6, dtype=torch.float64),
            "rotation6d_translation" if rotation == "6d" else representation,
            anchor_half_size_mm,
        )
        with torch.no_grad():
            nn.init.zeros_(self.linear.weight)
            self.linear.bias.copy_(identity / scale.double())

    def forward(self, features: Tensor) -> Tensor:
        """Labels predicted from features.

        Args:
            features: (B, in_features) features.

        Returns:
            (B, OUTPUT_SIZES[representation]) outputs in the label units of
            :func:`svr.sampling.poses.pose_labels` (rad, mm).
        """
        raw = self.linear(features) * self.scale
        if self.rotation == "rotvec":
            return raw
        rotvec = quat_to_rotvec(matrix_to_quat(rotation_6d_to_matrix(raw[..., :6])))
        return torch.cat([rotvec, raw[..., 6:]], dim=-1)

    def to_pose(self, output: Tensor) -> Tensor:
        """Pose vectors of outputs (or labels) of this head's representation.

        Args:
            output: (..., OUTPUT_SIZES[representation]) outputs in label units.

        Returns:
            (..., 6) pose vectors ``(r, t)``: rotation vector with angle in ``[0, pi]`` (rad),
            translation (mm).
        """
        if self.representation == "se3":
            if output.shape[-1:] != (6,):
                raise ValueError(
                    f"PoseHead.to_pose(): 'output' must have shape (..., 6), got "
                    f"{tuple(output.shape)}"
                )
            return torch.cat([regularize_rotvec(output[..., :3]), output[..., 3:]], dim=-1)
        if self.representation == "quat_translation":
            return quat_translation_to_pose(output)
        if self.representation == "anchor_points":
            return anchor_points_to_pose(output, self.anchor_half_size_mm)
        return rotation_6d_translation_to_pose(output)

    def extra_repr(self) -> str:
        """Hyper-parameters shown by ``repr``."""
        return (
            f"representation={self.representation!r}, translation_scale_mm="
            f"{self.translation_scale_mm}, anchor_half_size_mm={self.anchor_half_size_mm}"
        )
