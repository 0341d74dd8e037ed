"""Mirror symmetry of the canonical frame: reflection planes, mirror twins of slice poses, orbits.

A fetal brain is nearly symmetric about its mid-sagittal plane. If a volume ``V`` satisfies
``V(M x) = V(x)`` for the reflection ``M`` about a plane ``{x : n . x = d}`` of the canonical
frame (``M x = (I - 2 n n^T) x + 2 d n``), the slice cut at pose ``T = (R, t)`` and the slice cut
at its *mirror twin*

    ``twin(T) = M o T o D = ((I - 2 n n^T) R D, (I - 2 n n^T) t + 2 d n)``,

with ``D = diag(1, 1, -1)`` acting on the slice frame, are the same image: ``D`` fixes every
in-plane point ``(u, v, 0)`` (and maps the through-plane PSF, which is even, onto itself), so
the twin samples ``V`` at ``M T (u, v, w)`` wherever ``T`` samples it at ``T (u, v, w)``. Both
``M`` and ``D`` are improper, so the twin is a proper rigid transform again, and ``twin(twin(T))
= T``. The default plane is the canonical frame's sagittal plane ``x = 0``
(``n = (1, 0, 0)``, ``d = 0``), where ``twin(T) = (S R D, S t)`` with ``S = diag(-1, 1, 1)``.

A single slice cannot tell ``T`` from ``twin(T)``; the *orbit* of a pose under a set of planes is
``{T} + {twin_p(T) for each plane p}`` (identity first). A stack of slices, ordered along its
normal, can tell them apart (:mod:`svr.reconstruction.cnn_init`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from svr.errors import ConfigFieldError
from svr.geometry._validation import check_tensor
from svr.geometry.se3 import se3_to_vector, vector_to_se3
from svr.validation import check_number, check_number_tuple

SLICE_FLIP = (1.0, 1.0, -1.0)
"""``D``: the diagonal of the slice-frame reflection that fixes the slice plane."""


@dataclass(frozen=True)
class ReflectionPlane:
    """A plane ``{x : normal . x = offset_mm}`` of the canonical frame, as a mirror symmetry.

    Attributes:
        normal: Unit normal ``(n_x, n_y, n_z)`` in the canonical frame (normalised on
            construction; its sign is irrelevant and fixed so that its largest component is > 0).
        offset_mm: Signed distance of the plane from the canonical origin along ``normal``, mm.

    Raises:
        ConfigFieldError: If ``normal`` is not three finite numbers of non-zero length, or
            ``offset_mm`` is not finite.
    """

    normal: tuple[float, float, float] = (1.0, 0.0, 0.0)
    offset_mm: float = 0.0

    def __post_init__(self) -> None:
        owner = "ReflectionPlane"
        n = check_number_tuple(owner, "normal", self.normal, length=3, allow_list=True)
        check_number(owner, "offset_mm", self.offset_mm)
        length = math.sqrt(sum(float(v) ** 2 for v in n))
        if length < 1e-12:
            raise ConfigFieldError(owner, "normal", "non-zero", self.normal)
        unit = [float(v) / length for v in n]
        sign = 1.0 if max(unit, key=abs) > 0 else -1.0
        object.__setattr__(self, "normal", tuple(sign * v for v in unit))
        object.__setattr__(self, "offset_mm", sign * float(self.offset_mm))

    def matrix(
        self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
    ) -> Tensor:
        """The (4, 4) improper isometry ``M``: the reflection about the plane (canonical frame)."""
        n = torch.tensor(self.normal, dtype=dtype, device=device)
        m = torch.eye(4, dtype=dtype, device=device)
        m[:3, :3] -= 2.0 * torch.outer(n, n)
        m[:3, 3] = 2.0 * self.offset_mm * n
        return m

    def to_dict(self) -> dict[str, Any]:
        """JSON form: ``{"normal": [nx, ny, nz], "offset_mm": d}``."""
        return {"normal": list(self.normal), "offset_mm": self.offset_mm}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ReflectionPlane:
        """Plane from :meth:`to_dict`'s form.

        Raises:
            ValueError: If ``d`` is not such a dict (the problem named).
        """
        if not isinstance(d, dict) or set(d) != {"normal", "offset_mm"}:
            raise ValueError(
                "ReflectionPlane.from_dict(): expected a dict with keys 'normal' and "
                f"'offset_mm', got {d!r}"
            )
        return cls(tuple(d["normal"]), d["offset_mm"])

    def angle_to_deg(self, other: ReflectionPlane) -> float:
        """Angle between the two planes' normals, degrees in ``[0, 90]``."""
        dot = abs(sum(a * b for a, b in zip(self.normal, other.normal, strict=True)))
        return math.degrees(math.acos(min(1.0, dot)))


SAGITTAL = ReflectionPlane((1.0, 0.0, 0.0), 0.0)
"""The canonical frame's mid-sagittal plane ``x = 0`` (RAS: left-right mirror)."""


def mirror_twin_matrix(transforms: Tensor, plane: ReflectionPlane = SAGITTAL) -> Tensor:
    """Mirror twins ``M o T o D`` of slice-to-canonical transforms given as matrices.

    Args:
        transforms: (..., 4, 4) rigid slice-plane -> canonical transforms (mm).
        plane: The canonical-frame reflection plane ``M``.

    Returns:
        (..., 4, 4) the twins, rigid again (det +1), in the dtype and device of ``transforms``.
    """
    check_tensor(transforms, "mirror_twin_matrix", "transforms", (4, 4))
    m = plane.matrix(transforms.dtype, transforms.device)
    flip = torch.tensor((*SLICE_FLIP, 1.0), dtype=transforms.dtype, device=transforms.device)
    return (m @ transforms) * flip


def mirror_twin(poses: Tensor, plane: ReflectionPlane = SAGITTAL) -> Tensor:
    """Mirror twins of slice poses: the poses that cut the same slice from a symmetric volume.

    Args:
        poses: (..., 6) pose vectors ``(r, t)`` (rad, mm), slice plane -> canonical frame.
        plane: The canonical-frame reflection plane.

    Returns:
        (..., 6) the twins' pose vectors (rotation angle in ``[0, pi]``), in the dtype and device
        of ``poses``. ``mirror_twin(mirror_twin(p))`` is ``p`` up to the rotation vector's
        ``2 pi`` ambiguity at angle ``pi``.
    """
    check_tensor(poses, "mirror_twin", "poses", (6,))
    return se3_to_vector(mirror_twin_matrix(vector_to_se3(poses), plane))


def check_planes(planes: Sequence[ReflectionPlane], func: str) -> tuple[ReflectionPlane, ...]:
    """``planes`` as a tuple after checking that each is a :class:`ReflectionPlane`."""
    planes = tuple(planes)
    for p in planes:
        if not isinstance(p, ReflectionPlane):
            raise ValueError(
                f"{func}(): 'planes' must hold ReflectionPlane objects, got {type(p).__name__}"
            )
    return planes


def orbit_poses(poses: Tensor, planes: Sequence[ReflectionPlane] = (SAGITTAL,)) -> Tensor:
    """The symmetry orbit of each pose: itself, then its twin under each plane.

    Args:
        poses: (..., 6) pose vectors (rad, mm), slice plane -> canonical frame.
        planes: The reflection planes (may be empty: the orbit is the pose alone).

    Returns:
        (K, ..., 6) with ``K = 1 + len(planes)``; entry 0 is ``poses`` itself.
    """
    check_tensor(poses, "orbit_poses", "poses", (6,))
    planes = check_planes(planes, "orbit_poses")
    return torch.stack([poses, *(mirror_twin(poses, p) for p in planes)])


def orbit_matrices(transforms: Tensor, planes: Sequence[ReflectionPlane] = (SAGITTAL,)) -> Tensor:
    """:func:`orbit_poses` for (..., 4, 4) matrices: (K, ..., 4, 4), entry 0 the input."""
    check_tensor(transforms, "orbit_matrices", "transforms", (4, 4))
    planes = check_planes(planes, "orbit_matrices")
    return torch.stack([transforms, *(mirror_twin_matrix(transforms, p) for p in planes)])
