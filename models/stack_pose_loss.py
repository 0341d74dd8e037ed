"""The stack-pose network's training loss (:func:`svr.models.stack_pose_train.train_stack_pose`).

The pose loss on the blocks whose start frame is within reach (the SE(3) geodesic loss on the
refined stack pose, or a baseline representation's own loss), plus the cross-entropy of the
frame's score and, for the ``"coords"`` head, a smooth-L1 loss on the predicted coordinates.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import torch
from torch import Tensor
from torch.nn import functional

from svr.geometry import ANCHOR_HALF_SIZE_MM, se3_compose, se3_to_vector
from svr.losses.se3 import se3_geodesic_loss
from svr.representation_registry import Representation, get_representation

if TYPE_CHECKING:
    from svr.models.stack_pose import StackPoseOutput

__all__ = ["LossWeights", "stack_pose_loss"]


class LossWeights(Protocol):
    """The weights of the loss's parts beside the pose loss (a ``StackPoseTrainingConfig``)."""

    @property
    def score_weight(self) -> float:
        """Weight of the score's cross-entropy."""
        ...

    @property
    def coords_weight(self) -> float:
        """Weight of the coordinate loss (``"coords"`` head)."""
        ...


def stack_pose_loss(
    output: StackPoseOutput,
    starts: Tensor,
    targets: Tensor,
    labels: Tensor,
    config: LossWeights,
    grid_points: Tensor | None = None,
    representation: Representation = "se3",
) -> tuple[Tensor, dict[str, float]]:
    """The pose loss on the blocks within reach, plus the score's and coordinates' losses.

    The pose loss is the SE(3) geodesic loss on the refined stack poses (``"se3"``), or a
    baseline's own loss (:data:`svr.representation_registry.REPRESENTATIONS`) between the head's raw
    outputs and the true residual's labels.

    Args:
        output: The network's prediction for B blocks.
        starts: (B, 4, 4) start stack poses.
        targets: (B, 4, 4) true stack poses.
        labels: (B,) 1 where the start is within reach (only these get the pose loss).
        config: The weights (:class:`~svr.models.stack_pose_train.StackPoseTrainingConfig`).
        grid_points: (N, 3) the coordinate cells in the block frame (``"coords"`` head).
        representation: The regress head's representation (the network config's).

    Returns:
        The scalar loss and its parts (floats, for the log).

    Raises:
        ValueError: If a baseline representation is asked for without the head's raw outputs.
    """
    # The true residual (block frame -> canonical): target o start^-1.
    true_residual = se3_compose(targets.double(), torch.linalg.inv(starts.double()))
    if representation == "se3":
        pred = se3_to_vector(se3_compose(output.residual.double(), starts))
        per = se3_geodesic_loss(pred, se3_to_vector(targets.double()), reduction="none")
    else:
        if output.raw is None:
            raise ValueError(
                f"stack_pose_loss(): the {representation!r} loss needs the regress head's outputs"
            )
        entry = get_representation(representation, "stack_pose_loss()")
        truth = entry.encode(se3_to_vector(true_residual), ANCHOR_HALF_SIZE_MM)
        per = entry.loss(None, ANCHOR_HALF_SIZE_MM)(output.raw.double(), truth, reduction="none")
    within = labels > 0.5
    pose = (per * within).sum() / within.sum().clamp(min=1)
    bce = functional.binary_cross_entropy_with_logits(output.score, labels)
    total = pose + config.score_weight * bce.double()
    parts = {"pose": float(pose.detach()), "score": float(bce.detach())}
    if output.coords is not None and grid_points is not None:
        truth = (
            grid_points.double() @ true_residual[:, :3, :3].transpose(1, 2)
            + true_residual[:, None, :3, 3]
        )
        err = functional.smooth_l1_loss(
            output.coords[..., :3].double() / 10.0, truth / 10.0, reduction="none"
        )
        aux = (err.mean(-1).mean(-1) * within).sum() / within.sum().clamp(min=1)
        total = total + config.coords_weight * aux
        parts["coords"] = float(aux.detach())
    return total, parts
