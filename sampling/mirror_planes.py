"""Measuring the mirror symmetry of training volumes (``svr train --symmetry``).

A volume's reflection plane is found by registering the volume to its own mirror image: the plane
``{x : n . x = d}`` of the canonical frame that maximises the correlation of ``V(x)`` with
``V(M x)`` (``M`` the reflection about the plane) over the brain, searched with Powell's method
from the canonical sagittal plane ``x = 0`` over the normal's two tilts and the offset.

``resolve_symmetry`` turns the ``--symmetry`` choice into the planes the training loss uses:
``"none"`` (no planes), ``"sagittal"`` (the plane ``x = 0``), or ``"auto"`` (measure every
volume; if all are symmetric, correlation >= ``threshold``, use their mean plane; otherwise none).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np
import torch
from scipy.optimize import minimize
from torch import Tensor

from svr.geometry.mirror import SAGITTAL, ReflectionPlane
from svr.image import sample_world, voxel_to_world
from svr.sampling.volume import CanonicalVolume

log = logging.getLogger(__name__)

SymmetryMode = Literal["none", "sagittal", "auto"]
SYMMETRY_MODES: tuple[SymmetryMode, ...] = ("none", "sagittal", "auto")

SYMMETRY_THRESHOLD = 0.85
"""Correlation with its own mirror image above which ``"auto"`` calls a volume symmetric.

Measured over brain voxels of the masked volume only (no background), which is stricter than a
whole-image correlation: the sb-fidon2021 atlas scores 0.91-1.00 (GA27 lowest)."""


@dataclass(frozen=True)
class PlaneFit:
    """A volume's measured reflection plane.

    Attributes:
        plane: The best plane (canonical frame).
        correlation: Correlation of ``V`` and ``V o M`` over the brain at ``plane``.
        sagittal_correlation: The same at the canonical sagittal plane ``x = 0``.
    """

    plane: ReflectionPlane
    correlation: float
    sagittal_correlation: float

    def to_dict(self) -> dict[str, Any]:
        """JSON form (plane, correlations, and the tilt from ``x = 0`` in degrees)."""
        return {
            **self.plane.to_dict(),
            "correlation": round(self.correlation, 6),
            "sagittal_correlation": round(self.sagittal_correlation, 6),
            "tilt_deg": round(self.plane.angle_to_deg(SAGITTAL), 3),
        }


def _brain_points(volume: CanonicalVolume, max_points: int, seed: int) -> Tensor:
    """(P, 3) float64 canonical points (mm) of brain voxels, a fixed random subset."""
    idx = torch.nonzero(volume.mask.cpu()).to(torch.float64)
    if idx.shape[0] > max_points:
        g = torch.Generator().manual_seed(seed)
        idx = idx[torch.randperm(idx.shape[0], generator=g)[:max_points]]
    return voxel_to_world(volume.image.affine.cpu(), idx)


def _plane(params: np.ndarray) -> ReflectionPlane:
    a, b, d = (float(v) for v in params)
    return ReflectionPlane((1.0, math.tan(a), math.tan(b)), d)


def mirror_correlation(volume: CanonicalVolume, plane: ReflectionPlane, points: Tensor) -> float:
    """Correlation of ``V(x)`` and ``V(M x)`` over the points ``x`` and their mirror images.

    Taken over both ``x`` and ``M x`` (the brain and its mirror image), so that a brain that is
    lopsided about the plane is penalised on both sides.

    Args:
        volume: The canonical volume.
        plane: The reflection plane ``M``.
        points: (P, 3) canonical points (mm).

    Returns:
        The Pearson correlation (1 for a volume symmetric about ``plane``).
    """
    image = volume.image.to("cpu")
    m = plane.matrix(torch.float64)
    a = sample_world(image, points.float()).double()
    b = sample_world(image, (points @ m[:3, :3].T + m[:3, 3]).float()).double()
    a, b = torch.cat([a, b]), torch.cat([b, a])
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / ((a.square().sum() * b.square().sum()).sqrt() + 1e-12))


def _powell(
    volume: CanonicalVolume,
    points: Tensor,
    plane_of: Callable[[np.ndarray], ReflectionPlane],
    bounds: tuple[float, float],
    ftol: float,
    maxfev: int,
) -> tuple[ReflectionPlane, float]:
    """The plane ``plane_of(params)`` of highest mirror correlation, by Powell's method from 0.

    ``params`` are two tilts (radians, within ``bounds[0]``) and an offset (mm, within
    ``bounds[1]``); returns the plane and its correlation.
    """
    tilt, offset = bounds
    result = minimize(
        lambda params: -mirror_correlation(volume, plane_of(params), points),
        np.zeros(3),
        method="Powell",
        bounds=[(-tilt, tilt), (-tilt, tilt), (-offset, offset)],
        options={"xtol": 1e-3, "ftol": ftol, "maxfev": maxfev},
    )
    return plane_of(result.x), -float(result.fun)


def measure_reflection_plane(
    volume: CanonicalVolume, max_points: int = 20000, seed: int = 0
) -> PlaneFit:
    """The plane about which a volume is most nearly mirror-symmetric.

    Args:
        volume: A canonical volume (brain-masked intensities).
        max_points: Brain voxels used (a fixed random subset), >= 100.
        seed: Seed of the subset.

    Returns:
        The fitted plane and its correlation, beside the correlation at ``x = 0``.

    Raises:
        ValueError: If ``max_points`` < 100.
    """
    if max_points < 100:
        raise ValueError(
            f"measure_reflection_plane(): 'max_points' must be >= 100, got {max_points}"
        )
    points = _brain_points(volume, max_points, seed)
    sagittal = mirror_correlation(volume, SAGITTAL, points)
    best, corr = _powell(volume, points, _plane, (0.5, 20.0), ftol=1e-6, maxfev=400)
    if corr < sagittal:
        best, corr = SAGITTAL, sagittal
    return PlaneFit(best, corr, sagittal)


def _hemisphere(count: int) -> np.ndarray:
    """(count, 3) unit normals spread evenly over the half sphere z >= 0 (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    z = 1.0 - i / count
    r = np.sqrt(1.0 - z**2)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * np.arange(count)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _tilted(normal: np.ndarray, centre: np.ndarray, params: np.ndarray) -> ReflectionPlane:
    """The plane through ``centre`` + ``params[2]`` mm along ``normal``, tilted by two angles."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    n = normal + math.tan(params[0]) * u + math.tan(params[1]) * v
    n /= np.linalg.norm(n)
    return ReflectionPlane(
        cast("tuple[float, float, float]", tuple(float(x) for x in n)),
        float(n @ centre) + float(params[2]),
    )


def search_reflection_plane(
    volume: CanonicalVolume,
    normals: int = 100,
    refine: int = 4,
    max_points: int = 4000,
    seed: int = 0,
) -> PlaneFit:
    """The plane about which a volume is most nearly mirror-symmetric, in any orientation.

    :func:`measure_reflection_plane` searches near ``x = 0`` only; this scores the planes through
    the brain's centroid with ``normals`` normals spread evenly over a half sphere (about
    ``180 / sqrt(normals)`` degrees apart), then refines the ``refine`` best with Powell's method
    over two tilts (up to 0.3 rad) and the offset (up to 8 mm). A brain in any frame has a plane
    of high correlation (its mid-sagittal plane); a volume with none is not a recognisable
    brain.

    Args:
        volume: A volume (brain-masked intensities; its frame need not be canonical).
        normals: Normals of the coarse search, >= 1.
        refine: Best coarse planes refined, in [1, normals].
        max_points: Brain voxels used (a fixed random subset), >= 100.
        seed: Seed of the subset.

    Returns:
        The best plane and its correlation, beside the correlation at ``x = 0``.

    Raises:
        ValueError: If ``normals``, ``refine`` or ``max_points`` is out of range.
    """
    if normals < 1 or not 1 <= refine <= normals:
        raise ValueError(
            "search_reflection_plane(): 'normals' must be >= 1 and 'refine' in [1, normals], "
            f"got {normals} and {refine}"
        )
    if max_points < 100:
        raise ValueError(
            f"search_reflection_plane(): 'max_points' must be >= 100, got {max_points}"
        )
    points = _brain_points(volume, max_points, seed)
    centre = points.mean(dim=0).numpy()
    sagittal = mirror_correlation(volume, SAGITTAL, points)
    coarse = [
        (mirror_correlation(volume, _tilted(n, centre, np.zeros(3)), points), n)
        for n in _hemisphere(normals)
    ]
    coarse.sort(key=lambda scored: -scored[0])
    best, corr = SAGITTAL, sagittal
    for _, normal in coarse[:refine]:
        plane, fitted = _powell(
            volume,
            points,
            functools.partial(_tilted, normal, centre),
            (0.3, 8.0),
            ftol=1e-5,
            maxfev=200,
        )
        if fitted > corr:
            best, corr = plane, fitted
    return PlaneFit(best, corr, sagittal)


def mean_plane(planes: Sequence[ReflectionPlane]) -> ReflectionPlane:
    """Mean of planes with nearby normals (normals and offsets averaged)."""
    if not planes:
        raise ValueError("mean_plane(): 'planes' is empty")
    n = np.mean([p.normal for p in planes], axis=0)
    d = float(np.mean([p.offset_mm for p in planes]))
    return ReflectionPlane(cast("tuple[float, float, float]", tuple(float(v) for v in n)), d)


def resolve_symmetry(
    mode: SymmetryMode,
    volumes: Sequence[CanonicalVolume],
    names: Sequence[str] | None = None,
    threshold: float = SYMMETRY_THRESHOLD,
) -> tuple[tuple[ReflectionPlane, ...], dict[str, Any]]:
    """The reflection planes a training run's loss uses, and a report of how they were chosen.

    Args:
        mode: ``"none"``, ``"sagittal"`` or ``"auto"`` (module docstring).
        volumes: The training volumes (measured for ``"auto"`` only).
        names: Their names for the report (default ``volume 0``, ...).
        threshold: Correlation from which ``"auto"`` calls a volume symmetric, in (0, 1].

    Returns:
        ``(planes, report)``: the planes (empty or one), and a JSON-serialisable report with the
        mode, the planes and, for ``"auto"``, each volume's :meth:`PlaneFit.to_dict`.

    Raises:
        ValueError: For an unknown mode, a bad threshold or a names/volumes length mismatch.
    """
    if mode not in SYMMETRY_MODES:
        raise ValueError(
            f"resolve_symmetry(): 'mode' must be one of {', '.join(SYMMETRY_MODES)}, got {mode!r}"
        )
    if not 0 < threshold <= 1:
        raise ValueError(f"resolve_symmetry(): 'threshold' must be in (0, 1], got {threshold}")
    names = [f"volume {i}" for i in range(len(volumes))] if names is None else list(names)
    if len(names) != len(volumes):
        raise ValueError(
            f"resolve_symmetry(): {len(names)} names for {len(volumes)} volumes; they must pair up"
        )
    report: dict[str, Any] = {"mode": mode}
    if mode == "none":
        planes: tuple[ReflectionPlane, ...] = ()
    elif mode == "sagittal":
        planes = (SAGITTAL,)
    else:
        fits = [measure_reflection_plane(v) for v in volumes]
        report["threshold"] = threshold
        report["volumes"] = {n: f.to_dict() for n, f in zip(names, fits, strict=True)}
        symmetric = all(f.correlation >= threshold for f in fits)
        planes = (mean_plane([f.plane for f in fits]),) if symmetric and fits else ()
        for n, f in zip(names, fits, strict=True):
            log.info(
                "symmetry of %s: r = %.4f about a plane %.2f deg from x = 0, offset %.2f mm",
                n,
                f.correlation,
                f.plane.angle_to_deg(SAGITTAL),
                f.plane.offset_mm,
            )
    report["planes"] = [p.to_dict() for p in planes]
    return planes, report
