"""A canonical output levelled on the brain's own mid-sagittal plane.

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
"""

from __future__ import annotations

import dataclasses
import logging
import math

import torch
from torch import Tensor

from svr.geometry import so3_exp
from svr.image import Image
from svr.reconstruction.result import ReconstructionResult, relabelled
from svr.sampling.mirror_planes import measure_reflection_plane
from svr.sampling.volume import CanonicalVolume

__all__ = ["MIDPLANE_MAX_TILT_DEG", "MIDPLANE_MIN_CORRELATION", "level_to_midplane"]

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


def level_to_midplane(
    result: ReconstructionResult,
    min_correlation: float = MIDPLANE_MIN_CORRELATION,
    max_tilt_deg: float = MIDPLANE_MAX_TILT_DEG,
) -> tuple[ReconstructionResult, float | None]:
    """The canonical result turned so that the brain's mirror plane is ``x = 0`` (see above).

    Args:
        result: A canonical reconstruction.
        min_correlation: See :data:`MIDPLANE_MIN_CORRELATION`.
        max_tilt_deg: See :data:`MIDPLANE_MAX_TILT_DEG`.

    Returns:
        The result (relabelled, or as it was), and the tilt (degrees) it was levelled by, or
        ``None`` where it was kept.

    Raises:
        ValueError: If the result is not in the canonical frame.
    """
    if result.slices.frame != "canonical":
        raise ValueError("level_to_midplane(): 'result' must be in the canonical frame")
    inside = (result.mask.data > 0.5) & (result.volume.data > 0)
    if int(inside.sum()) < 100:
        return result, None
    data = result.volume.data.cpu().float() * inside.cpu()
    scale = float(data[inside.cpu()].quantile(0.99)) or 1.0
    volume = CanonicalVolume(
        image=Image(data / scale, result.volume.affine.cpu()),
        mask=inside.cpu(),
        centre_mm=torch.zeros(3, dtype=torch.float64),
        intensity_scale=scale,
    )
    fit = measure_reflection_plane(volume)
    normal = torch.tensor(fit.plane.normal, dtype=torch.float64)
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(normal[0])))))
    log.info(
        "mid-sagittal plane: %.1f deg from x = 0, %.1f mm off (mirror correlation %.3f, %.3f at "
        "x = 0)",
        tilt,
        fit.plane.offset_mm,
        fit.correlation,
        fit.sagittal_correlation,
    )
    if fit.correlation < min_correlation or tilt > max_tilt_deg:
        log.info("mid-sagittal plane: not clear or not near; the frame is kept")
        return result, None
    moved = relabelled(result, _levelling(normal, fit.plane.offset_mm))
    return dataclasses.replace(moved, midplane_tilt_deg=tilt), tilt
