"""The settings of the masking stage: how stacks get masks, the networks' canvases, the fusion."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from svr.errors import ConfigFieldError
from svr.models.segmentation import SegmentationConfig
from svr.sampling._validation import is_finite_number

__all__ = ["AUTO_MASKS", "AutoMask", "BrainMaskConfig", "MaskFusionConfig", "MaskingConfig"]

AutoMask = Literal["network", "otsu"]
AUTO_MASKS: tuple[str, ...] = ("network", "otsu")
"""The automatic masks of stacks given without one (``MaskingConfig.method``)."""


@dataclass(frozen=True)
class BrainMaskConfig:
    """Canvases and thresholds of :func:`segment_stack` and the two networks' shapes.

    Attributes:
        localiser_mm: Pixel size of the localiser's canvas, mm, > 0.
        localiser_size: Side of the localiser's canvas, pixels (a multiple of 16).
        localiser_tiles: Whether the localiser's canvases are tiles covering the field of view
            (overlapping by half) rather than one canvas centred on it.
        segmenter_mm: Pixel size of the segmenter's canvas, mm, > 0.
        segmenter_size: Side of the segmenter's canvas, pixels (a multiple of 16).
        localiser: The localiser U-Net's shape (one input channel).
        segmenter: The segmenter U-Net's shape; ``in_channels`` = 1 + 2 c (odd) makes it 2.5D:
            each slice comes with its c neighbours on either side (:attr:`segmenter_context`).
        threshold: Probability above which a voxel is brain, in (0, 1).
        min_volume_ml: Smallest brain accepted by the localiser, millilitres (cm^3), >= 0.
        max_volume_ml: Largest mask accepted, millilitres, > ``min_volume_ml`` (a term fetal
            head holds about 500 ml).
        max_stack_fraction: Largest fraction of the stack's voxels a mask may cover, in (0, 1]
            (a brain fills at most about half of a box cropped tightly around it; a mask over
            most of the field of view is the segmenter failing, not a brain).
        slice_margin: Slices beyond the localised brain's first and last that are segmented
            too, >= 0; ``None`` segments every slice (then the 3D clean-up alone decides where
            the brain ends, so pieces of other anatomy the segmenter takes for brain in slices
            beyond it may stay when they touch it).
        percentile: Percentile of a stack's positive voxels that is mapped to 1, in (0, 100].
        opening_mm: Radius of the ball by which the clean-up opens the mask (erodes, then
            dilates), mm, > 0; ``None`` for no opening. Where the opening would leave less than
            half of the mask (a brain thinner than the ball, e.g. a stack with few slices
            through it), the mask is kept unopened.
        regrow_mm: After the opening, the voxels of the mask within this distance of the
            opened mask (mm, >= 0) are kept too.

    Raises:
        ValueError: On construction, naming the field, for an invalid value.
    """

    localiser_mm: float = 3.0
    localiser_size: int = 128
    segmenter_mm: float = 1.25
    segmenter_size: int = 128
    localiser: SegmentationConfig = field(default_factory=lambda: SegmentationConfig(8, 4))
    segmenter: SegmentationConfig = field(default_factory=lambda: SegmentationConfig(8, 4))
    threshold: float = 0.5
    min_volume_ml: float = 5.0
    max_volume_ml: float = 1000.0
    max_stack_fraction: float = 0.8
    slice_margin: int | None = 2
    percentile: float = 99.0
    localiser_tiles: bool = False
    opening_mm: float | None = None
    regrow_mm: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.localiser_tiles, bool):
            raise ValueError(
                "BrainMaskConfig: 'localiser_tiles' must be true or false, "
                f"got {self.localiser_tiles!r}"
            )
        for name in ("localiser_mm", "segmenter_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and value > 0):
                raise ValueError(f"BrainMaskConfig: '{name}' must be a number > 0, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"BrainMaskConfig: '{name}' must be finite, got {value!r}")
        if self.localiser.in_channels != 1:
            raise ValueError(
                "BrainMaskConfig: 'localiser.in_channels' must be 1, "
                f"got {self.localiser.in_channels!r}"
            )
        if self.segmenter.in_channels % 2 != 1:
            raise ValueError(
                "BrainMaskConfig: 'segmenter.in_channels' must be odd (a slice and as many "
                f"neighbours on either side), got {self.segmenter.in_channels!r}"
            )
        for name, net in (("localiser", self.localiser), ("segmenter", self.segmenter)):
            size = getattr(self, f"{name}_size")
            step = 2**net.depth
            if isinstance(size, bool) or not isinstance(size, int) or size < step or size % step:
                raise ValueError(
                    f"BrainMaskConfig: '{name}_size' must be a positive multiple of {step} "
                    f"(2 ** {name}.depth), got {size!r}"
                )
        if not 0 < self.threshold < 1:
            raise ValueError(
                f"BrainMaskConfig: 'threshold' must be in (0, 1), got {self.threshold!r}"
            )
        if self.slice_margin is not None and (
            isinstance(self.slice_margin, bool)
            or not (isinstance(self.slice_margin, int) and self.slice_margin >= 0)
        ):
            raise ValueError(
                "BrainMaskConfig: 'slice_margin' must be an integer >= 0 or null, "
                f"got {self.slice_margin!r}"
            )
        radius, regrow = self.opening_mm, self.regrow_mm
        if radius is not None and not (is_finite_number(radius) and radius > 0):
            raise ValueError(
                f"BrainMaskConfig: 'opening_mm' must be a finite number > 0 or null, got {radius!r}"
            )
        if not (is_finite_number(regrow) and regrow >= 0):
            raise ValueError(
                f"BrainMaskConfig: 'regrow_mm' must be a finite number >= 0, got {regrow!r}"
            )
        if not self.min_volume_ml >= 0:
            raise ValueError(
                f"BrainMaskConfig: 'min_volume_ml' must be >= 0, got {self.min_volume_ml!r}"
            )
        if not (is_finite_number(self.max_volume_ml) and self.max_volume_ml > self.min_volume_ml):
            raise ValueError(
                "BrainMaskConfig: 'max_volume_ml' must be a finite number > 'min_volume_ml' "
                f"({self.min_volume_ml!r}), got {self.max_volume_ml!r}"
            )
        if not (is_finite_number(self.max_stack_fraction) and 0 < self.max_stack_fraction <= 1):
            raise ValueError(
                "BrainMaskConfig: 'max_stack_fraction' must be in (0, 1], "
                f"got {self.max_stack_fraction!r}"
            )
        if not 0 < self.percentile <= 100:
            raise ValueError(
                f"BrainMaskConfig: 'percentile' must be in (0, 100], got {self.percentile!r}"
            )

    @property
    def segmenter_context(self) -> int:
        """Neighbouring slices on either side that the segmenter sees (0: 2D)."""
        return (self.segmenter.in_channels - 1) // 2

    def to_dict(self) -> dict[str, Any]:
        """The config as JSON-serialisable data."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BrainMaskConfig:
        """The config written by :meth:`to_dict`.

        Raises:
            ValueError: For unknown or invalid fields.
        """
        values = dict(data)
        for name in ("localiser", "segmenter"):
            if name in values:
                values[name] = SegmentationConfig(**values[name])
        try:
            return cls(**values)
        except TypeError as exc:
            raise ValueError(f"BrainMaskConfig: {exc}") from exc


@dataclass(frozen=True)
class MaskFusionConfig:
    """How :func:`fuse_masks` makes the masks of one fetus's stacks agree.

    Attributes:
        resolution_mm: Voxel size of the fused mask volume, mm, > 0.
        footprint_mm: How far beyond the in-plane outline of a stack's mask (its union over the
            slices) its planes vote, mm, >= 0.
        threshold: Vote above which a pixel is brain, in (0, 1).
        own_margin: Where the vote is within this margin of ``threshold``, the stack's own mask
            decides, in [0, min(threshold, 1 - threshold)).
        min_agreement: Dice between a stack's own and fused masks below which the stack keeps
            its own mask and is left out of the vote, in [0, 1].
        registration_mm: Voxel size of the template volume of the stack registration
            (:func:`fuse_stack_masks`; the registration works at twice it), mm, > 0.
        psf_samples: Nodes of the through-plane PSF (odd).

    Raises:
        ValueError: On construction, naming the field, for an invalid value.
    """

    resolution_mm: float = 1.0
    footprint_mm: float = 10.0
    threshold: float = 0.5
    own_margin: float = 0.15
    min_agreement: float = 0.7
    registration_mm: float = 0.8
    psf_samples: int = 5

    def __post_init__(self) -> None:
        def fail(name: str, expected: str) -> None:
            raise ConfigFieldError("MaskFusionConfig", name, expected, getattr(self, name))

        for name in ("resolution_mm", "registration_mm"):
            if not (is_finite_number(getattr(self, name)) and getattr(self, name) > 0):
                fail(name, "a finite number > 0")
        if not (is_finite_number(self.footprint_mm) and self.footprint_mm >= 0):
            fail("footprint_mm", "a finite number >= 0")
        if not (is_finite_number(self.threshold) and 0 < self.threshold < 1):
            fail("threshold", "in (0, 1)")
        limit = min(self.threshold, 1 - self.threshold)
        if not (is_finite_number(self.own_margin) and 0 <= self.own_margin < limit):
            fail("own_margin", "in [0, min(threshold, 1 - threshold))")
        if not (is_finite_number(self.min_agreement) and 0 <= self.min_agreement <= 1):
            fail("min_agreement", "in [0, 1]")
        samples = self.psf_samples
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            fail("psf_samples", "an odd integer >= 1")
        if samples % 2 == 0:
            fail("psf_samples", "an odd integer >= 1")


@dataclass(frozen=True)
class MaskingConfig:
    """How stacks given without masks get one (:func:`svr.masking.auto_masks`).

    Attributes:
        method: ``"network"`` runs the brain-mask networks on each stack
            (:func:`svr.masking.segment.segment_stack`; for whole-uterus and cropped stacks);
            ``"otsu"`` keeps the voxels above each stack's Otsu threshold inside the region every
            stack's field of view covers, then the largest 3D component with its holes filled
            (:func:`svr.masking.otsu.otsu_mask`; only for stacks already cropped around the brain).
        fuse: Whether the network's masks are made to agree in 3D across the stacks (all of one
            fetus, at least 3; :func:`svr.masking.fuse.fuse_stack_masks`). Needs
            ``method="network"``.
        fusion: The fusion's settings.

    Raises:
        ConfigFieldError: On construction, naming the field and what it accepts.
    """

    method: AutoMask = "network"
    fuse: bool = False
    fusion: MaskFusionConfig = field(default_factory=MaskFusionConfig)

    def __post_init__(self) -> None:
        if self.method not in AUTO_MASKS:
            raise ConfigFieldError(
                "MaskingConfig", "method", f"one of {', '.join(AUTO_MASKS)}", self.method
            )
        if not isinstance(self.fuse, bool):
            raise ConfigFieldError("MaskingConfig", "fuse", "true or false", self.fuse)
        if self.fuse and self.method != "network":
            raise ConfigFieldError(
                "MaskingConfig", "fuse", "false unless method='network'", self.fuse
            )
        if not isinstance(self.fusion, MaskFusionConfig):
            raise ConfigFieldError("MaskingConfig", "fusion", "a MaskFusionConfig", self.fusion)
