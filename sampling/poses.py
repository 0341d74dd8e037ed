"""Slice poses for training and evaluation: the Euler grid, random poses and loss labels.

Conventions (``docs/conventions.md``):
    * A slice pose maps slice-plane coordinates ``(u, v, 0)`` in mm (origin at the slice centre) to
      the canonical frame by ``x -> R x + t``; pose vectors (..., 6) are
      ``(r_x, r_y, r_z, t_x, t_y, t_z)``, rotation vector (rad) first, translation (mm) second.
    * Euler angles are extrinsic ``"xyz"`` in radians (scipy's ``Rotation.from_euler("xyz", ...)``,
      ``R = Rz Ry Rx``); degrees appear only in the configuration fields that say so.
    * A slice at angles ``(Rx, Ry, Rz)`` and offset ``Tz`` (mm) has ``R = Euler(Rx, Ry, Rz)`` and
      ``t = R (0, 0, Tz)``: the plane through the origin with normal ``R[:, 2]``, moved ``Tz`` mm
      along that normal.

The Euler grid is ordered row-major over the indices of ``(Rx, Ry, Rz, Tz)``: ``Rx`` varies
slowest and ``Tz`` fastest. Every value is computed in float64 on the CPU and cast at the end, so
the same configuration gives the same poses whatever the chunking, dtype or device.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal, get_args

import torch
from torch import Tensor

from svr.errors import ConfigFieldError
from svr.geometry import (
    ANCHOR_HALF_SIZE_MM,
    euler_to_matrix,
    quat_to_matrix,
    quat_to_rotvec,
    so3_log,
)
from svr.image import Image
from svr.representation_registry import Representation, get_representation
from svr.sampling.slicer import SliceConfig, brain_fraction
from svr.sampling.volume import CanonicalVolume
from svr.validation import check_number, is_integer

RotationSampling = Literal["euler", "uniform"]
"""How :func:`random_slice_poses` draws rotations."""

_ROTATION_SAMPLINGS: tuple[str, ...] = get_args(RotationSampling)
_MULTIPLE_TOLERANCE = 1e-9


def _grid_half_count(range_name: str, range_value: float, step_name: str, step: float) -> int:
    """Number ``n`` of steps in ``[0, range]`` (the axis has ``2 n + 1`` values), validated."""
    owner = "EulerGridConfig"
    check_number(owner, step_name, step, gt=0)
    check_number(owner, range_name, range_value, ge=0)
    ratio = range_value / step
    count = round(ratio)
    if abs(ratio - count) > _MULTIPLE_TOLERANCE:
        raise ConfigFieldError(
            owner,
            range_name,
            f"a multiple of '{step_name}' ({step}) to within {_MULTIPLE_TOLERANCE:g} steps",
            range_value,
        )
    return count


@dataclass(frozen=True)
class EulerGridConfig:
    """The regular grid of slice poses over Euler angles and offsets along the slice normal.

    Each of ``Rx``, ``Ry`` and ``Rz`` takes the values ``k * angle_step_deg`` for the integers
    ``k`` with ``|k * angle_step_deg| <= angle_range_deg``, and ``Tz`` the values
    ``k * tz_step_mm`` within ``+-tz_range_mm``; both ends are included. The default grid
    (steps 18 deg and 2 mm, ranges 90 deg and 40 mm) has ``11**3 * 41 = 54,571`` poses. Near
    ``Ry = +-90 deg`` (gimbal lock) different angle triples can give the same rotation; the grid
    keeps them all.

    Attributes:
        angle_step_deg: Spacing of each Euler angle, degrees, > 0.
        angle_range_deg: Each angle lies in ``[-angle_range_deg, +angle_range_deg]``, degrees,
            >= 0 and a multiple of ``angle_step_deg`` (to within 1e-9 steps).
        tz_step_mm: Spacing of the offset along the slice normal, mm, > 0.
        tz_range_mm: The offset lies in ``[-tz_range_mm, +tz_range_mm]``, mm, >= 0 and a multiple
            of ``tz_step_mm`` (to within 1e-9 steps).

    Raises:
        ConfigFieldError: On construction, naming the field, if a step is not finite and
            positive, a range is not finite and non-negative, or a range is not a multiple of its
            step.
    """

    angle_step_deg: float = 18.0
    angle_range_deg: float = 90.0
    tz_step_mm: float = 2.0
    tz_range_mm: float = 40.0

    def __post_init__(self) -> None:
        self._angle_half_count()
        self._tz_half_count()

    def _angle_half_count(self) -> int:
        return _grid_half_count(
            "angle_range_deg", self.angle_range_deg, "angle_step_deg", self.angle_step_deg
        )

    def _tz_half_count(self) -> int:
        return _grid_half_count("tz_range_mm", self.tz_range_mm, "tz_step_mm", self.tz_step_mm)

    @property
    def num_angles(self) -> int:
        """Number of values of each Euler angle."""
        return 2 * self._angle_half_count() + 1

    @property
    def num_tz(self) -> int:
        """Number of values of the offset ``Tz``."""
        return 2 * self._tz_half_count() + 1

    @property
    def num_poses(self) -> int:
        """Number ``M = num_angles**3 * num_tz`` of poses in the grid."""
        return self.num_angles**3 * self.num_tz

    def angle_values_rad(self) -> Tensor:
        """The values of each Euler angle, increasing.

        Returns:
            (num_angles,) float64 CPU tensor of angles in radians.
        """
        half = self._angle_half_count()
        degrees = torch.arange(-half, half + 1, dtype=torch.float64) * self.angle_step_deg
        return torch.deg2rad(degrees)

    def tz_values_mm(self) -> Tensor:
        """The values of the offset ``Tz``, increasing.

        Returns:
            (num_tz,) float64 CPU tensor of offsets in mm.
        """
        half = self._tz_half_count()
        return torch.arange(-half, half + 1, dtype=torch.float64) * self.tz_step_mm


DEFAULT_EULER_GRID = EulerGridConfig()
"""The paper's grid: 18 deg steps over +-90 deg, 2 mm steps over +-40 mm (54,571 poses)."""


def _check_float_dtype(dtype: torch.dtype, func: str) -> None:
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise TypeError(f"{func}(): 'dtype' must be a floating-point torch.dtype, got {dtype}")


def _rotvec_and_normal(angles_rad: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation vectors and slice normals ``R[..., :, 2]`` of (..., 3) extrinsic xyz angles."""
    R = euler_to_matrix(angles_rad, "xyz")
    return so3_log(R), R[..., :, 2]


def euler_grid(config: EulerGridConfig = DEFAULT_EULER_GRID) -> tuple[Tensor, Tensor]:
    """The Euler angles and offsets of every pose in the grid.

    Args:
        config: The grid.

    Returns:
        ``(angles_rad, tz_mm)``: (M, 3) extrinsic xyz Euler angles in radians and (M,) offsets along
        the slice normal in mm, float64 on the CPU, ordered with ``Rx`` slowest and ``Tz`` fastest;
        ``M = config.num_poses`` (54,571 by default).
    """
    angles = config.angle_values_rad()
    rx, ry, rz, tz = torch.meshgrid(angles, angles, angles, config.tz_values_mm(), indexing="ij")
    return torch.stack([rx, ry, rz], dim=-1).reshape(-1, 3), tz.reshape(-1)


def euler_to_poses(angles_rad: Tensor, tz_mm: Tensor) -> Tensor:
    """Slice poses of Euler angles and offsets: ``R = Euler(angles)``, ``t = R (0, 0, Tz)``.

    Args:
        angles_rad: (..., 3) extrinsic xyz Euler angles in radians.
        tz_mm: (...) offsets along the slice normal in mm, broadcastable with
            ``angles_rad[..., 0]`` and of a floating-point dtype.

    Returns:
        (B..., 6) pose vectors mapping the slice plane to the canonical frame, ``B`` the broadcast
        batch shape, in the promoted dtype of the inputs.

    Raises:
        TypeError: If ``tz_mm`` is not a floating-point tensor (``angles_rad`` is checked by
            :func:`svr.geometry.euler_to_matrix`).
    """
    if not (isinstance(tz_mm, Tensor) and tz_mm.is_floating_point()):
        raise TypeError(
            "euler_to_poses(): 'tz_mm' must be a floating-point torch.Tensor, got "
            f"{tz_mm.dtype if isinstance(tz_mm, Tensor) else type(tz_mm).__name__}"
        )
    rotvec, normal = _rotvec_and_normal(angles_rad)
    shape = torch.broadcast_shapes(rotvec.shape[:-1], tz_mm.shape)
    translation = normal * tz_mm.unsqueeze(-1)
    return torch.cat([rotvec.expand(*shape, 3), translation.expand(*shape, 3)], dim=-1)


def iter_euler_grid_poses(
    config: EulerGridConfig = DEFAULT_EULER_GRID,
    chunk_size: int = 4096,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Iterator[Tensor]:
    """Stream the Euler-grid poses in chunks, in the order of :func:`euler_grid`.

    Memory stays within one chunk plus one block of ``num_angles**2`` rotations (those sharing
    ``Rx``), so grids far larger than memory can be swept. Rotations are computed block by block
    whatever ``chunk_size``, so the chunks concatenate exactly (bit for bit) to
    :func:`euler_grid_poses` for every chunk size.

    Args:
        config: The grid.
        chunk_size: Number of poses per chunk (> 0); the last chunk may be shorter.
        dtype: Floating-point dtype of the chunks (computed in float64, then cast).
        device: Device of the chunks; ``None`` for the CPU.

    Yields:
        (chunk_size, 6) pose vectors (fewer rows in the last chunk) mapping the slice plane to the
        canonical frame.

    Raises:
        ValueError: If ``chunk_size`` is not a positive integer.
        TypeError: If ``dtype`` is not a floating-point dtype.
    """
    if not (is_integer(chunk_size) and chunk_size > 0):
        raise ValueError(
            f"iter_euler_grid_poses(): 'chunk_size' must be a positive integer, got {chunk_size!r}"
        )
    _check_float_dtype(dtype, "iter_euler_grid_poses")
    return _iter_grid_chunks(config, chunk_size, dtype, device)


def _iter_grid_chunks(
    config: EulerGridConfig,
    chunk_size: int,
    dtype: torch.dtype,
    device: torch.device | str | None,
) -> Iterator[Tensor]:
    angles, tz = config.angle_values_rad(), config.tz_values_mm()
    ry, rz = (a.reshape(-1) for a in torch.meshgrid(angles, angles, indexing="ij"))
    block_size = ry.numel() * tz.numel()  # poses sharing one Rx value

    @functools.lru_cache(maxsize=1)
    def block(index: int) -> tuple[Tensor, Tensor]:
        return _rotvec_and_normal(torch.stack([angles[index].expand_as(ry), ry, rz], dim=-1))

    for start in range(0, config.num_poses, chunk_size):
        stop = min(start + chunk_size, config.num_poses)
        parts = []
        for index in range(start // block_size, (stop - 1) // block_size + 1):
            rotvec, normal = block(index)
            offset = index * block_size
            local = torch.arange(max(start, offset), min(stop, offset + block_size)) - offset
            rotation, tz_index = local // tz.numel(), local % tz.numel()
            translation = normal[rotation] * tz[tz_index].unsqueeze(-1)
            parts.append(torch.cat([rotvec[rotation], translation], dim=-1))
        yield torch.cat(parts).to(device=device, dtype=dtype)


def euler_grid_poses(
    config: EulerGridConfig = DEFAULT_EULER_GRID,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Tensor:
    """All poses of the Euler grid: ``R = Euler(Rx, Ry, Rz)``, ``t = R (0, 0, Tz)``.

    Equal to :func:`euler_to_poses` of :func:`euler_grid` to rounding, and exactly to the
    concatenated chunks of :func:`iter_euler_grid_poses`.

    Args:
        config: The grid.
        dtype: Floating-point dtype of the result (computed in float64, then cast).
        device: Device of the result; ``None`` for the CPU.

    Returns:
        (M, 6) pose vectors mapping the slice plane to the canonical frame, in the order of
        :func:`euler_grid`; ``M = config.num_poses`` (54,571 by default).

    Raises:
        TypeError: If ``dtype`` is not a floating-point dtype.
    """
    _check_float_dtype(dtype, "euler_grid_poses")
    return next(_iter_grid_chunks(config, config.num_poses, dtype, device))


def _check_range(value: float, name: str) -> None:
    if isinstance(value, bool) or not (math.isfinite(value) and value >= 0):
        raise ValueError(f"random_slice_poses(): '{name}' must be finite and >= 0, got {value!r}")


def random_slice_poses(
    n: int,
    generator: torch.Generator,
    angle_range_deg: float = 90.0,
    tz_range_mm: float = 40.0,
    rotation: RotationSampling = "euler",
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Tensor:
    """Random slice poses ``R``, ``t = R (0, 0, Tz)``, drawn from ``generator`` only.

    ``Tz`` is uniform in ``[-tz_range_mm, +tz_range_mm]``. With ``rotation="euler"`` the three
    extrinsic xyz Euler angles are independent and uniform in ``[-angle_range_deg,
    +angle_range_deg]`` (the paper's validation poses); with ``rotation="uniform"`` the rotations
    are uniform on SO(3) (Haar measure: normalised 4D Gaussian quaternions) and
    ``angle_range_deg`` is not used. Samples are drawn in float64 on the generator's device, so a
    seed gives the same poses for every ``dtype``; the global RNG is never touched.

    Args:
        n: Number of poses, >= 0.
        generator: The source of randomness (required).
        angle_range_deg: Half-width of each Euler angle's range in degrees, >= 0 ("euler" only).
        tz_range_mm: Half-width of the offset range along the slice normal in mm, >= 0.
        rotation: ``"euler"`` or ``"uniform"``.
        dtype: Floating-point dtype of the result.
        device: Device of the result; ``None`` for the generator's device.

    Returns:
        (n, 6) pose vectors mapping the slice plane to the canonical frame.

    Raises:
        TypeError: If ``generator`` is not a ``torch.Generator`` or ``dtype`` not floating-point.
        ValueError: If ``n`` is not a non-negative integer, a range is negative or not finite, or
            ``rotation`` is not one of ``"euler"``, ``"uniform"``.
    """
    if not isinstance(generator, torch.Generator):
        raise TypeError(
            "random_slice_poses(): 'generator' must be a torch.Generator, got "
            f"{type(generator).__name__}"
        )
    if not (is_integer(n) and n >= 0):
        raise ValueError(f"random_slice_poses(): 'n' must be a non-negative integer, got {n!r}")
    _check_range(angle_range_deg, "angle_range_deg")
    _check_range(tz_range_mm, "tz_range_mm")
    if rotation not in _ROTATION_SAMPLINGS:
        raise ValueError(
            f"random_slice_poses(): 'rotation' must be one of {_ROTATION_SAMPLINGS}, "
            f"got {rotation!r}"
        )
    _check_float_dtype(dtype, "random_slice_poses")

    def uniform(shape: tuple[int, ...], half_width: float) -> Tensor:
        u = torch.rand(shape, generator=generator, dtype=torch.float64, device=generator.device)
        return (2.0 * u - 1.0) * half_width

    if rotation == "euler":
        poses = euler_to_poses(
            uniform((n, 3), math.radians(angle_range_deg)), uniform((n,), tz_range_mm)
        )
    else:
        quat = torch.randn(
            (n, 4), generator=generator, dtype=torch.float64, device=generator.device
        )
        translation = quat_to_matrix(quat)[..., :, 2] * uniform((n,), tz_range_mm).unsqueeze(-1)
        poses = torch.cat([quat_to_rotvec(quat), translation], dim=-1)
    return poses.to(device=device, dtype=dtype)


PoseDraw = Literal["euler", "uniform", "euler-grid"]
"""Where candidate slice poses come from: :func:`random_slice_poses` with Euler angles in
+-90 deg (``"euler"``, the paper's validation poses) or uniform rotations (``"uniform"``), or a
random subset of the paper's Euler grid (``"euler-grid"``, :func:`euler_grid_poses`)."""

POSE_DRAWS: tuple[str, ...] = get_args(PoseDraw)

VALIDATION_BRAIN_FRACTION = 0.1
"""Default empty-slice rule of validation slices: at least 10 % of the pixels in the brain."""


def draw_pose_candidates(kind: PoseDraw, n: int, generator: torch.Generator) -> Tensor:
    """``n`` candidate slice poses of one :data:`PoseDraw` kind, drawn from ``generator`` only.

    Args:
        kind: ``"euler"``, ``"uniform"`` (offsets in +-40 mm along the normal) or
            ``"euler-grid"`` (``n`` distinct grid poses in random order).
        n: Number of poses, >= 0.
        generator: The source of randomness.

    Returns:
        (n, 6) float64 poses (rad, mm), slice plane -> canonical frame, on the CPU.

    Raises:
        ValueError: If ``kind`` is not one of :data:`POSE_DRAWS`.
    """
    if kind == "euler-grid":
        grid = euler_grid_poses()
        return grid[torch.randperm(len(grid), generator=generator)[:n]]
    if kind not in POSE_DRAWS:
        raise ValueError(
            f"draw_pose_candidates(): 'kind' must be one of {', '.join(POSE_DRAWS)}, got {kind!r}"
        )
    return random_slice_poses(n, generator, rotation=kind)


def draw_validation_poses(
    volume: CanonicalVolume,
    num_slices: int,
    config: SliceConfig,
    generator: torch.Generator,
    rotation: PoseDraw = "euler",
    min_brain_fraction: float = VALIDATION_BRAIN_FRACTION,
    max_rounds: int = 100,
) -> Tensor:
    """Random poses of a volume whose slices show enough brain (validation and test slices).

    Candidates are drawn by :func:`draw_pose_candidates` in rounds of ``2 * num_slices``, keeping
    those whose slice has at least ``min_brain_fraction`` of its pixels in the brain mask
    (:func:`~svr.sampling.slicer.brain_fraction`), in the order drawn.

    Args:
        volume: The canonical volume (poses are in its frame).
        num_slices: How many poses to return, >= 1.
        config: Slice size and spacing (as the slices will be cut).
        generator: The random stream (advanced by the draws).
        rotation: A :data:`PoseDraw` kind: ``"euler"`` (the paper's +-90 deg box),
            ``"uniform"`` (on SO(3)) or ``"euler-grid"``.
        min_brain_fraction: The empty-slice rule, in [0, 1).
        max_rounds: Rounds of drawing before giving up, >= 1.

    Returns:
        (num_slices, 6) float64 poses (rad, mm), slice plane -> canonical frame, on the volume's
        device.

    Raises:
        ValueError: Naming the argument, for a bad ``num_slices``, ``min_brain_fraction`` or
            ``max_rounds``; or if ``max_rounds`` rounds give fewer than ``num_slices`` poses
            (the message starts with ``"only <count> of <num_slices> slices"``).
    """
    if not (is_integer(num_slices) and num_slices >= 1):
        raise ValueError(f"draw_validation_poses(): 'num_slices' must be >= 1, got {num_slices!r}")
    if not 0 <= min_brain_fraction < 1:
        raise ValueError(
            "draw_validation_poses(): 'min_brain_fraction' must be in [0, 1), "
            f"got {min_brain_fraction!r}"
        )
    if max_rounds < 1:
        raise ValueError(f"draw_validation_poses(): 'max_rounds' must be >= 1, got {max_rounds}")
    device = volume.image.data.device
    mask = Image(volume.mask.to(volume.image.data.dtype), volume.image.affine)
    kept: list[Tensor] = []
    count = 0
    for _ in range(max_rounds):
        poses = draw_pose_candidates(rotation, 2 * num_slices, generator)
        keep = brain_fraction(mask, poses.to(device), config).cpu() >= min_brain_fraction
        kept.append(poses[keep])
        count += int(keep.sum())
        if count >= num_slices:
            return torch.cat(kept)[:num_slices].to(device)
    raise ValueError(
        f"only {count} of {num_slices} slices reach a brain fraction of {min_brain_fraction} "
        f"in {max_rounds} rounds; lower it or check the mask"
    )


def pose_labels(
    poses: Tensor,
    representation: Representation,
    anchor_half_size_mm: float = ANCHOR_HALF_SIZE_MM,
) -> Tensor:
    """Training labels of poses in the representation a loss works on.

    The registry entry's ``encode`` (:data:`svr.representation_registry.REPRESENTATIONS`, where
    the label layouts are listed); its ``decode`` maps each label back to the pose.

    Args:
        poses: (..., 6) pose vectors (rad, mm) mapping the slice plane to the canonical frame.
        representation: A registered name (:data:`svr.representation_registry.REPRESENTATIONS`),
            e.g. ``"se3"`` (the pose vectors themselves, the same tensor), ``"quat_translation"``,
            ``"anchor_points"`` or ``"rotation6d_translation"``.
        anchor_half_size_mm: Half-size of the anchor-point triangle in mm, > 0 (``"anchor_points"``
            only).

    Returns:
        (..., D) labels, ``D = REPRESENTATIONS[representation].size`` (6, 7, 9 and 9 for the names
        above), in the dtype and device of ``poses``.

    Raises:
        ValueError: If ``representation`` is not registered (the message lists the valid names),
            ``poses`` does not have shape (..., 6) or ``anchor_half_size_mm`` is not > 0.
        TypeError: If ``poses`` is not a floating-point tensor.
    """
    entry = get_representation(representation, "pose_labels()")
    if not (isinstance(poses, Tensor) and poses.is_floating_point()):
        raise TypeError("pose_labels(): 'poses' must be a floating-point torch.Tensor (..., 6)")
    if poses.dim() == 0 or poses.shape[-1] != 6:
        raise ValueError(
            f"pose_labels(): 'poses' must have shape (..., 6), got {tuple(poses.shape)}"
        )
    return entry.encode(poses, anchor_half_size_mm)
