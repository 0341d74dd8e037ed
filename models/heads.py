"""Pose heads: a linear layer from backbone features to the labels of one pose representation.

Everything a head needs to know about its representation comes from the registry
:data:`svr.representation_registry.REPRESENTATIONS`: the output size, the scale of the raw
outputs, the identity label and the decoder. A head's output is in the units of
:func:`svr.sampling.poses.pose_labels` (rad, mm), so that it goes straight into the
representation's loss and :meth:`PoseHead.to_pose` recovers pose vectors with the entry's
``decode``. The linear layer's raw outputs are kept O(1) by the entry's ``output_scale``: the
millimetre outputs are multiplied by ``translation_scale_mm`` (by ``anchor_half_size_mm`` for the
anchor points), the others (rotation vector, quaternion, 6D columns) are used as they are.

Initialisation: zero weights and a bias equal to the scaled label of the identity pose (the entry's
``encode`` of the zero pose vector), so that an untrained network predicts the identity pose at the
origin for every input: ``0`` for ``"se3"``, ``(1, 0, 0, 0, 0, 0, 0)`` for ``"quat_translation"``,
``(-1, -1, 0, 0, 0, 0, 1, -1, 0)`` for ``"anchor_points"`` and ``(1, 0, 0, 0, 1, 0, 0, 0, 0)`` for
``"rotation6d_translation"``.

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

import torch
from torch import Tensor, nn

from svr.geometry import ANCHOR_HALF_SIZE_MM, matrix_to_quat, quat_to_rotvec, rotation_6d_to_matrix
from svr.geometry._validation import check_tensor
from svr.losses import DEFAULT_LENGTH_SCALE_MM
from svr.representation_registry import REPRESENTATIONS, Representation, get_representation
from svr.validation import check_int, check_number

SE3_ROTATIONS = ("rotvec", "6d")
"""Rotation parameterisations of the ``"se3"`` head's linear layer."""

_SE3_6D_LAYER = "rotation6d_translation"
"""The representation whose layout the ``"6d"`` rotation of an ``"se3"`` head's layer takes."""


class PoseHead(nn.Module):
    """Linear pose head whose outputs are labels of ``representation`` (rad, mm).

    Args:
        in_features: Number of input features, >= 1.
        representation: A registered name (:data:`svr.representation_registry.REPRESENTATIONS`).
        translation_scale_mm: Millimetres per unit of the raw translation outputs, > 0.
        anchor_half_size_mm: Half-size ``a`` (mm) of the anchor-point triangle and millimetres per
            unit of the raw anchor-point outputs, > 0 (``"anchor_points"`` only).
        rotation: ``"se3"`` only: ``"rotvec"`` (the linear layer gives the rotation vector) or
            ``"6d"`` (it gives two 3-vectors, turned into the rotation vector; module docstring).

    Attributes:
        linear: The ``(in_features -> D)`` layer of raw outputs, ``D`` the registry entry's
            ``size`` (that of ``"rotation6d_translation"``, 9, for the ``"6d"`` rotation).
        scale: (D,) buffer multiplying the raw outputs (the entry's ``output_scale``).

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
        check_int("PoseHead", "in_features", in_features, minimum=1)
        entry = get_representation(representation, "PoseHead")
        check_number("PoseHead", "translation_scale_mm", translation_scale_mm, gt=0)
        check_number("PoseHead", "anchor_half_size_mm", anchor_half_size_mm, gt=0)
        if rotation not in SE3_ROTATIONS or (rotation != "rotvec" and representation != "se3"):
            raise ValueError(
                f"PoseHead: 'rotation' must be one of {', '.join(SE3_ROTATIONS)} ('6d' for the "
                f"'se3' representation only), got {rotation!r} for {representation!r}"
            )
        self.rotation = rotation
        self.representation = representation
        self.translation_scale_mm = float(translation_scale_mm)
        self.anchor_half_size_mm = float(anchor_half_size_mm)
        layer = REPRESENTATIONS[_SE3_6D_LAYER] if rotation == "6d" else entry
        self.linear = nn.Linear(in_features, layer.size)
        scale = layer.output_scale(self.translation_scale_mm, self.anchor_half_size_mm)
        self.register_buffer("scale", scale, persistent=False)
        identity = layer.encode(torch.zeros(6, dtype=torch.float64), self.anchor_half_size_mm)
        with torch.no_grad():
            nn.init.zeros_(self.linear.weight)
            self.linear.bias.copy_(identity / scale.double())

    def forward(self, features: Tensor) -> Tensor:
        """Labels predicted from features.

        Args:
            features: (B, in_features) features.

        Returns:
            (B, D) outputs in the label units of :func:`svr.sampling.poses.pose_labels` (rad, mm),
            ``D = REPRESENTATIONS[representation].size``.
        """
        raw = self.linear(features) * self.scale
        if self.rotation == "rotvec":
            return raw
        rotvec = quat_to_rotvec(matrix_to_quat(rotation_6d_to_matrix(raw[..., :6])))
        return torch.cat([rotvec, raw[..., 6:]], dim=-1)

    def to_pose(self, output: Tensor) -> Tensor:
        """Pose vectors of outputs (or labels) of this head's representation (its ``decode``).

        Args:
            output: (..., D) outputs in label units, ``D = REPRESENTATIONS[representation].size``.

        Returns:
            (..., 6) pose vectors ``(r, t)``: rotation vector with angle in ``[0, pi]`` (rad),
            translation (mm).

        Raises:
            TypeError: If ``output`` is not a floating-point tensor.
            ValueError: If ``output`` does not have shape (..., D).
        """
        entry = get_representation(self.representation, "PoseHead.to_pose()")
        check_tensor(output, "PoseHead.to_pose", "output", (entry.size,))
        return entry.decode(output, self.anchor_half_size_mm)

    def extra_repr(self) -> str:
        """Hyper-parameters shown by ``repr``."""
        return (
            f"representation={self.representation!r}, translation_scale_mm="
            f"{self.translation_scale_mm}, anchor_half_size_mm={self.anchor_half_size_mm}"
        )
