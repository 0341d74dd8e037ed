"""The brain's own mirror plane: a canonical output levelled onto it, any output checked by it.

The left-right mirror symmetry of a fetal brain is a landmark the reconstruction itself carries,
whatever its contrast or anatomy: its mid-sagittal plane is the canonical plane ``x = 0``. A
canonical frame estimated from the stacks (the stack-pose network) or from an atlas of another
brain can be rolled or yawed by several degrees; :func:`level_to_midplane` measures the plane
about which the reconstructed brain is most nearly mirror-symmetric
(:func:`svr.sampling.mirror_planes.measure_reflection_plane`) and turns the output so that the
plane is ``x = 0``: roll and yaw are corrected, pitch (a turn about the plane's normal) is left to
the frame's estimate. Nothing is resampled; the volume is relabelled
(:func:`~svr.reconstruction.result.relabelled`). A brain that is not clearly symmetric (its best
mirror correlation below ``min_correlation``) or a plane farther than ``max_tilt_deg`` from
``x = 0`` (another optimum: the estimate is not in reach) leaves the frame as it is.

The same measurement is evidence for the verdict (:mod:`svr.reconstruction.verdict`): where no
clear plane lies near ``x = 0``, the plane is searched in every orientation
(:func:`svr.sampling.mirror_planes.search_reflection_plane`) and the result records its
correlation and its angle from ``x = 0`` (``mirror_correlation``, ``mirror_tilt_deg``). A clear
plane far from ``x = 0`` says that the canonical frame is wrong; no clear plane anywhere says that
the volume is not a recognisable brain. A scanner-frame output is searched in every orientation
(:func:`measure_symmetry`).
"""

from __future__ import annotations

import dataclasses
import logging
import math

import torch
from torch import Tensor

from svr.geometry import so3_exp
from svr.geometry.mirror import SAGITTAL
from svr.image import Image
from svr.reconstruction.result import ReconstructionResult, relabelled
from svr.sampling.mirror_planes import (
    PlaneFit,
    measure_reflection_plane,
    search_reflection_plane,
)
from svr.sampling.volume import CanonicalVolume

__all__ = [
    "MIDPLANE_MAX_TILT_DEG",
    "MIDPLANE_MIN_CORRELATION",
    "level_to_midplane",
    "measure_symmetry",
    "mirror_plane_line",
    "symmetry_volume",
]

log = logging.getLogger(__name__)

MIDPLANE_MIN_CORRELATION = 0.4
"""The mirror correlation below which a brain is not clearly symmetric: the frame is kept."""

MIDPLANE_MAX_TILT_DEG = 20.0
"""The largest tilt (degrees) of the mirror plane from ``x = 0`` that the frame is turned by."""


def _levelling(normal: Tensor, offset_mm: float) -> Tensor:
    """(4, 4) the rigid transform that takes the plane ``normal . x = offset_mm`` to ``x = 0``.

    The smallest turn that takes ``normal`` (unit, its x component > 0) onto the x axis, then a
    shift along x.
    """
    axis = torch.linalg.cross(normal, torch.tensor([1.0, 0.0, 0.0], dtype=normal.dtype))
    angle = math.acos(max(-1.0, min(1.0, float(normal[0]))))
    transform = torch.eye(4, dtype=normal.dtype)
    if float(axis.norm()) > 1e-12:
        transform[:3, :3] = so3_exp(axis / axis.norm() * angle)
    transform[0, 3] = -offset_mm
    return transform


def symmetry_volume(volume: Image, inside: Tensor) -> CanonicalVolume | None:
    """A volume's brain, as the mirror-plane fits take it.

    Args:
        volume: The reconstructed volume (any frame).
        inside: Bool mask of its brain voxels, the volume's shape.

    Returns:
        The masked volume scaled to its 99th percentile, in the volume's own frame, or ``None``
        for fewer than 100 brain voxels.
    """
    inside = inside.cpu()
    if int(inside.sum()) < 100:
        return None
    data = volume.data.cpu().float() * inside
    scale = float(data[inside].quantile(0.99)) or 1.0
    return CanonicalVolume(
        image=Image(data / scale, volume.affine.cpu()),
        mask=inside,
        centre_mm=torch.zeros(3, dtype=torch.float64),
        intensity_scale=scale,
    )


def _brain(result: ReconstructionResult) -> CanonicalVolume | None:
    """The result's brain: its mask where the volume is positive (:func:`symmetry_volume`)."""
    return symmetry_volume(result.volume, (result.mask.data > 0.5) & (result.volume.data > 0))


def _tilt_deg(fit: PlaneFit) -> float:
    """The angle (degrees) of the fitted plane from ``x = 0``."""
    return fit.plane.angle_to_deg(SAGITTAL)


def measure_symmetry(result: ReconstructionResult) -> ReconstructionResult:
    """The result with its brain's best mirror plane in any orientation recorded.

    For an output in any frame (the scanner's, typically): ``mirror_correlation`` is set from
    :func:`~svr.sampling.mirror_planes.search_reflection_plane` (``mirror_tilt_deg`` only for a
    canonical output). Nothing is moved.

    Args:
        result: A reconstruction.

    Returns:
        The result with ``mirror_correlation`` (and ``mirror_tilt_deg``) set, or as it was for
        a volume of fewer than 100 brain voxels.
    """
    volume = _brain(result)
    if volume is None:
        return result
    fit = search_reflection_plane(volume)
    log.info("mirror plane (any orientation): correlation %.3f", fit.correlation)
    canonical = result.slices.frame == "canonical"
    return dataclasses.replace(
        result,
        mirror_correlation=fit.correlation,
        mirror_tilt_deg=_tilt_deg(fit) if canonical else None,
    )


def level_to_midplane(
    result: ReconstructionResult,
    min_correlation: float = MIDPLANE_MIN_CORRELATION,
    max_tilt_deg: float = MIDPLANE_MAX_TILT_DEG,
) -> tuple[ReconstructionResult, float | None]:
    """The canonical result turned so that the brain's mirror plane is ``x = 0`` (see above).

    Where no plane of correlation ``min_correlation`` or more lies within ``max_tilt_deg`` of
    ``x = 0``, the plane is searched in every orientation and the result records the better of
    the two fits (``mirror_correlation``, ``mirror_tilt_deg``); the frame is then kept.

    Args:
        result: A canonical reconstruction.
        min_correlation: See :data:`MIDPLANE_MIN_CORRELATION`.
        max_tilt_deg: See :data:`MIDPLANE_MAX_TILT_DEG`.

    Returns:
        The result (relabelled, or as it was but for the recorded plane), and the tilt (degrees)
        it was levelled by, or ``None`` where it was kept.

    Raises:
        ValueError: If the result is not in the canonical frame.
    """
    if result.slices.frame != "canonical":
        raise ValueError("level_to_midplane(): 'result' must be in the canonical frame")
    volume = _brain(result)
    if volume is None:
        return result, None
    fit = measure_reflection_plane(volume)
    tilt = _tilt_deg(fit)
    log.info(
        "mid-sagittal plane: %.1f deg from x = 0, %.1f mm off (mirror correlation %.3f, %.3f at "
        "x = 0)",
        tilt,
        fit.plane.offset_mm,
        fit.correlation,
        fit.sagittal_correlation,
    )
    if fit.correlation < min_correlation or tilt > max_tilt_deg:
        anywhere = search_reflection_plane(volume)
        if anywhere.correlation > fit.correlation:
            fit, tilt = anywhere, _tilt_deg(anywhere)
        log.info(
            "mid-sagittal plane: not clear or not near; the frame is kept (best plane in any "
            "orientation: correlation %.3f, %.1f deg from x = 0)",
            fit.correlation,
            tilt,
        )
        return dataclasses.replace(
            result, mirror_correlation=fit.correlation, mirror_tilt_deg=tilt
        ), None
    moved = relabelled(
        result, _levelling(torch.tensor(fit.plane.normal, dtype=torch.float64), fit.plane.offset_mm)
    )
    levelled = dataclasses.replace(
        moved, midplane_tilt_deg=tilt, mirror_correlation=fit.correlation, mirror_tilt_deg=tilt
    )
    return levelled, tilt


def mirror_plane_line(result: ReconstructionResult) -> str | None:
    """One line on the brain's mirror plane for a log or QA page, or ``None`` if not measured.

    For example ``"mirror plane: correlation 0.78, x = 0 (levelled by 2 deg)"`` (a canonical
    output levelled onto it), ``"mirror plane: correlation 0.17, 82 deg from x = 0"`` (one whose
    frame was kept) or ``"mirror plane: correlation 0.15"`` (a scanner-frame output).
    """
    if result.mirror_correlation is None:
        return None
    line = f"mirror plane: correlation {result.mirror_correlation:.2f}"
    if result.midplane_tilt_deg is not None:
        return f"{line}, x = 0 (levelled by {result.midplane_tilt_deg:.0f} deg)"
    tilt = result.mirror_tilt_deg
    return line if tilt is None else f"{line}, {tilt:.0f} deg from x = 0"
