"""Training and evaluation datasets of slices cut from canonical volumes, with pose labels.

* :class:`SliceStream`: an endless (or ``num_batches``-long) stream of random batches for training,
  sampled on the fly: random poses (Euler angles or uniform rotations, offsets along the normal,
  in-plane shifts), the empty-slice rule, per-batch in-plane spacing and thickness jitter, and
  intensity augmentation (:mod:`svr.sampling.augment`).
* :class:`EulerGridDataset`: the paper's regular Euler grid over one volume (map-style), for the
  paper-scale experiment; :class:`EulerGridStream`: the grids of several volumes as a shuffled,
  resumable training stream with :class:`SliceStream`'s batches and augmentation.

**Empty-slice rule.** A slice is kept only if at least ``min_brain_fraction`` of its pixels lie
inside the brain mask (:func:`svr.sampling.slicer.brain_fraction`: the mask sampled by nearest
neighbour on the slice's centre plane, with the slice's size and in-plane spacing). Rejected random
poses are redrawn; rejected grid poses are left out.

**Labels** are :func:`svr.sampling.poses.pose_labels` of the poses actually sampled (after any
in-plane shift), in float32; the poses themselves come in float64. Poses map slice-plane mm to
canonical mm.

**Reproducibility.** Batch ``i`` of epoch ``e`` of a :class:`SliceStream` is a pure function of
``(config.seed, e, i)``: its ``torch.Generator`` is seeded with a hash of the three, and nothing
else (no global RNG) is used. With a ``DataLoader`` of ``W`` workers, worker ``w`` makes batches
``w, w + W, w + 2 W, ...``; the ``DataLoader`` takes them round-robin, so the stream is the same
for every number of workers, and each worker's own stream is different and reproducible. Call
:meth:`SliceStream.set_epoch` before each epoch (like ``DistributedSampler``) to get new batches.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, get_args

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from svr.image import Image
from svr.representation_registry import REPRESENTATIONS, Representation, get_representation
from svr.sampling.augment import SliceAugmentConfig, apply_augment, draw_augment_params, shift_poses
from svr.sampling.deform import DEFAULT_CONTROL_POINTS, random_displacement
from svr.sampling.poses import (
    DEFAULT_EULER_GRID,
    EulerGridConfig,
    RotationSampling,
    iter_euler_grid_poses,
    pose_labels,
    random_slice_poses,
)
from svr.sampling.slicer import SliceConfig, brain_fraction, sample_slices
from svr.sampling.volume import CanonicalVolume
from svr.validation import (
    check_bool,
    check_choice,
    check_fraction,
    check_instance,
    check_int,
    check_number,
    check_range,
    is_integer,
)

DEFAULT_MIN_BRAIN_FRACTION = 0.02
"""Default of the empty-slice rule: at least 2 % of a slice's pixels inside the brain mask.

With the default 128 x 128 slices at 1 mm that is about 330 mm^2 of brain: slices that only graze
the brain are dropped, while a young fetal brain (a mid-slice of ~15 % of the field of view) keeps
most of its off-centre slices."""


@dataclass(frozen=True)
class SliceDatasetConfig:
    """How :class:`SliceStream` draws its batches.

    Attributes:
        slice: Slice size, spacing, thickness, PSF and interpolation (the jitter ranges below
            replace its ``spacing_mm`` and ``thickness_mm`` per batch when set).
        thickness_range_mm: ``None`` to use ``slice.thickness_mm``, else ``(low, high)``: each batch
            has one thickness (FWHM of the through-plane PSF), uniform in the range, mm.
        spacing_range_mm: ``None`` to use ``slice.spacing_mm``, else ``(low, high)``: each batch has
            one in-plane spacing, uniform in the range, mm (the field of view changes with it).
        rotation: ``"euler"`` (three Euler angles uniform in +-``angle_range_deg``, the paper's) or
            ``"uniform"`` (uniform on SO(3)); see :func:`svr.sampling.poses.random_slice_poses`.
        angle_range_deg: Half-width of each Euler angle's range, degrees, >= 0.
        tz_range_mm: Half-width of the offset along the slice normal, mm, >= 0.
        shift_mm: Maximum in-plane shift, mm, >= 0: ``du`` and ``dv`` are each uniform in
            ``[-shift_mm, +shift_mm]`` and applied to the pose before sampling
            (:func:`svr.sampling.augment.shift_poses`), so the label is that of the shifted slice.
        min_brain_fraction: The empty-slice rule (module docstring), in [0, 1]; 0 keeps all.
        max_resample_rounds: How many times rejected poses are redrawn before giving up, >= 1.
        mix_volumes: ``False``: each batch comes from one volume drawn uniformly; ``True``: each
            slice draws its own volume.
        representation: Label representation, a registered name
            (:data:`svr.representation_registry.REPRESENTATIONS`).
        augment: Intensity augmentation, or ``None`` for none.
        scale_range: ``None`` for none, else ``(low, high)``, ``0 < low <= high``: each batch
            scales its volume about the canonical origin by a factor drawn log-uniformly per
            canonical axis (a brain of another size and shape; the labels are the poses in the
            scaled brain's canonical frame).
        deform_mm: Random smooth non-rigid deformation of each batch's volume(s)
            (:func:`svr.sampling.deform.random_displacement`): standard deviation of the control
            displacements in mm, >= 0; 0 for none. The field has no rigid part, so the labels stay
            the poses in the canonical frame; the empty-slice rule reads the undeformed mask.
        deform_control_points: Control points per axis of that field, >= 2.
        batch_size: Slices per batch, >= 1.
        num_batches: Batches per epoch (over all ``DataLoader`` workers), >= 1, or ``None`` for an
            endless stream.
        seed: Seed of the stream, >= 0.

    Raises:
        ConfigFieldError: On construction, naming the field, if a value is invalid.
    """

    slice: SliceConfig = field(default_factory=SliceConfig)
    thickness_range_mm: tuple[float, float] | None = None
    spacing_range_mm: tuple[float, float] | None = None
    rotation: RotationSampling = "euler"
    angle_range_deg: float = 90.0
    tz_range_mm: float = 40.0
    shift_mm: float = 0.0
    min_brain_fraction: float = DEFAULT_MIN_BRAIN_FRACTION
    max_resample_rounds: int = 100
    mix_volumes: bool = False
    representation: Representation = "se3"
    augment: SliceAugmentConfig | None = None
    scale_range: tuple[float, float] | None = None
    deform_mm: float = 0.0
    deform_control_points: int = DEFAULT_CONTROL_POINTS
    batch_size: int = 32
    num_batches: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        owner = "SliceDatasetConfig"
        check_instance(owner, "slice", self.slice, SliceConfig)
        for name in ("thickness_range_mm", "spacing_range_mm", "scale_range"):
            check_range(owner, name, getattr(self, name), gt=0, allow_none=True)
        check_choice(owner, "rotation", self.rotation, get_args(RotationSampling))
        for name in ("angle_range_deg", "tz_range_mm", "shift_mm", "deform_mm"):
            check_number(owner, name, getattr(self, name), ge=0)
        check_fraction(owner, "min_brain_fraction", self.min_brain_fraction)
        check_int(owner, "max_resample_rounds", self.max_resample_rounds, minimum=1)
        check_int(owner, "deform_control_points", self.deform_control_points, minimum=2)
        check_bool(owner, "mix_volumes", self.mix_volumes)
        check_choice(owner, "representation", self.representation, tuple(REPRESENTATIONS))
        check_instance(owner, "augment", self.augment, SliceAugmentConfig, allow_none=True)
        check_int(owner, "batch_size", self.batch_size, minimum=1)
        check_int(owner, "num_batches", self.num_batches, minimum=1, allow_none=True)
        check_int(owner, "seed", self.seed, minimum=0)


def _mask_image(volume: CanonicalVolume) -> Image:
    """The brain mask of ``volume`` as a float image on the volume's grid (1 inside)."""
    return Image(volume.mask.to(volume.image.data.dtype), volume.image.affine)


def _scaled(image: Image, scale: Tensor | None) -> Image:
    """``image`` scaled about the canonical origin by (3,) per-axis factors (``None``: as is)."""
    if scale is None:
        return image
    factors = torch.ones(4, dtype=image.affine.dtype, device=image.affine.device)
    factors[:3] = scale.to(factors)
    return Image(image.data, factors[:, None] * image.affine)


_GRID_ORDER_TAG = 0x67726964  # keeps the seeds of grid passes apart from those of batches


def _batch_seed(seed: int, epoch: int, index: int) -> int:
    """A 64-bit seed hashed from the stream seed, the epoch and the batch index."""
    return int(np.random.SeedSequence([seed, epoch, index]).generate_state(1, np.uint64)[0])


class SliceStream(IterableDataset[dict[str, Tensor]]):
    """Random batches of slices with pose labels, sampled on the fly from canonical volumes.

    Each batch draws its in-plane spacing and thickness (when jittered), its volume(s), then the
    poses (random rotation, offset along the normal, in-plane shift), redrawing those that break
    the empty-slice rule, samples the slices and augments them. Use it with
    ``DataLoader(stream, batch_size=None, num_workers=...)``: the stream makes whole batches.

    Each yielded batch is a dict of tensors, on the volumes' device:

    * ``"slices"``: (B, 1, H, W) float32 slices (after augmentation).
    * ``"labels"``: (B, D) float32 :func:`~svr.sampling.poses.pose_labels` of ``"poses"`` in
      ``config.representation`` (D: the ``size`` of its entry in
      :data:`svr.representation_registry.REPRESENTATIONS`).
    * ``"poses"``: (B, 6) float64 pose vectors (rad, mm), slice plane -> canonical frame.
    * ``"volume_index"``: (B,) int64 index of each slice's volume in ``volumes``.
    * ``"spacing_mm"``: (B,) float64 in-plane spacing the slices were sampled with, mm.
    * ``"thickness_mm"``: (B,) float64 slice thickness (PSF FWHM), mm; 0 for thin slices.

    Args:
        volumes: One or more canonical volumes, all on one device (where sampling runs).
        config: How batches are drawn; ``None`` for ``SliceDatasetConfig()``.

    Attributes:
        volumes: The volumes, as a tuple.
        config: The configuration.
        device: The volumes' device.
        epoch: The epoch the next iteration yields (:meth:`set_epoch`).

    Raises:
        ValueError: If ``volumes`` is empty, holds something else than ``CanonicalVolume`` or
            spans several devices.
    """

    def __init__(
        self, volumes: Sequence[CanonicalVolume], config: SliceDatasetConfig | None = None
    ) -> None:
        super().__init__()
        volumes = tuple(volumes)
        if not volumes or not all(isinstance(v, CanonicalVolume) for v in volumes):
            raise ValueError(
                "SliceStream: 'volumes' must be a non-empty sequence of CanonicalVolume"
            )
        devices = {v.image.data.device for v in volumes}
        if len(devices) != 1:
            raise ValueError(f"SliceStream: 'volumes' must all be on one device, got {devices}")
        self.volumes = volumes
        self.config = SliceDatasetConfig() if config is None else config
        self.device = devices.pop()
        self.epoch = 0
        self._masks = tuple(_mask_image(v) for v in volumes)

    def set_epoch(self, epoch: int) -> None:
        """Choose the epoch whose batches the next iteration yields (default 0).

        Raises:
            ValueError: If ``epoch`` is not a non-negative integer.
        """
        if not (is_integer(epoch) and epoch >= 0):
            raise ValueError(
                f"SliceStream.set_epoch(): 'epoch' must be an integer >= 0, got {epoch!r}"
            )
        self.epoch = epoch

    def __len__(self) -> int:
        """``config.num_batches``; an endless stream has no length (``TypeError``)."""
        if self.config.num_batches is None:
            raise TypeError("SliceStream: an endless stream (num_batches=None) has no length")
        return self.config.num_batches

    def __iter__(self) -> Iterator[dict[str, Tensor]]:
        """Yield this worker's share of the epoch's batches (module docstring)."""
        info = get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        total = self.config.num_batches
        indices = (
            itertools.count(worker, workers) if total is None else range(worker, total, workers)
        )
        epoch = self.epoch
        for index in indices:
            yield self.batch(index, epoch)

    def batch(self, index: int, epoch: int | None = None) -> dict[str, Tensor]:
        """Batch ``index`` of ``epoch`` (default: the current epoch), as the stream yields it.

        Args:
            index: Batch index in the epoch, >= 0.
            epoch: Epoch, >= 0; ``None`` for :attr:`epoch`.

        Returns:
            The batch dict (class docstring).

        Raises:
            ValueError: If ``index`` or ``epoch`` is not a non-negative integer.
            RuntimeError: If ``config.max_resample_rounds`` rounds of redrawing leave poses that
                break the empty-slice rule.
        """
        epoch = self.epoch if epoch is None else epoch
        for name, value in (("index", index), ("epoch", epoch)):
            if not (is_integer(value) and value >= 0):
                raise ValueError(
                    f"SliceStream.batch(): '{name}' must be an integer >= 0, got {value!r}"
                )
        cfg = self.config
        generator = torch.Generator().manual_seed(_batch_seed(cfg.seed, epoch, index))
        b = cfg.batch_size
        slice_config = self._draw_slice_config(generator)
        scale = None
        if cfg.scale_range is not None:
            low, high = (math.log(x) for x in cfg.scale_range)
            scale = torch.exp(low + (high - low) * torch.rand(3, generator=generator).double())
        masks = tuple(_scaled(m, scale) for m in self._masks)
        volume_index, poses = self._batch_poses(index, epoch, slice_config, generator, masks)

        slices = torch.empty((b, *slice_config.size), dtype=torch.float32, device=self.device)
        for v in volume_index.unique().tolist():
            chosen = volume_index == v
            image = _scaled(self.volumes[v].image, scale)
            displacement = None
            if cfg.deform_mm > 0:
                displacement = random_displacement(
                    image, cfg.deform_mm, generator, cfg.deform_control_points
                )
            slices[chosen.to(self.device)] = sample_slices(
                image, poses[chosen].to(self.device), slice_config, displacement
            ).float()
        if cfg.augment is not None:
            slices = apply_augment(slices, draw_augment_params(cfg.augment, b, generator))
        thickness = slice_config.thickness_mm or 0.0
        kw: dict[str, Any] = {"dtype": torch.float64, "device": self.device}
        return {
            "slices": slices.unsqueeze(1),
            "labels": pose_labels(poses, cfg.representation).to(self.device, torch.float32),
            "poses": poses.to(self.device),
            "volume_index": volume_index.to(self.device),
            "spacing_mm": torch.full((b,), slice_config.spacing_mm, **kw),
            "thickness_mm": torch.full((b,), thickness, **kw),
        }

    def _draw_slice_config(self, generator: torch.Generator) -> SliceConfig:
        """The batch's slice configuration, with jittered spacing and thickness."""
        cfg = self.config
        u = torch.rand(2, generator=generator, dtype=torch.float64).tolist()
        spacing, thickness = cfg.slice.spacing_mm, cfg.slice.thickness_mm
        if cfg.spacing_range_mm is not None:
            low, high = cfg.spacing_range_mm
            spacing = low + (high - low) * u[0]
        if cfg.thickness_range_mm is not None:
            low, high = cfg.thickness_range_mm
            thickness = low + (high - low) * u[1]
        return dataclasses.replace(cfg.slice, spacing_mm=spacing, thickness_mm=thickness)

    def _batch_poses(
        self,
        index: int,
        epoch: int,
        slice_config: SliceConfig,
        generator: torch.Generator,
        masks: Sequence[Image],
    ) -> tuple[Tensor, Tensor]:
        """The batch's (B,) int64 volume indices and (B, 6) float64 CPU poses.

        Random poses here (each batch from one volume unless ``config.mix_volumes``); subclasses
        choose them otherwise. ``index`` and ``epoch`` identify the batch; ``generator`` is its
        random stream, after the slice configuration's draws; ``masks`` are the volumes' brain
        masks as this batch sees them (scaled).
        """
        b, n = self.config.batch_size, len(self.volumes)
        if self.config.mix_volumes:
            volume_index = torch.randint(n, (b,), generator=generator)
        else:
            volume_index = torch.randint(n, (1,), generator=generator).repeat(b)
        return volume_index, self._draw_poses(volume_index, slice_config, generator, masks)

    def _draw_poses(
        self,
        volume_index: Tensor,
        slice_config: SliceConfig,
        generator: torch.Generator,
        masks: Sequence[Image],
    ) -> Tensor:
        """(B, 6) float64 CPU poses obeying the empty-slice rule, each in its slice's volume."""
        cfg = self.config
        poses = torch.empty(len(volume_index), 6, dtype=torch.float64)
        missing = torch.ones(len(volume_index), dtype=torch.bool)
        for _ in range(cfg.max_resample_rounds):
            slots = torch.nonzero(missing).flatten()
            k = len(slots)
            candidates = random_slice_poses(
                k, generator, cfg.angle_range_deg, cfg.tz_range_mm, cfg.rotation
            )
            shifts = 2.0 * torch.rand(k, 2, generator=generator, dtype=torch.float64) - 1.0
            candidates = shift_poses(candidates, shifts * cfg.shift_mm)
            keep = torch.ones(k, dtype=torch.bool)
            if cfg.min_brain_fraction > 0:
                for v in volume_index[slots].unique().tolist():
                    chosen = volume_index[slots] == v
                    fraction = brain_fraction(
                        masks[v], candidates[chosen].to(self.device), slice_config
                    )
                    keep[chosen] = fraction.cpu() >= cfg.min_brain_fraction
            poses[slots[keep]] = candidates[keep]
            missing[slots[keep]] = False
            if not bool(missing.any()):
                return poses
        raise RuntimeError(
            f"SliceStream: {int(missing.sum())} of {len(missing)} slices still had a brain "
            f"fraction below min_brain_fraction={cfg.min_brain_fraction} after "
            f"max_resample_rounds={cfg.max_resample_rounds}; lower 'min_brain_fraction', "
            "'tz_range_mm' or 'shift_mm', or enlarge the slices"
        )


class EulerGridStream(SliceStream):
    """Training batches at the Euler-grid poses of every volume, shuffled (the paper's data).

    The items are the ``(volume, grid pose)`` pairs that pass the empty-slice rule: the poses of an
    :class:`EulerGridDataset` of each volume, built with ``config.slice`` (size and nominal
    spacing) and ``config.min_brain_fraction``. The stream goes through all ``N`` items in
    *passes*: pass ``p`` of epoch ``e`` is a permutation of the items seeded by
    ``(config.seed, e, p)``, cut into ``N // batch_size`` full batches (the last ``N mod
    batch_size`` items of the permutation are left out of that pass). Batch ``i`` is batch
    ``i mod (N // batch_size)`` of pass ``i // (N // batch_size)``, so, as in
    :class:`SliceStream`, a batch is a pure function of ``(config.seed, epoch, index)`` and a
    training run resumed at step ``s`` sees the batches it would have seen.

    Everything else is :class:`SliceStream`'s: the batch dict, per-batch spacing and thickness
    jitter, in-plane shifts of up to ``config.shift_mm`` (applied to the grid pose; the label is
    that of the shifted slice) and intensity augmentation, all drawn from the batch's generator.
    The grid replaces the random poses: ``config.rotation``, ``angle_range_deg``,
    ``tz_range_mm``, ``mix_volumes`` and ``max_resample_rounds`` are not used.

    Args:
        volumes: One or more canonical volumes, all on one device (where the grid is swept and
            slices are sampled).
        config: How batches are drawn; ``None`` for ``SliceDatasetConfig()``.
        grid: The Euler grid (default: the paper's, 54,571 poses per volume).

    Attributes:
        grid_volume_index: (N,) int64 volume of each item, on the CPU.
        grid_poses: (N, 6) float64 grid pose of each item (rad, mm), on the CPU.
        batches_per_pass: ``N // config.batch_size``.

    Raises:
        ValueError: As :class:`SliceStream`, or if fewer than ``config.batch_size`` grid poses
            pass the empty-slice rule.
    """

    def __init__(
        self,
        volumes: Sequence[CanonicalVolume],
        config: SliceDatasetConfig | None = None,
        grid: EulerGridConfig = DEFAULT_EULER_GRID,
    ) -> None:
        super().__init__(volumes, config)
        cfg = self.config
        grids = [
            EulerGridDataset(v, grid, cfg.slice, cfg.min_brain_fraction, cfg.representation)
            for v in self.volumes
        ]
        self.grid_volume_index = torch.cat(
            [torch.full((len(g),), v, dtype=torch.int64) for v, g in enumerate(grids)]
        )
        self.grid_poses = torch.cat([g.poses for g in grids])
        self.batches_per_pass = len(self.grid_poses) // cfg.batch_size
        if self.batches_per_pass == 0:
            raise ValueError(
                f"EulerGridStream: only {len(self.grid_poses)} grid poses pass the empty-slice "
                f"rule, fewer than batch_size={cfg.batch_size}; use a finer grid, more volumes "
                "or a lower 'min_brain_fraction'"
            )
        self._order: tuple[tuple[int, int], Tensor] | None = None

    def _pass_order(self, epoch: int, pass_index: int) -> Tensor:
        """(N,) int64 permutation of the items in pass ``pass_index`` of ``epoch`` (cached)."""
        key = (epoch, pass_index)
        if self._order is None or self._order[0] != key:
            seed = np.random.SeedSequence([self.config.seed, epoch, pass_index, _GRID_ORDER_TAG])
            generator = torch.Generator().manual_seed(int(seed.generate_state(1, np.uint64)[0]))
            self._order = key, torch.randperm(len(self.grid_poses), generator=generator)
        return self._order[1]

    def _batch_poses(
        self,
        index: int,
        epoch: int,
        slice_config: SliceConfig,
        generator: torch.Generator,
        masks: Sequence[Image],
    ) -> tuple[Tensor, Tensor]:
        """The batch's items of its pass, with in-plane shifts drawn from ``generator``.

        The grid's empty-slice rule was applied to the unscaled masks; ``masks`` is unused.
        """
        b = self.config.batch_size
        pass_index, position = divmod(index, self.batches_per_pass)
        items = self._pass_order(epoch, pass_index)[position * b : (position + 1) * b]
        shifts = 2.0 * torch.rand(b, 2, generator=generator, dtype=torch.float64) - 1.0
        poses = shift_poses(self.grid_poses[items], shifts * self.config.shift_mm)
        return self.grid_volume_index[items], poses


class EulerGridDataset(Dataset[tuple[Tensor, Tensor]]):
    """Slices of one volume at the Euler-grid poses that pass the empty-slice rule (map-style).

    The kept poses are found once, on construction, by sweeping the grid in chunks of
    ``chunk_size`` poses (:func:`svr.sampling.poses.iter_euler_grid_poses`); slices are sampled when
    read. Item ``i`` is ``(slice, label)``: a (1, H, W) float32 slice at ``poses[i]`` and its
    (D,) float32 label in ``representation``. ``DataLoader`` reads whole batches at once through
    :meth:`__getitems__`.

    Args:
        volume: The canonical volume (sampling runs on its device).
        grid_config: The Euler grid (default: the paper's, 54,571 poses).
        slice_config: Slice size, spacing, PSF and interpolation.
        min_brain_fraction: The empty-slice rule (module docstring), in [0, 1].
        representation: Label representation, a registered name
            (:data:`svr.representation_registry.REPRESENTATIONS`).
        chunk_size: Poses per chunk of the sweep, >= 1.

    Attributes:
        grid_indices: (K,) int64 indices of the kept poses in the grid order of
            :func:`svr.sampling.poses.euler_grid_poses`, increasing.
        poses: (K, 6) float64 kept poses (rad, mm), slice plane -> canonical frame, on the CPU.
        labels: (K, D) float32 labels of ``poses``, on the CPU.

    Raises:
        ValueError: Naming the argument, if ``min_brain_fraction``, ``representation`` or
            ``chunk_size`` is invalid.
    """

    def __init__(
        self,
        volume: CanonicalVolume,
        grid_config: EulerGridConfig = DEFAULT_EULER_GRID,
        slice_config: SliceConfig | None = None,
        min_brain_fraction: float = DEFAULT_MIN_BRAIN_FRACTION,
        representation: Representation = "se3",
        chunk_size: int = 4096,
    ) -> None:
        super().__init__()
        check_fraction("EulerGridDataset", "min_brain_fraction", min_brain_fraction)
        get_representation(representation, "EulerGridDataset")
        check_int("EulerGridDataset", "chunk_size", chunk_size, minimum=1)
        self.volume = volume
        self.slice_config = SliceConfig() if slice_config is None else slice_config
        self.representation = representation
        device = volume.image.data.device
        mask = _mask_image(volume)
        indices, poses, start = [], [], 0
        for chunk in iter_euler_grid_poses(grid_config, chunk_size):
            if min_brain_fraction > 0:
                fraction = brain_fraction(mask, chunk.to(device), self.slice_config).cpu()
                keep = torch.nonzero(fraction >= min_brain_fraction).flatten()
            else:
                keep = torch.arange(len(chunk))
            indices.append(keep + start)
            poses.append(chunk[keep])
            start += len(chunk)
        self.grid_indices = torch.cat(indices)
        self.poses = torch.cat(poses)
        self.labels = pose_labels(self.poses, representation).float()

    def __len__(self) -> int:
        """Number ``K`` of kept poses."""
        return len(self.grid_indices)

    def __getitem__(self, index: int) -> tuple[Tensor, Tensor]:
        """Item ``index``: ``(slice (1, H, W), label (D,))``, float32, on the volume's device."""
        return self.__getitems__([index])[0]

    def __getitems__(self, indices: Sequence[int]) -> list[tuple[Tensor, Tensor]]:
        """Several items, sampled in one call (``DataLoader``'s batched fetch).

        Raises:
            IndexError: If an index is out of range.
        """
        device = self.volume.image.data.device
        index = torch.as_tensor(list(indices), dtype=torch.int64)
        if len(index) and not bool(((index >= -len(self)) & (index < len(self))).all()):
            raise IndexError(f"EulerGridDataset: index out of range for {len(self)} items")
        slices = sample_slices(self.volume.image, self.poses[index].to(device), self.slice_config)
        labels = self.labels[index].to(device)
        return [(s[None].float(), label) for s, label in zip(slices, labels, strict=True)]
