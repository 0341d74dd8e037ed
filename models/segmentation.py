"""A small 2D U-Net for fetal brain masks on thick-slice stacks (issue 14, first piece).

:class:`BrainUNet` maps (B, C, H, W) slices (intensities normalised per stack; C = 1, or a slice
with its neighbours for 2.5D) to (B, 1, H, W) brain logits; H and W must be multiples of
``2 ** depth``. It is small enough to ship inside the package (:func:`parameter_bytes`) and
fast enough on a CPU for clinical stacks (320 x 320 x 22, measured). :mod:`svr.masking` runs two
of them (localise, then segment) behind ``svr segment-stack``; :mod:`svr.masking.train` trains
them on simulated scenes (``svr train-brain-mask``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from svr.validation import check_int

__all__ = ["BrainUNet", "SegmentationConfig", "parameter_bytes"]


@dataclass(frozen=True)
class SegmentationConfig:
    """The U-Net's shape.

    Attributes:
        width: Channels of the first level, >= 1 (doubled at each level down).
        depth: Number of down-sampling levels, >= 1.
        in_channels: Channels of the input, >= 1 (1 for single slices; 2.5D inputs stack a
            slice's neighbours as channels).

    Raises:
        ConfigFieldError: On construction, naming the field, for a value below 1.
    """

    width: int = 16
    depth: int = 4
    in_channels: int = 1

    def __post_init__(self) -> None:
        for name in ("width", "depth", "in_channels"):
            check_int("SegmentationConfig", name, getattr(self, name), minimum=1)


def _block(channels_in: int, channels_out: int) -> nn.Sequential:
    """Two 3x3 convolutions, each with batch norm and ReLU."""
    return nn.Sequential(
        nn.Conv2d(channels_in, channels_out, 3, padding=1, bias=False),
        nn.BatchNorm2d(channels_out),
        nn.ReLU(inplace=True),
        nn.Conv2d(channels_out, channels_out, 3, padding=1, bias=False),
        nn.BatchNorm2d(channels_out),
        nn.ReLU(inplace=True),
    )


class BrainUNet(nn.Module):
    """U-Net (Ronneberger et al. 2015) with ``config.depth`` levels and skip connections.

    Args:
        config: Width and depth; ``None`` for ``SegmentationConfig()``.

    Attributes:
        config: The configuration.
    """

    def __init__(self, config: SegmentationConfig | None = None) -> None:
        super().__init__()
        self.config = SegmentationConfig() if config is None else config
        w, d = self.config.width, self.config.depth
        widths = [w * 2**i for i in range(d + 1)]
        self.down = nn.ModuleList(
            [_block(self.config.in_channels, widths[0])]
            + [_block(widths[i], widths[i + 1]) for i in range(d)]
        )
        self.pool = nn.MaxPool2d(2)
        self.up = nn.ModuleList(
            [nn.ConvTranspose2d(widths[i + 1], widths[i], 2, stride=2) for i in reversed(range(d))]
        )
        self.merge = nn.ModuleList([_block(2 * widths[i], widths[i]) for i in reversed(range(d))])
        self.head = nn.Conv2d(widths[0], 1, 1)

    def forward(self, slices: Tensor) -> Tensor:
        """Brain logits (B, 1, H, W) of (B, C, H, W) slices.

        C is ``in_channels``; H and W are multiples of ``2 ** depth``.

        Raises:
            ValueError: If the input is not (B, C, H, W) with such C, H and W.
        """
        step = 2**self.config.depth
        channels = self.config.in_channels
        if (
            slices.dim() != 4
            or slices.shape[1] != channels
            or slices.shape[2] % step
            or slices.shape[3] % step
        ):
            raise ValueError(
                f"BrainUNet: input must be (B, {channels}, H, W) with H and W multiples of {step}, "
                f"got {tuple(slices.shape)}"
            )
        skips = []
        x = slices
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else self.pool(x))
            skips.append(x)
        skips.pop()
        for up, merge in zip(self.up, self.merge, strict=True):
            x = merge(torch.cat([up(x), skips.pop()], dim=1))
        return self.head(x)


def parameter_bytes(model: nn.Module, dtype: torch.dtype = torch.float16) -> int:
    """Size of ``model``'s parameters and buffers when stored in ``dtype`` (bytes)."""
    size = torch.empty((), dtype=dtype).element_size()
    return (
        sum(t.numel() for t in (*model.parameters(), *model.buffers()) if t.is_floating_point())
        * size
    )
