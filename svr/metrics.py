"""Pose-error metrics for evaluating slice-pose predictions.

Conventions: poses are (..., 6) vectors ``(r, t)`` (rad, mm) as everywhere in the project; the
error of a prediction is ``e = Log_id(pred^-1 o target) = (e_r, e_t)``
(:func:`svr.geometry.se3_error`).

* Rotation error: the angle ``|e_r|`` of the relative rotation ``R_pred^T R``, in ``[0, pi]`` rad.
* Translation error: ``|t - t_pred|`` in mm (the same as ``|e_t|``; frame-independent).
* Geodesic distance: ``sqrt(e^T Z e)``, with the default Z ``sqrt(theta^2 + |dt|^2 / L^2)``; in
  "radian-equivalents" (1 means 1 rad, or L = 30 mm).
* Euler-angle errors: per-axis ``|wrap(angle_pred - angle_true)|`` in degrees for the extrinsic
  ``"xyz"`` angles of :func:`svr.geometry.matrix_to_euler` (what a reader of Euler-grid results
  expects; unstable near gimbal lock, where the geodesic rotation error is the one to trust).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from svr.geometry._validation import check_tensor
from svr.geometry.mirror import SAGITTAL, ReflectionPlane, check_planes, orbit_poses
from svr.geometry.se3 import se3_error
from svr.geometry.so3 import matrix_to_euler, so3_exp
from svr.losses.se3 import quadratic_form, resolve_weights


def _check_poses(pred: Tensor, target: Tensor, func: str) -> None:
    check_tensor(pred, func, "pred", (6,))
    check_tensor(target, func, "target", (6,))


def rotation_error_rad(pred: Tensor, target: Tensor) -> Tensor:
    """Angle of ``R_pred^T R_target`` in rad, in ``[0, pi]``.

    Args:
        pred: (..., 6) predicted poses.
        target: (..., 6) true poses, broadcastable with ``pred``.

    Returns:
        (...) angles in rad.
    """
    _check_poses(pred, target, "rotation_error_rad")
    return se3_error(pred, target)[..., :3].norm(dim=-1)


def translation_error_mm(pred: Tensor, target: Tensor) -> Tensor:
    """Euclidean distance ``|t_target - t_pred|`` in mm.

    Args:
        pred: (..., 6) predicted poses.
        target: (..., 6) true poses, broadcastable with ``pred``.

    Returns:
        (...) distances in mm.
    """
    _check_poses(pred, target, "translation_error_mm")
    return (target[..., 3:] - pred[..., 3:]).norm(dim=-1)


def geodesic_distance(pred: Tensor, target: Tensor, weights: Tensor | None = None) -> Tensor:
    """Left-invariant geodesic distance ``sqrt(e^T Z e)`` between poses.

    Args:
        pred: (..., 6) predicted poses.
        target: (..., 6) true poses, broadcastable with ``pred``.
        weights: Z as in :func:`svr.losses.se3_geodesic_loss` (``None``: the default, giving
            ``sqrt(theta^2 + |dt|^2 / (30 mm)^2)``).

    Returns:
        (...) distances.
    """
    _check_poses(pred, target, "geodesic_distance")
    e = se3_error(pred, target)
    z = resolve_weights(weights, e, "geodesic_distance")
    return quadratic_form(e, z.to(device=e.device, dtype=e.dtype)).sqrt()


def euler_angle_errors_deg(pred: Tensor, target: Tensor, convention: str = "xyz") -> Tensor:
    """Per-axis absolute differences of Euler angles, wrapped to ``[0, 180]`` degrees.

    Args:
        pred: (..., 6) predicted poses.
        target: (..., 6) true poses, broadcastable with ``pred``.
        convention: Euler sequence, as :func:`svr.geometry.matrix_to_euler`.

    Returns:
        (..., 3) errors in degrees, in the order of ``convention``.
    """
    _check_poses(pred, target, "euler_angle_errors_deg")
    diff = matrix_to_euler(so3_exp(pred[..., :3]), convention) - matrix_to_euler(
        so3_exp(target[..., :3]), convention
    )
    wrapped = torch.remainder(diff + math.pi, 2 * math.pi) - math.pi
    return wrapped.abs().rad2deg()


def pose_errors(pred: Tensor, target: Tensor, weights: Tensor | None = None) -> dict[str, Tensor]:
    """All pose metrics at once, as (...) tensors keyed by name.

    Keys: ``rotation_deg`` (geodesic rotation error in degrees), ``translation_mm``,
    ``geodesic`` (:func:`geodesic_distance`), ``euler_x_deg``, ``euler_y_deg``, ``euler_z_deg``.

    Args:
        pred: (..., 6) predicted poses.
        target: (..., 6) true poses, broadcastable with ``pred``.
        weights: Z for the geodesic distance (``None``: the default).

    Returns:
        A dict of (...) tensors.
    """
    euler = euler_angle_errors_deg(pred, target)
    return {
        "rotation_deg": rotation_error_rad(pred, target).rad2deg(),
        "translation_mm": translation_error_mm(pred, target),
        "geodesic": geodesic_distance(pred, target, weights),
        "euler_x_deg": euler[..., 0],
        "euler_y_deg": euler[..., 1],
        "euler_z_deg": euler[..., 2],
    }


def nearest_orbit_member(
    pred: Tensor,
    target: Tensor,
    planes: Sequence[ReflectionPlane] = (SAGITTAL,),
    distance: Callable[[Tensor, Tensor], Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    """The member of each target's mirror orbit nearest to its prediction (errors up to the twin).

    Args:
        pred: (..., 6) predicted pose vectors (rad, mm).
        target: (..., 6) true pose vectors, the same shape.
        planes: Canonical-frame mirror planes (:mod:`svr.geometry.mirror`); empty: the target.
        distance: ``(pred, target) -> (...)`` between pose vectors; default
            :func:`geodesic_distance` with the default Z.

    Returns:
        ``(member, index)``: (..., 6) the nearest orbit member of each target and the (...)
        int64 index of it (0: the target itself, ``k``: its twin about ``planes[k - 1]``).
    """
    _check_poses(pred, target, "nearest_orbit_member")
    orbit = orbit_poses(target, check_planes(planes, "nearest_orbit_member"))
    measure = geodesic_distance if distance is None else distance
    index = measure(pred.expand_as(orbit), orbit).argmin(0)
    member = orbit.gather(0, index[None, ..., None].expand(1, *target.shape))[0]
    return member, index
