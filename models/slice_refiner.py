"""The slice refiner: a slice beside a reference volume on its current plane -> the residual pose.

Every slice of a reconstruction starts near its place (its stack's or packet's learned pose) but
not on it: within a stack the fetus moved. :class:`SliceRefinerNet` sees the slice (channel 0)
beside a reference volume resampled on the slice's current plane and on planes parallel to it
(``plane_offsets_mm`` along the slice normal), and predicts the rigid residual ``D`` in the
slice's own frame that takes the current pose to the true one, ``T_true = T_current o D``
(rotation about the slice's centre, translation in slice-plane mm: ``u``, ``v`` and the normal
``w``). Applied and iterated, it is a learned local registration whose reach is trained, not set
by an optimiser's basin: it is trained with the SE(3) geodesic loss on ``D`` (or a baseline's
loss, for the comparison of losses) on slices cut at known poses from atlas brains, the reference
the same brain blurred and its intensities remapped (``benchmarks/experiments/
slice_refiner_train.py``; the shipped stages' recipe is on their model card). The reconstruction
uses the shipped stages against an atlas
(:mod:`svr.reconstruction.initialisation.slice_refinement`).

Two heads, both trained with the SE(3) geodesic loss on ``D``: ``"regress"`` maps the backbone's
features to ``D`` directly (a pose representation: ``"se3"``, or a baseline's for the comparison
of losses); ``"coords"`` predicts, on a coarse grid of cells over the slice, where each cell's
content truly lies in the slice's current frame (a 3D point, and a confidence), and ``D`` is the
weighted rigid fit of the cells onto those points (:func:`svr.geometry.weighted_rigid_fit`): the
network solves a local matching problem at every cell, which convolutions are good at, and the fit
turns the local answers into one rigid pose (the geometry is not learned).

With ``context="sequence"`` the slices of one interleaved packet are seen together: each slice's
features, with its position in the acquisition and its current pose relative to the packet's
mean, go through a small transformer encoder, so that a slice with little brain borrows from its
temporal neighbours (the motion is one trajectory in time). ``context="none"`` sees each slice
alone (the local, iterated structure).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import torch
from torch import Tensor, nn

from svr.errors import ConfigFieldError
from svr.geometry import se3_to_vector, weighted_rigid_fit
from svr.models.backbones import BackboneConfig, build_backbone
from svr.models.checkpoint import CheckpointError, load_checkpoint, resolve_model_path
from svr.models.heads import PoseHead
from svr.representation_registry import REPRESENTATIONS, Representation
from svr.validation import (
    check_choice,
    check_instance,
    check_int,
    check_int_tuple,
    check_number,
    check_number_tuple,
)

__all__ = [
    "SLICE_REFINER",
    "Context",
    "Head",
    "SliceRefinerConfig",
    "SliceRefinerNet",
    "load_slice_refiner",
    "shipped_slice_refiners",
]

SLICE_REFINER = "slice-refiner"
"""The checkpoint ``architecture`` of a slice refiner."""

Context = Literal["none", "sequence"]
Head = Literal["regress", "coords"]


@dataclass(frozen=True)
class SliceRefinerConfig:
    """The slice refiner's inputs and network.

    Attributes:
        size: (H, W) pixels of the slice and of each reference plane.
        spacing_mm: Their pixel spacing (mm).
        plane_offsets_mm: Offsets (mm) along the slice normal of the reference planes, beside
            the slice's own plane (0 should be among them).
        backbone: The 2D backbone (its ``in_channels`` is set to ``1 + len(plane_offsets_mm)``).
        head: ``"regress"`` or ``"coords"`` (module docstring).
        representation: What the ``"regress"`` head outputs, a registered name: ``"se3"``
            (trained with the SE(3) geodesic loss) or a baseline's; ``"se3"`` with ``"coords"``.
        translation_scale_mm: Millimetres per unit of the head's raw translation outputs.
        context: ``"none"`` (each slice alone) or ``"sequence"`` (a packet's slices together).
        context_layers: Transformer encoder layers of the ``"sequence"`` context, >= 1.
        context_heads: Their attention heads (dividing ``hidden``), >= 1.
        hidden: Features of the hidden layer on the backbone's flattened feature map (which keeps
            where in the slice each feature is: a rotation moves features across the slice, and
            pooling them away would hide it), >= 8.

    Raises:
        ConfigFieldError: On construction, naming the field.
    """

    size: tuple[int, int] = (64, 64)
    spacing_mm: float = 2.0
    plane_offsets_mm: tuple[float, ...] = (-12.0, -6.0, 0.0, 6.0, 12.0)
    backbone: BackboneConfig = field(default_factory=lambda: BackboneConfig(width=16, depth=4))
    head: Head = "regress"
    representation: Representation = "se3"
    translation_scale_mm: float = 10.0
    context: Context = "none"
    context_layers: int = 2
    context_heads: int = 4
    hidden: int = 256

    def __post_init__(self) -> None:
        owner = "SliceRefinerConfig"
        size = check_int_tuple(owner, "size", self.size, length=2, minimum=16, allow_list=True)
        object.__setattr__(self, "size", size)
        check_number(owner, "spacing_mm", self.spacing_mm, gt=0)
        offsets = check_number_tuple(
            owner, "plane_offsets_mm", self.plane_offsets_mm, allow_empty=False, allow_list=True
        )
        object.__setattr__(self, "plane_offsets_mm", offsets)
        check_instance(owner, "backbone", self.backbone, BackboneConfig)
        check_choice(owner, "head", self.head, get_args(Head))
        check_choice(owner, "representation", self.representation, tuple(REPRESENTATIONS))
        if self.head == "coords" and self.representation != "se3":
            raise ConfigFieldError(
                owner, "representation", "se3 with the coords head", self.representation
            )
        if self.head == "coords" and self.context != "none":
            raise ConfigFieldError(owner, "context", "none with the coords head", self.context)
        check_number(owner, "translation_scale_mm", self.translation_scale_mm, gt=0)
        check_choice(owner, "context", self.context, get_args(Context))
        check_int(owner, "context_layers", self.context_layers, minimum=1)
        check_int(owner, "context_heads", self.context_heads, minimum=1)
        check_int(owner, "hidden", self.hidden, minimum=8)
        channels = 1 + len(offsets)
        if self.backbone.in_channels != channels:
            object.__setattr__(
                self, "backbone", dataclasses.replace(self.backbone, in_channels=channels)
            )

    @property
    def channels(self) -> int:
        """Input channels: the slice and one per reference plane."""
        return 1 + len(self.plane_offsets_mm)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> SliceRefinerConfig:
        """The configuration of :meth:`to_dict`'s form."""
        values = dict(values)
        if isinstance(values.get("backbone"), dict):
            values["backbone"] = BackboneConfig(**values["backbone"])
        return cls(**values)


class SliceRefinerNet(nn.Module):
    """(B, C, H, W) slice and reference planes -> (B, D) residual labels; see the module docstring.

    Args:
        config: The inputs and network.

    Attributes:
        config: The configuration it was built from.
    """

    def __init__(self, config: SliceRefinerConfig) -> None:
        super().__init__()
        self.config = config
        self.backbone = build_backbone(config.backbone)
        if config.head == "coords":
            self._build_coords(config)
            return
        cells = 1
        for size in config.size:
            for _ in range(config.backbone.depth + 1):  # the stem and every stage halve it
                size = (size + 1) // 2
            cells *= size
        features = config.hidden
        self.hidden = nn.Sequential(
            nn.Flatten(),
            nn.Linear(self.backbone.out_features * cells, features),
            nn.ReLU(inplace=True),
        )
        self.context: nn.Module | None = None
        if config.context == "sequence":
            layer = nn.TransformerEncoderLayer(
                features, config.context_heads, 2 * features, dropout=0.0, batch_first=True
            )
            self.context = nn.TransformerEncoder(layer, config.context_layers)
            # position in time (sin, cos at two scales) and the current pose (6) -> features
            self.position = nn.Linear(4 + 6, features)
        self.head = PoseHead(features, config.representation, config.translation_scale_mm)

    cells: Tensor
    """(M, 3) the ``"coords"`` head's cell centres in the slice's frame (mm)."""

    def _build_coords(self, config: SliceRefinerConfig) -> None:
        """The ``"coords"`` head: a 1x1 convolution to (dx, dy, dz, confidence) per cell."""
        width = self.backbone.out_features
        self.coords = nn.Conv2d(width, 4, 1)
        nn.init.zeros_(self.coords.weight)
        if self.coords.bias is not None:
            nn.init.zeros_(self.coords.bias)
        h, w = config.size
        for _ in range(config.backbone.depth + 1):
            h, w = (h + 1) // 2, (w + 1) // 2
        step = config.spacing_mm * config.size[0] / h
        u = (torch.arange(h, dtype=torch.float32) - (h - 1) / 2) * step
        v = (
            (torch.arange(w, dtype=torch.float32) - (w - 1) / 2)
            * config.spacing_mm
            * config.size[1]
            / w
        )
        grid_u, grid_v = torch.meshgrid(u, v, indexing="ij")
        cells = torch.stack([grid_u, grid_v, torch.zeros_like(grid_u)], dim=-1).reshape(-1, 3)
        self.register_buffer("cells", cells, persistent=False)
        self.head = None  # type: ignore[assignment]
        self.context = None

    def points(self, inputs: Tensor) -> Tensor:
        """(B, M, 4) the ``"coords"`` head's points (mm, slice frame) and confidence logits."""
        backbone = self.backbone
        raw = self.coords(backbone.stages(backbone.stem(inputs))).flatten(2).transpose(1, 2)
        scale = self.config.translation_scale_mm
        return torch.cat([self.cells.to(raw) + raw[..., :3] * scale, raw[..., 3:]], dim=-1)

    def forward(
        self,
        inputs: Tensor,
        times: Tensor | None = None,
        poses: Tensor | None = None,
        padding: Tensor | None = None,
    ) -> Tensor:
        """Residual labels of each slice (label units of the representation: rad, mm).

        Args:
            inputs: (B, C, H, W) for ``context="none"``; (B, L, C, H, W) packets of L slices for
                ``"sequence"``.
            times: (B, L) each slice's time in its packet (slice steps), ``"sequence"`` only.
            poses: (B, L, 6) each slice's current pose relative to its packet's mean (rad, mm),
                ``"sequence"`` only.
            padding: (B, L) bool, True where a packet is padded (no slice), ``"sequence"`` only.

        Returns:
            (B, D) or (B, L, D) outputs of the head.
        """
        if self.config.head == "coords":
            points = self.points(inputs)
            weights = torch.sigmoid(points[..., 3]) + 1e-4
            source = self.cells.to(points).expand_as(points[..., :3])
            fitted = weighted_rigid_fit(source, points[..., :3], weights)
            return se3_to_vector(fitted)
        if self.context is None:
            return self.head(self._features(inputs))
        b, length = inputs.shape[:2]
        features = self._features(inputs.flatten(0, 1)).reshape(b, length, -1)
        if times is None or poses is None:
            raise ValueError("SliceRefinerNet: the 'sequence' context needs 'times' and 'poses'")
        t = times.to(features)[..., None]
        position = torch.cat(
            [torch.sin(t / 4), torch.cos(t / 4), torch.sin(t / 16), torch.cos(t / 16)], dim=-1
        )
        scaled = poses.to(features) / torch.tensor(
            [1.0, 1.0, 1.0, 10.0, 10.0, 10.0], dtype=features.dtype, device=features.device
        )
        features = features + self.position(torch.cat([position, scaled], dim=-1))
        features = self.context(features, src_key_padding_mask=padding)
        return self.head(features)

    def _features(self, inputs: Tensor) -> Tensor:
        """(B, hidden) features of (B, C, H, W) inputs: the backbone's map, flattened."""
        backbone = self.backbone
        return self.hidden(backbone.stages(backbone.stem(inputs)))

    def to_pose(self, outputs: Tensor) -> Tensor:
        """(..., 6) residual pose vectors of the head's outputs."""
        if self.config.head == "coords":
            return outputs  # already pose vectors (rad, mm)
        return self.head.to_pose(outputs)


def load_slice_refiner(
    path: str | os.PathLike[str], device: str | torch.device = "cpu"
) -> SliceRefinerNet:
    """A slice refiner from a checkpoint or model folder (or a run folder: its newest).

    Args:
        path: A folder written by :func:`svr.models.checkpoint.save_checkpoint` whose config has
            ``"architecture": "slice-refiner"``, or a training run's folder of such checkpoints.
        device: Where to put the network.

    Returns:
        The network in eval mode.

    Raises:
        CheckpointError: If the folder is not a slice refiner (nothing in it is executed).
    """
    folder = resolve_model_path(path)
    checkpoint = load_checkpoint(folder, map_location=device)
    if checkpoint.config.get("architecture") != SLICE_REFINER:
        raise CheckpointError(
            folder,
            f"not a slice refiner (architecture {checkpoint.config.get('architecture')!r})",
        )
    try:
        config = SliceRefinerConfig.from_dict(checkpoint.config["model"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(folder, f"bad 'model' section in config.json: {exc}") from exc
    net = SliceRefinerNet(config)
    net.load_state_dict(checkpoint.state_dict)
    return net.to(device).eval()


@functools.lru_cache(maxsize=4)
def shipped_slice_refiners(device: str = "cpu") -> tuple[SliceRefinerNet, ...]:
    """The shipped refiner's stages, in the order applied (loaded once per device).

    Args:
        device: Where to put them (``str(torch.device)``).

    Returns:
        The stages of :data:`svr.models.pretrained.SLICE_REFINER_STAGES`, in eval mode.

    Raises:
        CheckpointError: If a stage's folder is missing or not a slice refiner.
    """
    from svr.models.pretrained import slice_refiner_paths

    return tuple(load_slice_refiner(path, device) for path in slice_refiner_paths())
