"""The slice sampler: 2D slices cut from a 3D volume at given poses, with an optional slice PSF.

Slice geometry (``docs/conventions.md``): a slice of ``size = (H, W)`` pixels with in-plane spacing
``s`` mm has pixel ``(a, b)`` at slice-plane coordinates ``u = (a - (H - 1) / 2) s`` (array axis 0)
and ``v = (b - (W - 1) / 2) s`` (array axis 1), ``w = 0``; its pose ``(R, t)`` maps ``(u, v, w)`` to
the volume's world frame (canonical space for a :class:`~svr.sampling.volume.CanonicalVolume`). The
slice normal is ``R[:, 2]``.

Point-spread function: a slice of thickness ``T`` mm integrates the volume along its normal with a
Gaussian of FWHM ``T`` (sigma = T / 2.3548), as the peers model it; the in-plane PSF (optional) is a
Gaussian of sigma = 1.2067 s / 2.3548 (NeSVoR's). Both are integrated by Gauss-Hermite quadrature:
the slice is the weighted sum of plain samples at a few offsets. Sampling goes through
:func:`svr.image.sample_grid` with :func:`svr.image.world_to_grid` folded into each slice's
origin and pixel steps (trilinear ``grid_sample``, zero outside the volume).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from svr.errors import ConfigFieldError
from svr.geometry import vector_to_se3
from svr.geometry._validation import check_tensor
from svr.image import Image, sample_channels, sample_grid, world_to_grid
from svr.validation import check_bool, check_choice, check_int, check_int_tuple, check_number

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
IN_PLANE_PSF_FWHM = 1.2067  # in-plane PSF FWHM in units of the pixel spacing (NeSVoR)
_POINTS_PER_CHUNK = 1 << 20


@dataclass(frozen=True)
class SliceConfig:
    """How slices are cut.

    Attributes:
        size: (H, W) pixels.
        spacing_mm: In-plane pixel spacing in mm.
        thickness_mm: Slice thickness (FWHM of the through-plane Gaussian PSF) in mm, or ``None``
            for an infinitely thin slice (plain interpolation).
        in_plane_psf: Also integrate over the in-plane Gaussian PSF.
        psf_samples: Gauss-Hermite nodes per PSF axis (odd, >= 1).
        mode: ``"bilinear"`` (trilinear) or ``"nearest"`` interpolation.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    size: tuple[int, int] = (128, 128)
    spacing_mm: float = 1.0
    thickness_mm: float | None = None
    in_plane_psf: bool = False
    psf_samples: int = 5
    mode: str = "bilinear"

    def __post_init__(self) -> None:
        owner = "SliceConfig"
        size = check_int_tuple(owner, "size", self.size, length=2, minimum=1, allow_list=True)
        check_number(owner, "spacing_mm", self.spacing_mm, gt=0)
        check_number(owner, "thickness_mm", self.thickness_mm, gt=0, allow_none=True)
        check_bool(owner, "in_plane_psf", self.in_plane_psf)
        check_int(owner, "psf_samples", self.psf_samples, minimum=1)
        if self.psf_samples % 2 == 0:
            raise ConfigFieldError(owner, "psf_samples", "an odd integer >= 1", self.psf_samples)
        check_choice(owner, "mode", self.mode, ("bilinear", "nearest"))
        object.__setattr__(self, "size", size)


def pose_matrices(poses: Tensor, func: str = "pose_matrices") -> Tensor:
    """Poses as (B, 4, 4) or (B, 3, 4) matrices; (B, 6) vectors are converted.

    Raises:
        ValueError: If ``poses`` is not (B, 6), (B, 4, 4) or (B, 3, 4).
    """
    if poses.dim() == 2:
        return vector_to_se3(check_tensor(poses, func, "poses", (6,)))
    if poses.dim() == 3 and tuple(poses.shape[1:]) in ((4, 4), (3, 4)):
        return check_tensor(poses, func, "poses", tuple(poses.shape[1:]))
    raise ValueError(
        f"{func}(): 'poses' must have shape (B, 6), (B, 4, 4) or (B, 3, 4), "
        f"got {tuple(poses.shape)}"
    )


def _slice_frames(
    poses: Tensor, size: tuple[int, int], spacing_mm: float, offset_mm: tuple[float, float, float]
) -> tuple[Tensor, Tensor, Tensor]:
    """World position of pixel (0, 0) and the steps to the next pixel along axes 0 and 1.

    Returns:
        Three (B, 3) float64 tensors: origin, step along axis 0 (u), step along axis 1 (v), in mm.
    """
    T = pose_matrices(poses, "slice_points").to(torch.float64)
    h, w = size
    R = T[:, :3, :3]
    step_u, step_v = R[:, :, 0] * spacing_mm, R[:, :, 1] * spacing_mm
    origin = (
        T[:, :3, 3]
        + offset_mm[2] * R[:, :, 2]
        + step_u * (offset_mm[0] / spacing_mm - (h - 1) / 2)
        + step_v * (offset_mm[1] / spacing_mm - (w - 1) / 2)
    )
    return origin, step_u, step_v


def _plane(
    origin: Tensor, step_u: Tensor, step_v: Tensor, size: tuple[int, int], dtype: torch.dtype
) -> Tensor:
    """(B, H, W, 3) points ``origin + a step_u + b step_v`` for pixels (a, b), in ``dtype``."""
    kw: dict[str, Any] = {"dtype": dtype, "device": origin.device}
    a = torch.arange(size[0], **kw)[None, :, None, None]
    b = torch.arange(size[1], **kw)[None, None, :, None]
    return (
        origin.to(dtype)[:, None, None, :]
        + a * step_u.to(dtype)[:, None, None, :]
        + b * step_v.to(dtype)[:, None, None, :]
    )


def slice_points(
    poses: Tensor,
    size: tuple[int, int],
    spacing_mm: float,
    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
    dtype: torch.dtype | None = None,
) -> Tensor:
    """World points of every pixel of every slice.

    Args:
        poses: (B, 6), (B, 4, 4) or (B, 3, 4) slice poses.
        size: (H, W) pixels.
        spacing_mm: In-plane spacing in mm.
        offset_mm: Shift ``(du, dv, dw)`` in slice coordinates added to every pixel (mm).
        dtype: dtype of the result (default: the poses'); the per-slice axes are computed in
            float64 first.

    Returns:
        (B, H, W, 3) world points in mm.
    """
    return _plane(*_slice_frames(poses, size, spacing_mm, offset_mm), size, dtype or poses.dtype)


def _gauss_hermite(n: int, sigma: float) -> list[tuple[float, float]]:
    """Offsets and weights (summing to 1) integrating against a Gaussian of std ``sigma``."""
    nodes, weights = np.polynomial.hermite_e.hermegauss(n)
    weights = weights / weights.sum()
    return [(sigma * float(x), float(wt)) for x, wt in zip(nodes, weights, strict=True)]


def psf_offsets(config: SliceConfig) -> list[tuple[tuple[float, float, float], float]]:
    """Quadrature offsets ``(du, dv, dw)`` in mm and weights (summing to 1) of the slice PSF."""
    n = config.psf_samples
    through = (
        [(0.0, 1.0)]
        if config.thickness_mm is None
        else _gauss_hermite(n, config.thickness_mm * FWHM_TO_SIGMA)
    )
    in_plane = (
        [(0.0, 1.0)]
        if not config.in_plane_psf
        else _gauss_hermite(n, IN_PLANE_PSF_FWHM * config.spacing_mm * FWHM_TO_SIGMA)
    )
    return [
        ((du, dv, dw), wu * wv * ww)
        for du, wu in in_plane
        for dv, wv in in_plane
        for dw, ww in through
    ]


def sample_slices(
    volume: Image,
    poses: Tensor,
    config: SliceConfig = SliceConfig(),
    displacement_mm: Tensor | None = None,
) -> Tensor:
    """Cut slices from a volume at the given poses.

    Args:
        volume: The volume (its world frame is the poses' target frame).
        poses: (B, 6), (B, 4, 4) or (B, 3, 4) slice poses, on the volume's device.
        config: Size, spacing, PSF and interpolation.
        displacement_mm: ``None``, or a (3, c, c, c) world-frame displacement field in mm on a
            control grid spanning the volume's voxel grid corner to corner (array order; see
            :mod:`svr.sampling.deform`): each point ``x`` reads the volume at ``x + d(x)``, with
            ``d`` trilinear between control points and read on the slice's centre plane (one
            ``d`` per pixel for all PSF samples).

    Returns:
        (B, H, W) slices in the dtype of ``volume.data``. A float16 volume is sampled with a
        float16 grid (``grid_sample`` needs one dtype), which places points to about 2**-11 of
        the volume's half-extent (~0.03 voxel across 128 voxels): fine for training batches on
        CUDA, not for reconstruction.
    """
    T = pose_matrices(poses, "sample_slices").to(torch.float64)
    to_grid = world_to_grid(volume).to(T.device)
    h, w = config.size
    out = volume.data.new_zeros((T.shape[0], h, w))
    grid_displacement = None
    if displacement_mm is not None:
        if displacement_mm.dim() != 4 or displacement_mm.shape[0] != 3:
            raise ValueError(
                "sample_slices(): 'displacement_mm' must have shape (3, c, c, c), "
                f"got {tuple(displacement_mm.shape)}"
            )
        # mm in the world frame -> grid_sample units, once per control point.
        flat = to_grid[:, :3] @ displacement_mm.to(to_grid).reshape(3, -1)
        grid_displacement = flat.reshape(displacement_mm.shape).to(volume.data.dtype)
    # Chunks of ~1M points keep each grid in cache between being built and being sampled.
    chunk = max(1, _POINTS_PER_CHUNK // (h * w))
    for start in range(0, T.shape[0], chunk):
        part = T[start : start + chunk]

        def plane(offset: tuple[float, float, float], part: Tensor = part) -> Tensor:
            # Each slice's origin and pixel steps are mapped to grid coordinates once (B x 3).
            origin, step_u, step_v = _slice_frames(part, config.size, config.spacing_mm, offset)
            return _plane(
                origin @ to_grid[:, :3].T + to_grid[:, 3],
                step_u @ to_grid[:, :3].T,
                step_v @ to_grid[:, :3].T,
                config.size,
                volume.data.dtype,
            )

        shift = None
        if grid_displacement is not None:
            # Read at the slice's centre plane and used for every PSF sample: the field is
            # smooth over tens of mm, the PSF spans a few.
            shift = sample_channels(grid_displacement, plane((0.0, 0.0, 0.0))).movedim(0, -1)
        for offset, weight in psf_offsets(config):
            grid = plane(offset)
            if shift is not None:
                grid = grid + shift
            out[start : start + chunk].add_(sample_grid(volume, grid, config.mode), alpha=weight)
    return out


def brain_fraction(mask: Image, poses: Tensor, config: SliceConfig = SliceConfig()) -> Tensor:
    """Fraction of each slice's pixels that fall inside a brain mask (thin slices, nearest).

    Args:
        mask: The mask as an image (1 inside).
        poses: (B, ...) slice poses.
        config: Size and spacing of the slices (PSF and mode are ignored).

    Returns:
        (B,) fractions in [0, 1].
    """
    thin = SliceConfig(size=config.size, spacing_mm=config.spacing_mm, mode="nearest")
    return (sample_slices(mask, poses, thin) > 0.5).flatten(1).float().mean(1)
