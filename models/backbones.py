"""CNN backbones that map a 2D slice to a feature vector: ResNet-style and Inception-style.

Both take ``(B, 1, H, W)`` float slices and return ``(B, F)`` features, ``F = out_features``; any
input size works (global average pooling), 32 x 32 or more is meaningful. Layout for
``width = w`` and ``depth = d``:

* a stem: 7 x 7 convolution with stride 2 to ``w`` channels, BatchNorm, ReLU;
* ``d`` stages, each halving the resolution and ending with ``w * 2**i`` channels (stage ``i``, from
  0), so that ``F = w * 2**(d - 1)``; a 128 x 128 slice ends at ``128 / 2**(d + 1)`` pixels;

  - ResNet: ``blocks`` basic residual blocks (two 3 x 3 convolutions), the first with stride 2;
  - Inception (GoogLeNet-like, the paper's choice): a 3 x 3 max-pool with stride 2, then
    ``blocks`` inception modules with 1 x 1, 3 x 3, 5 x 5 (as two 3 x 3) and pool-projection
    branches concatenated;

* global average pooling and dropout (probability ``dropout``) on the features.

Normalisation is BatchNorm2d after every convolution: use ``model.eval()`` for prediction and
training batches of more than one slice. Convolutions have Kaiming-normal weights (fan-out, ReLU);
the last BatchNorm of each residual branch starts with zero scale, so that every residual block
starts as the identity.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, cast, get_args

import torch
from torch import Tensor, nn

from svr.validation import check_choice, check_int, check_number

BackboneName = Literal["resnet", "inception"]
"""Names of the backbone families."""

BACKBONE_NAMES: tuple[str, ...] = get_args(BackboneName)
"""The valid values of :data:`BackboneName`, in order."""

MIN_WIDTH = 8
"""Smallest ``width``: an inception module splits its channels eight ways."""


@dataclass(frozen=True)
class BackboneConfig:
    """Architecture of a backbone.

    Attributes:
        name: ``"resnet"`` or ``"inception"``.
        width: Channels of the first stage, >= 8; each later stage doubles them.
        depth: Number of downsampling stages, >= 1.
        blocks: Residual blocks (ResNet) or inception modules (Inception) per stage, >= 1.
        dropout: Dropout probability on the pooled features, in ``[0, 1)``.
        in_channels: Image channels of the input, >= 1 (1: a slice alone).

    Raises:
        ConfigFieldError: Naming the field, for a value of the wrong type or out of range.
    """

    name: BackboneName = "resnet"
    width: int = 32
    depth: int = 4
    blocks: int = 2
    dropout: float = 0.0
    in_channels: int = 1

    def __post_init__(self) -> None:
        owner = "BackboneConfig"
        check_int(owner, "in_channels", self.in_channels, minimum=1)
        check_choice(owner, "name", self.name, BACKBONE_NAMES)
        check_int(owner, "width", self.width, minimum=MIN_WIDTH)
        check_int(owner, "depth", self.depth, minimum=1)
        check_int(owner, "blocks", self.blocks, minimum=1)
        check_number(owner, "dropout", self.dropout, ge=0, lt=1)
        object.__setattr__(self, "dropout", float(self.dropout))

    @property
    def out_features(self) -> int:
        """Number of output features ``width * 2**(depth - 1)``."""
        return self.width * 2 ** (self.depth - 1)


def _conv_bn_relu(
    in_channels: int, out_channels: int, kernel_size: int, stride: int = 1
) -> nn.Sequential:
    """Convolution (no bias, "same" padding for odd kernels), BatchNorm and ReLU."""
    return nn.Sequential(
        nn.Conv2d(
            in_channels, out_channels, kernel_size, stride, padding=kernel_size // 2, bias=False
        ),
        nn.BatchNorm2d(out_channels),
        nn.ReLU(inplace=True),
    )


class BasicBlock(nn.Module):
    """Residual block ``relu(x' + bn(conv(relu(bn(conv(x))))))`` with two 3 x 3 convolutions.

    ``x'`` is ``x``, or a strided 1 x 1 convolution and BatchNorm of it when the stride or the
    number of channels changes.

    Args:
        in_channels: Input channels.
        out_channels: Output channels.
        stride: Stride of the first convolution (and of the shortcut).
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int) -> None:
        super().__init__()
        self.branch = nn.Sequential(
            _conv_bn_relu(in_channels, out_channels, 3, stride),
            nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
        )
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride, bias=False),
                nn.BatchNorm2d(out_channels),
            )
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        """(B, C_in, H, W) -> (B, C_out, ceil(H / stride), ceil(W / stride))."""
        return self.relu(self.branch(x) + self.shortcut(x))


class InceptionModule(nn.Module):
    """GoogLeNet inception module: four branches concatenated along the channels.

    With ``c = out_channels``, the branches give ``c/4`` (1 x 1), ``c/2`` (1 x 1 reduction to
    ``c/4``, then 3 x 3), ``c/8`` (1 x 1 reduction to ``max(c/16, 1)``, then two 3 x 3 in place of
    a 5 x 5) and the rest (3 x 3 max-pool, then 1 x 1 projection) channels, as in GoogLeNet's first
    module.

    Args:
        in_channels: Input channels.
        out_channels: Output channels, >= 8.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        c1, c3, c5 = out_channels // 4, out_channels // 2, out_channels // 8
        cp = out_channels - c1 - c3 - c5
        r3, r5 = out_channels // 4, max(out_channels // 16, 1)
        self.branch1 = _conv_bn_relu(in_channels, c1, 1)
        self.branch3 = nn.Sequential(_conv_bn_relu(in_channels, r3, 1), _conv_bn_relu(r3, c3, 3))
        self.branch5 = nn.Sequential(
            _conv_bn_relu(in_channels, r5, 1), _conv_bn_relu(r5, c5, 3), _conv_bn_relu(c5, c5, 3)
        )
        self.branch_pool = nn.Sequential(
            nn.MaxPool2d(3, stride=1, padding=1), _conv_bn_relu(in_channels, cp, 1)
        )

    def forward(self, x: Tensor) -> Tensor:
        """(B, C_in, H, W) -> (B, C_out, H, W)."""
        branches = (self.branch1, self.branch3, self.branch5, self.branch_pool)
        return torch.cat([branch(x) for branch in branches], dim=1)


class Backbone(nn.Module):
    """Stem, downsampling stages, global average pooling and dropout (see the module docstring).

    Args:
        config: The architecture.

    Attributes:
        config: The architecture it was built from.
        out_features: Number of output features ``F``.
    """

    def __init__(self, config: BackboneConfig) -> None:
        super().__init__()
        self.config = config
        self.out_features = config.out_features
        self.stem = _conv_bn_relu(config.in_channels, config.width, 7, stride=2)
        stages = []
        in_channels = config.width
        for i in range(config.depth):
            out_channels = config.width * 2**i
            if config.name == "resnet":
                layers: list[nn.Module] = [BasicBlock(in_channels, out_channels, stride=2)]
                layers += [
                    BasicBlock(out_channels, out_channels, stride=1)
                    for _ in range(config.blocks - 1)
                ]
            else:
                layers = [nn.MaxPool2d(3, stride=2, padding=1)]
                layers += [
                    InceptionModule(in_channels if j == 0 else out_channels, out_channels)
                    for j in range(config.blocks)
                ]
            stages.append(nn.Sequential(*layers))
            in_channels = out_channels
        self.stages = nn.Sequential(*stages)
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.dropout = nn.Dropout(config.dropout)
        self._initialise()

    def _initialise(self) -> None:
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.ones_(module.weight)
                nn.init.zeros_(module.bias)
        for module in self.modules():
            if isinstance(module, BasicBlock):
                # the branch's last layer is its BatchNorm2d
                nn.init.zeros_(cast("nn.BatchNorm2d", module.branch[-1]).weight)

    def forward(self, slices: Tensor) -> Tensor:
        """Features of slices.

        Args:
            slices: (B, C, H, W) float images, ``C = config.in_channels``.

        Returns:
            (B, out_features) features.
        """
        features = self.pool(self.stages(self.stem(slices))).flatten(1)
        return self.dropout(features)


def build_backbone(config: BackboneConfig) -> Backbone:
    """Build the backbone described by ``config``.

    Args:
        config: The architecture.

    Returns:
        A module mapping (B, ``in_channels``, H, W) images to (B, ``out_features``) features.
    """
    return Backbone(config)
