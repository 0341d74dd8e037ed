"""Slice-pose networks: a backbone and a pose head, their configuration, and the matching loss.

A :class:`SlicePoseNet` maps ``(B, 1, H, W)`` slices (in-plane spacing ``spacing_mm``, normally
``input_size`` pixels) to the labels of its representation (:func:`svr.sampling.poses.pose_labels`,
rad and mm); :meth:`SlicePoseNet.predict_poses` turns them into pose vectors in the canonical
frame. :func:`loss_function` gives the loss that trains each representation (the registry
:data:`svr.representation_registry.REPRESENTATIONS` says which).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from svr.errors import ConfigFieldError
from svr.geometry import ANCHOR_HALF_SIZE_MM
from svr.geometry.mirror import ReflectionPlane, check_planes
from svr.losses import DEFAULT_LENGTH_SCALE_MM, validate_metric_weights
from svr.losses.orbit import orbit_min_loss
from svr.models.backbones import BackboneConfig, build_backbone
from svr.models.heads import SE3_ROTATIONS, PoseHead
from svr.representation_registry import REPRESENTATIONS, Representation, get_representation
from svr.validation import (
    check_choice,
    check_instance,
    check_instance_tuple,
    check_int_tuple,
    check_number,
)

MIN_INPUT_SIZE = 32
"""Smallest height and width (pixels) of ``ModelConfig.input_size``."""


@dataclass(frozen=True)
class ModelConfig:
    """Architecture and input conventions of a :class:`SlicePoseNet`.

    Attributes:
        backbone: The backbone's architecture.
        representation: A registered name (:data:`svr.representation_registry.REPRESENTATIONS`).
        input_size: ``(H, W)`` in pixels (each >= 32) of the slices the model is trained on; the
            network itself accepts any size.
        spacing_mm: In-plane pixel spacing (mm) of the slices the model expects, > 0.
        translation_scale_mm: Millimetres per unit of the head's raw translation outputs, > 0.
        anchor_half_size_mm: Half-size (mm) of the anchor-point triangle, > 0.
        se3_rotation: Rotation parameterisation of the ``"se3"`` head's linear layer:
            ``"rotvec"`` or ``"6d"`` (:class:`svr.models.heads.PoseHead`); the head's output is the
            pose vector either way.
        symmetry_planes: Canonical-frame mirror planes of the training anatomy. Non-empty: the
            network was trained up to the mirror twin (:mod:`svr.losses.orbit`), so each
            prediction stands for its whole orbit; the stack consensus picks the member
            (:mod:`svr.reconstruction.cnn_init`) and evaluation reports errors up to the twin.

    Raises:
        ConfigFieldError: Naming the field, for a value of the wrong type or out of range.
    """

    backbone: BackboneConfig = dataclasses.field(default_factory=BackboneConfig)
    representation: Representation = "se3"
    input_size: tuple[int, int] = (128, 128)
    spacing_mm: float = 1.0
    translation_scale_mm: float = DEFAULT_LENGTH_SCALE_MM
    anchor_half_size_mm: float = ANCHOR_HALF_SIZE_MM
    se3_rotation: str = "rotvec"
    symmetry_planes: tuple[ReflectionPlane, ...] = ()

    def __post_init__(self) -> None:
        owner = "ModelConfig"
        check_instance(owner, "backbone", self.backbone, BackboneConfig)
        check_choice(owner, "representation", self.representation, tuple(REPRESENTATIONS))
        size = check_int_tuple(
            owner, "input_size", self.input_size, length=2, minimum=MIN_INPUT_SIZE, allow_list=True
        )
        for name in ("spacing_mm", "translation_scale_mm", "anchor_half_size_mm"):
            check_number(owner, name, getattr(self, name), gt=0)
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.se3_rotation not in SE3_ROTATIONS or (
            self.se3_rotation != "rotvec" and self.representation != "se3"
        ):
            listed = ", ".join(map(repr, SE3_ROTATIONS))
            expected = f"one of {listed} ('6d' with the 'se3' representation only)"
            raise ConfigFieldError(owner, "se3_rotation", expected, self.se3_rotation)
        planes: object = self.symmetry_planes
        if isinstance(planes, tuple | list):  # planes read from JSON are dicts
            planes = [ReflectionPlane.from_dict(p) if isinstance(p, dict) else p for p in planes]
        planes = check_instance_tuple(
            owner, "symmetry_planes", planes, ReflectionPlane, allow_list=True
        )
        object.__setattr__(self, "input_size", size)
        object.__setattr__(self, "symmetry_planes", planes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form of the fields.

        Returns:
            The fields by name, ``backbone`` as a nested dict, ``input_size`` as a list and
            ``symmetry_planes`` as a list of :meth:`ReflectionPlane.to_dict` dicts.
        """
        d = dataclasses.asdict(self)
        d["input_size"] = list(self.input_size)
        d["symmetry_planes"] = [p.to_dict() for p in self.symmetry_planes]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        """Configuration from :meth:`to_dict`'s form; missing keys take their defaults.

        Args:
            d: Field values, ``backbone`` a dict of :class:`BackboneConfig` fields.

        Returns:
            The configuration.

        Raises:
            ValueError: For an unknown key (named, ``backbone.<key>`` inside the backbone) or a bad
                value (the field named).
        """
        values = dict(_check_keys(d, cls, "ModelConfig.from_dict()", ""))
        if "backbone" in values:
            backbone = _check_keys(
                values["backbone"], BackboneConfig, "ModelConfig.from_dict()", "backbone."
            )
            values["backbone"] = BackboneConfig(**backbone)
        return cls(**values)


def _check_keys(d: object, config: type, func: str, prefix: str) -> dict[str, Any]:
    """``d`` itself after checking that it is a dict whose keys are fields of ``config``."""
    if not isinstance(d, dict):
        raise ValueError(f"{func}: '{prefix.rstrip('.') or 'd'}' must be a dict, got {d!r}")
    fields = {f.name for f in dataclasses.fields(config)}
    unknown = [k for k in d if k not in fields]
    if unknown:
        raise ValueError(
            f"{func}: unknown key '{prefix}{unknown[0]}'; "
            f"valid keys are {', '.join(sorted(fields))}"
        )
    return d


class SlicePoseNet(nn.Module):
    """CNN that regresses the pose of a 2D slice in the canonical frame.

    Args:
        config: The architecture and input conventions.

    Attributes:
        config: The configuration it was built from.
        backbone: Module mapping (B, 1, H, W) slices to (B, F) features.
        head: The :class:`svr.models.heads.PoseHead` of ``config.representation``.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        if not isinstance(config, ModelConfig):
            raise ValueError(
                f"SlicePoseNet: 'config' must be a ModelConfig, got {type(config).__name__}"
            )
        self.config = config
        self.backbone = build_backbone(config.backbone)
        self.head = PoseHead(
            self.backbone.out_features,
            config.representation,
            config.translation_scale_mm,
            config.anchor_half_size_mm,
            config.se3_rotation,
        )

    def forward(self, slices: Tensor) -> Tensor:
        """Labels predicted for slices.

        Args:
            slices: (B, 1, H, W) float images, normally ``config.input_size`` pixels at
                ``config.spacing_mm``.

        Returns:
            (B, D) outputs in the label units of the representation (rad, mm), ``D =
            REPRESENTATIONS[config.representation].size``.

        Raises:
            ValueError: If ``slices`` is not a (B, 1, H, W) floating-point tensor.
        """
        if not (
            isinstance(slices, Tensor)
            and slices.is_floating_point()
            and slices.dim() == 4
            and slices.shape[1] == 1
        ):
            raise ValueError(
                "SlicePoseNet.forward(): 'slices' must be a floating-point tensor of shape "
                f"(B, 1, H, W), got {getattr(slices, 'shape', type(slices).__name__)}"
            )
        return self.head(self.backbone(slices))

    def predict_poses(self, slices: Tensor) -> Tensor:
        """Pose vectors predicted for slices, without gradients.

        The module's mode is left as it is: call ``eval()`` first for inference.

        Args:
            slices: (B, 1, H, W) float images.

        Returns:
            (B, 6) pose vectors ``(r, t)`` (rotation vector with angle in ``[0, pi]``, rad;
            translation, mm) mapping the slice plane to the canonical frame.
        """
        with torch.no_grad():
            return self.head.to_pose(self(slices))


def build_model(config: ModelConfig) -> SlicePoseNet:
    """Build the network described by ``config``.

    Args:
        config: The architecture and input conventions.

    Returns:
        The untrained network, which predicts the identity pose for every slice.
    """
    return SlicePoseNet(config)


def loss_function(
    representation: Representation,
    weights: Tensor | None = None,
    planes: Sequence[ReflectionPlane] = (),
    anchor_half_size_mm: float = ANCHOR_HALF_SIZE_MM,
) -> Callable[[Tensor, Tensor], Tensor]:
    """The loss that trains a representation, reduced by the mean over the batch.

    The registry entry's ``loss`` (:data:`svr.representation_registry.REPRESENTATIONS`):
    :func:`svr.losses.se3_geodesic_loss` with metric weights ``weights`` for ``"se3"``, and the
    baselines :func:`svr.losses.posenet_loss` (``"quat_translation"``),
    :func:`svr.losses.anchor_point_loss` (``"anchor_points"``) and
    :func:`svr.losses.rotation_6d_loss` (``"rotation6d_translation"``) with their default
    parameters. With reflection ``planes`` every loss is taken to the nearest member of the
    label's mirror orbit (:mod:`svr.losses.orbit`): the entry's fused ``orbit_loss`` where it
    has one (``"se3"``), else the labels are decoded to poses, their twins encoded back, and the
    smallest per-slice loss kept, so that the SE(3) loss and the baselines meet the symmetry on the
    same terms.

    Args:
        representation: A registered name (:data:`svr.representation_registry.REPRESENTATIONS`).
        weights: Z as a (6,) diagonal or (6, 6) SPD matrix (rad, mm), or ``None`` for the
            default; only for representations whose entry has ``metric_weights`` (``"se3"``).
        planes: Canonical-frame mirror planes of the training anatomy (empty: plain losses).
        anchor_half_size_mm: Half-size of the anchor-point triangle (``"anchor_points"``).

    Returns:
        A function ``loss(outputs, labels)`` of (B, D) network outputs and (B, D) labels of the
        representation, returning a scalar.

    Raises:
        ValueError: For an unknown representation, or weights given for a loss that takes none
            or invalid.
    """
    entry = get_representation(representation, "loss_function()")
    planes = check_planes(planes, "loss_function")
    if weights is not None:
        if not entry.metric_weights:
            takes = [name for name, e in REPRESENTATIONS.items() if e.metric_weights]
            raise ValueError(
                f"loss_function(): 'weights' apply to the {', '.join(map(repr, takes))} loss "
                f"only, not {representation!r}"
            )
        validate_metric_weights(weights, "loss_function")
    base = entry.loss(weights, anchor_half_size_mm)
    if not planes:
        return base
    if entry.orbit_loss is not None:
        return entry.orbit_loss(weights, planes)
    per_slice = functools.partial(base, reduction="none")

    def orbit_loss(outputs: Tensor, labels: Tensor) -> Tensor:
        poses = entry.decode(labels.detach().double(), anchor_half_size_mm)
        return orbit_min_loss(
            per_slice,
            outputs,
            poses,
            planes,
            encode=lambda p: entry.encode(p, anchor_half_size_mm).to(outputs.dtype),
        )

    return orbit_loss


def checkpoint_model_config(config: ModelConfig) -> dict:
    """The part of a checkpoint's JSON config that a predictor needs.

    ``model`` (:meth:`ModelConfig.to_dict`), and for readers of the JSON its ``representation``,
    ``input_size`` (pixels) and ``spacing_mm``.
    """
    return {
        "model": config.to_dict(),
        "representation": config.representation,
        "input_size": list(config.input_size),
        "spacing_mm": config.spacing_mm,
    }
