"""The settings of the masking stage: how stacks get masks, the networks' canvases, the fusion."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from svr.errors import ConfigFieldError
from svr.models.segmentation import SegmentationConfig
from svr.validation import (
    check_bool,
    check_choice,
    check_fraction,
    check_instance,
    check_int,
    check_number,
    is_finite_number,
    is_integer,
)

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
        ConfigFieldError: On construction, naming the field and what it accepts.
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
        owner = "BrainMaskConfig"
        check_bool(owner, "localiser_tiles", self.localiser_tiles)
        check_number(owner, "localiser_mm", self.localiser_mm, gt=0)
        check_number(owner, "segmenter_mm", self.segmenter_mm, gt=0)
        check_instance(owner, "localiser", self.localiser, SegmentationConfig)
        check_instance(owner, "segmenter", self.segmenter, SegmentationConfig)
        if self.localiser.in_channels != 1:
            raise ConfigFieldError(owner, "localiser.in_channels", "1", self.localiser.in_channels)
        if self.segmenter.in_channels % 2 != 1:
            raise ConfigFieldError(
                owner,
                "segmenter.in_channels",
                "odd (a slice and as many neighbours on either side)",
                self.segmenter.in_channels,
            )
        for name, net in (("localiser", self.localiser), ("segmenter", self.segmenter)):
            size, step = getattr(self, f"{name}_size"), 2**net.depth
            check_int(owner, f"{name}_size", size, minimum=step)
            if size % step:
                expected = f"a positive multiple of {step} (2 ** {name}.depth)"
                raise ConfigFieldError(owner, f"{name}_size", expected, size)
        check_number(owner, "threshold", self.threshold, gt=0, lt=1)
        check_int(owner, "slice_margin", self.slice_margin, minimum=0, allow_none=True)
        check_number(owner, "opening_mm", self.opening_mm, gt=0, allow_none=True)
        check_number(owner, "regrow_mm", self.regrow_mm, ge=0)
        check_number(owner, "min_volume_ml", self.min_volume_ml, ge=0)
        if not (is_finite_number(self.max_volume_ml) and self.max_volume_ml > self.min_volume_ml):
            raise ConfigFieldError(
                owner,
                "max_volume_ml",
                f"a finite number > 'min_volume_ml' ({self.min_volume_ml!r})",
                self.max_volume_ml,
            )
        check_fraction(owner, "max_stack_fraction", self.max_stack_fraction, include_zero=False)
        check_number(owner, "percentile", self.percentile, gt=0, le=100)

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
        ConfigFieldError: On construction, naming the field and what it accepts.
    """

    resolution_mm: float = 1.0
    footprint_mm: float = 10.0
    threshold: float = 0.5
    own_margin: float = 0.15
    min_agreement: float = 0.7
    registration_mm: float = 0.8
    psf_samples: int = 5

    def __post_init__(self) -> None:
        owner = "MaskFusionConfig"
        check_number(owner, "resolution_mm", self.resolution_mm, gt=0)
        check_number(owner, "registration_mm", self.registration_mm, gt=0)
        check_number(owner, "footprint_mm", self.footprint_mm, ge=0)
        check_number(owner, "threshold", self.threshold, gt=0, lt=1)
        limit = min(self.threshold, 1 - self.threshold)
        if not (is_finite_number(self.own_margin) and 0 <= self.own_margin < limit):
            raise ConfigFieldError(
                owner, "own_margin", "in [0, min(threshold, 1 - threshold))", self.own_margin
            )
        check_fraction(owner, "min_agreement", self.min_agreement)
        samples = self.psf_samples
        if not (is_integer(samples) and samples >= 1 and samples % 2 == 1):
            raise ConfigFieldError(owner, "psf_samples", "an odd integer >= 1", samples)


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
        owner = "MaskingConfig"
        check_choice(owner, "method", self.method, AUTO_MASKS)
        check_bool(owner, "fuse", self.fuse)
        if self.fuse and self.method != "network":
            raise ConfigFieldError(owner, "fuse", "false unless method='network'", self.fuse)
        check_instance(owner, "fusion", self.fusion, MaskFusionConfig)
