"""The stack-pose network: a block of a stack in a candidate canonical frame -> the residual.

:class:`StackPoseNet` sees a stack resampled in a candidate canonical frame
(:func:`svr.sampling.blocks.block_inputs`) and predicts the residual rigid transform to the true
canonical frame (within about 40 degrees and a few centimetres) and a score of how likely the
candidate is right. Inference (hypotheses, refinement, choice) is
:mod:`svr.reconstruction.initialisation.stack_pose`; training is
:mod:`svr.models.stack_pose_train`.

Two heads share the encoder, both trained with the SE(3) geodesic loss on the final stack pose:

* ``"regress"``: a rotation vector and a translation, regressed from the flattened features;
  for the baselines of the loss comparison, the residual in another registered representation
  (``representation``: PoseNet's quaternion, Anchor Points, 6D), trained with that
  representation's loss on the residual;
* ``"coords"``: per-cell canonical coordinates with confidences on a coarse grid, turned into
  the residual by a differentiable weighted rigid fit (:func:`svr.geometry.weighted_rigid_fit`),
  with an auxiliary loss on the coordinates.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, NamedTuple, get_args

import torch
from torch import Tensor, nn

from svr.errors import ConfigFieldError
from svr.geometry import vector_to_se3, weighted_rigid_fit
from svr.models.checkpoint import (
    CHECKPOINT_CONFIG,
    CheckpointError,
    latest_checkpoint,
    load_checkpoint,
)
from svr.models.heads import PoseHead
from svr.models.pretrained import stack_pose_model_path
from svr.representation_registry import REPRESENTATIONS, Representation
from svr.sampling.blocks import BlockGrid
from svr.validation import check_choice, check_instance, check_int, check_number

__all__ = [
    "STACK_POSE_MODEL",
    "StackPoseConfig",
    "StackPoseNet",
    "StackPoseOutput",
    "load_stack_pose_model",
]

Head = Literal["regress", "coords"]

STACK_POSE_MODEL = "stack-pose"
"""The name that stands for the stack-pose model shipped in the package."""


@dataclass(frozen=True)
class StackPoseConfig:
    """The stack-pose network.

    Attributes:
        head: ``"regress"`` or ``"coords"`` (see the module docstring).
        width: Channels of the first stage (doubled at each of the three stages), >= 4.
        grid_size: Block voxels per side, a multiple of 8, >= 16.
        grid_spacing_mm: Block voxel spacing (mm).
        in_plane_mm: Stacks are averaged in-plane to about this spacing first (mm).
        translation_scale_mm: The network's translation outputs are in units of this (mm).
        representation: What the ``"regress"`` head outputs, a registered name
            (:data:`svr.representation_registry.REPRESENTATIONS`): ``"se3"`` (the rotation vector
            and translation, trained with the SE(3) geodesic loss on the final pose: the shipped
            model) or a baseline trained with its own loss on the residual.
        hidden_norm: Batch normalisation before the ReLU of the hidden layer that the heads
            share. Without it (the models trained before it, which load so) the hidden units
            can all stop firing in the first steps, a run that never learns (measured), and most
            of them did so even in runs that learned.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range (``representation`` other than ``"se3"`` with the ``"coords"`` head).
    """

    head: Head = "regress"
    width: int = 16
    grid_size: int = 32
    grid_spacing_mm: float = 4.0
    in_plane_mm: float = 2.0
    translation_scale_mm: float = 10.0
    representation: Representation = "se3"
    hidden_norm: bool = True

    def __post_init__(self) -> None:
        owner = "StackPoseConfig"
        check_instance(owner, "hidden_norm", self.hidden_norm, bool)
        check_choice(owner, "head", self.head, get_args(Head))
        check_choice(owner, "representation", self.representation, tuple(REPRESENTATIONS))
        check_int(owner, "width", self.width, minimum=4)
        check_int(owner, "grid_size", self.grid_size, minimum=16)
        for name in ("grid_spacing_mm", "in_plane_mm", "translation_scale_mm"):
            check_number(owner, name, getattr(self, name), gt=0)
        if self.grid_size % 8:
            raise ConfigFieldError(owner, "grid_size", "a multiple of 8", self.grid_size)
        if self.head == "coords" and self.representation != "se3":
            raise ConfigFieldError(
                owner, "representation", "se3 with the coords head", self.representation
            )

    @property
    def grid(self) -> BlockGrid:
        """The block grid."""
        return BlockGrid(self.grid_size, self.grid_spacing_mm, self.in_plane_mm)

    def to_dict(self) -> dict:
        """JSON-ready fields."""
        return asdict(self)


def _stage(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv3d(c_in, c_out, 3, stride=2, padding=1, bias=False),
        nn.BatchNorm3d(c_out),
        nn.ReLU(inplace=True),
        nn.Conv3d(c_out, c_out, 3, padding=1, bias=False),
        nn.BatchNorm3d(c_out),
        nn.ReLU(inplace=True),
    )


class StackPoseOutput(NamedTuple):
    """What :class:`StackPoseNet` predicts for a batch of B blocks.

    Attributes:
        residual: (B, 4, 4) residual transforms (the block's canonical frame -> the true
            canonical frame, mm).
        score: (B,) logits that the frame is within the refinement's reach.
        coords: (B, N, 4) per-cell predicted canonical coordinates (mm) and confidence logits for
            the ``"coords"`` head, else ``None``.
        raw: (B, D) the ``"regress"`` head's outputs in its representation's label units (the
            residual's labels, :class:`svr.models.heads.PoseHead`), else ``None``.
    """

    residual: Tensor
    score: Tensor
    coords: Tensor | None
    raw: Tensor | None


class StackPoseNet(nn.Module):
    """Block -> residual transform to the canonical frame, and a score for the frame.

    Input ``(B, 3, S, S, S)`` blocks (:func:`svr.sampling.blocks.block_inputs`); three stages of two
    3D convolutions (the first with stride 2) to ``(4w, S/8, S/8, S/8)`` features.
    """

    cells: Tensor
    """(N, 3) the coordinate head's cell centres in the block frame (mm)."""

    def __init__(self, config: StackPoseConfig) -> None:
        super().__init__()
        self.config = config
        w, s = config.width, config.grid_size
        self.stages = nn.ModuleList([_stage(3, w), _stage(w, 2 * w), _stage(2 * w, 4 * w)])
        flat = 4 * w * (s // 8) ** 3
        norm = [nn.BatchNorm1d(8 * w)] if config.hidden_norm else []
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(flat, 8 * w), *norm, nn.ReLU(inplace=True))
        self.score = nn.Linear(8 * w, 1)
        if config.head == "regress":
            self.pose = PoseHead(8 * w, config.representation, config.translation_scale_mm)
            self._register_load_state_dict_pre_hook(_rename_legacy_pose_keys)
        else:
            self.decode = nn.Upsample(scale_factor=2, mode="trilinear", align_corners=False)
            last = nn.Conv3d(2 * w, 4, 1)
            assert last.bias is not None
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
            self.coords = nn.Sequential(
                nn.Conv3d(6 * w, 2 * w, 3, padding=1), nn.ReLU(inplace=True), last
            )
            g = config.grid
            cells = BlockGrid(s // 4, g.spacing_mm * 4, g.in_plane_mm).points(torch.float32)
            self.register_buffer("cells", cells.reshape(-1, 3), persistent=False)

    def forward(self, blocks: Tensor) -> StackPoseOutput:
        """Predict.

        Args:
            blocks: (B, 3, S, S, S) float blocks.

        Returns:
            The residuals, scores and the head's own outputs.
        """
        features = []
        x = blocks
        for stage in self.stages:
            x = stage(x)
            features.append(x)
        hidden = self.fc(x)
        score = self.score(hidden)[:, 0]
        scale = self.config.translation_scale_mm
        if self.config.head == "regress":
            raw = self.pose(hidden)
            return StackPoseOutput(vector_to_se3(self.pose.to_pose(raw)), score, None, raw)
        up = torch.cat([self.decode(features[2]), features[1]], dim=1)
        raw = self.coords(up).flatten(2).transpose(1, 2)  # (B, N, 4)
        cells = self.cells.to(raw)
        coords = torch.cat([cells + raw[..., :3] * scale, raw[..., 3:]], dim=-1)
        weights = torch.sigmoid(raw[..., 3]) + 1e-4
        residual = weighted_rigid_fit(cells.expand_as(coords[..., :3]), coords[..., :3], weights)
        return StackPoseOutput(residual, score, coords, None)


def _rename_legacy_pose_keys(state_dict: dict, prefix: str, *args: object) -> None:
    """Load checkpoints written before the head was a :class:`PoseHead` (``pose.weight``)."""
    for name in ("weight", "bias"):
        old = f"{prefix}pose.{name}"
        if old in state_dict:
            state_dict[f"{prefix}pose.linear.{name}"] = state_dict.pop(old)


def load_stack_pose_model(
    path: str | os.PathLike[str], device: str | torch.device = "cpu"
) -> StackPoseNet:
    """Load a stack-pose network from a checkpoint or model folder (or a run folder: its newest).

    Args:
        path: A folder written by :func:`svr.models.checkpoint.save_checkpoint` whose config has
            ``"architecture": "stack_pose"``, a training run's folder of such checkpoints, or
            :data:`STACK_POSE_MODEL` for the shipped model.
        device: Where to put the network.

    Returns:
        The network in eval mode.

    Raises:
        CheckpointError: If the folder is not a stack-pose checkpoint (nothing in it is executed).
    """
    folder = stack_pose_model_path() if str(path) == STACK_POSE_MODEL else Path(path)
    if not (folder / CHECKPOINT_CONFIG).exists():
        newest = latest_checkpoint(folder)
        if newest is not None:
            folder = newest
    checkpoint = load_checkpoint(folder, map_location=device)
    if checkpoint.config.get("architecture") != "stack_pose":
        raise CheckpointError(
            folder,
            f"not a stack-pose model (architecture {checkpoint.config.get('architecture')!r})",
        )
    try:
        # Models from before the field have no normalisation in the hidden layer.
        config = StackPoseConfig(**{"hidden_norm": False, **checkpoint.config["model"]})
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(folder, f"bad 'model' section in config.json: {exc}") from exc
    net = StackPoseNet(config)
    net.load_state_dict(checkpoint.state_dict)
    return net.to(device).eval()
