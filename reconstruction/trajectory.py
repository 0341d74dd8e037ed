"""Slice poses as samples of one smooth head motion: a robust trajectory per interleaved packet.

Within an interleaved packet (slices ``k = p, p + P, p + 2P, ...`` of a stack, acquired in that
order) the slices are acquired one after another, so their poses sample one head motion in time.
:func:`fit_trajectory` fits that motion per packet, robustly, and returns each slice's pose on
the fitted trajectory, how far its own pose is from it and whether it is an outlier.

The fit, per packet:

1. *Transport* (optional): with the slices' ``nominal`` poses (where they would be without
   motion, e.g. :attr:`SliceSet.scanner_poses`), each pose ``T_i`` becomes ``U_i = T_i o N_i^-1
   o G``, the pose the packet's nominal centre plane ``G`` (robust mean of the ``N_i``) had at
   slice ``i``'s time. ``U`` depends on the head motion alone: the step of the slices along the
   stack normal drops out. Without nominal poses, ``U_i = T_i``.
2. *Chart*: ``y_i = Log_id(Ref^-1 o U_i)`` (:func:`svr.geometry.se3_to_vector`: rotation vector,
   then translation; the pose-error chart of the conventions) about ``Ref``, the robust mean
   (:func:`svr.geometry.averaging.robust_mean_pose`) of the packet's known ``U_i``.
3. *Smoothing*: each of the 6 components is a penalised cubic B-spline (P-spline, Eilers & Marx
   1996) of time: uniform knots every ``knot_spacing`` time units over the packet's time span and
   the penalty ``smoothness * sum (differences of order m of the coefficients)^2 / h^(2m - 1)``
   (``h`` the knot spacing), which approximates ``smoothness * integral (f^(m)(t))^2 dt``.
   Order ``m = 1`` (default) is the prior of a random walk, whose steps are independent (severe
   fetal motion can turn the head by ten degrees and more from one slice of a packet to the
   next, with no smooth velocity to exploit). Order 2 is the
   cubic smoothing spline (smooth velocity). For order 1, ``smoothness`` is roughly the ratio of
   a pose estimate's error variance to the motion's variance per time unit, per component. The
   fit reproduces constant motion exactly (order 2: linear motion too), works for any times
   (uneven ones and gaps included) and solves one small linear system per packet, all packets
   batched together.
4. *Robustness*: iteratively reweighted least squares on each slice's residual, the rotation
   angle (degrees) and the displacement of its centre (mm) between its pose and the fitted one,
   scaled by ``outlier_deg`` and ``outlier_mm`` (``r = max(angle / outlier_deg, shift /
   outlier_mm)``): first Huber weights ``min(1, 1 / r)`` (a convex start that a few gross outliers
   cannot capture), then Tukey's biweight ``(1 - r^2)^2`` for ``r < 1``, else 0, so that outliers
   stop pulling the fit altogether. A slice is an outlier if ``r > 1`` after the last fit.
5. *Back*: ``T_hat_i = Ref o Exp(f(t_i)) o G^-1 o N_i``.

Slices marked unknown (``known``) are not fitted and get the trajectory's pose at their time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
from torch import Tensor

from svr.geometry import rotation_angle, se3_compose, se3_inverse, se3_to_vector, vector_to_se3
from svr.geometry.averaging import robust_mean_pose
from svr.reconstruction.acquisition import packet_key
from svr.reconstruction.slices import SliceSet
from svr.validation import check_int, check_number

__all__ = [
    "SMOOTHNESS_GRID",
    "TrajectoryConfig",
    "TrajectoryFit",
    "cross_validated_trajectory",
    "fit_slice_trajectory",
    "fit_trajectory",
    "leave_one_out_deg",
    "packet_times",
]

SMOOTHNESS_GRID = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
"""Smoothness values :func:`cross_validated_trajectory` chooses from (0.05, the default, is for
known noise; these span from motion that follows every estimate to nearly constant packets)."""

LOO_CAP_DEG = 30.0
"""A left-out slice's prediction error counts at most this (degrees): a slice the refiner sent
far away must not decide the smoothness alone."""

_WEIGHT_FLOOR = 1e-9  # a known slice's least weight, so that every system stays solvable
_RIDGE = 1e-12  # relative ridge on the normal equations (coinciding times)


@dataclass(frozen=True)
class TrajectoryConfig:
    """How the motion of a packet's slices is fitted (:func:`fit_trajectory`).

    Attributes:
        knot_spacing: Time between the knots of the cubic B-spline (time units: slices in
            acquisition order by default), > 0.
        smoothness: Weight of the roughness penalty, >= 0 (module docstring). 0 leaves only the
            knots to smooth; the default is the best of a sweep on ``sb32-severe`` with 5 to 15
            degrees of error per slice.
        outlier_deg: A slice whose rotation is farther than this from the fit is an outlier; also
            the scale of the robust weights (degrees), > 0.
        outlier_mm: Likewise for the displacement of its centre (mm), > 0.
        irls_iterations: Reweighting steps after the first, unweighted fit: the first half with
            Huber weights, the rest with Tukey's biweight, >= 0.
        min_slices: A packet with fewer known slices gets no trajectory (see
            :func:`fit_trajectory`), >= 2.
        penalty_order: 1 (random walk: penalise the velocity) or 2 (smoothing spline: penalise
            the acceleration). Without nominal poses (:func:`fit_trajectory`), the slices' step
            along the stack normal is a linear trend in time, which order 1 shrinks: use order 2
            there.
    """

    knot_spacing: float = 1.0
    smoothness: float = 0.05
    outlier_deg: float = 20.0
    outlier_mm: float = 10.0
    irls_iterations: int = 10
    min_slices: int = 4
    penalty_order: int = 1

    def __post_init__(self) -> None:
        owner = "TrajectoryConfig"
        check_number(owner, "knot_spacing", self.knot_spacing, gt=0)
        check_number(owner, "smoothness", self.smoothness, ge=0)
        check_number(owner, "outlier_deg", self.outlier_deg, gt=0, le=180)
        check_number(owner, "outlier_mm", self.outlier_mm, gt=0)
        check_int(owner, "irls_iterations", self.irls_iterations, minimum=0)
        check_int(owner, "min_slices", self.min_slices, minimum=2)
        check_int(owner, "penalty_order", self.penalty_order, minimum=1, maximum=2)


@dataclass(frozen=True)
class TrajectoryFit:
    """The fitted trajectories of N slices in Q packets.

    Attributes:
        poses: (N, 4, 4) float64 each slice's pose on its packet's trajectory, in the frame of the
            input poses (see :func:`fit_trajectory` for packets without a trajectory).
        residual_deg: (N,) float64 rotation angle between each slice's input and fitted pose
            (degrees); NaN for unknown slices.
        residual_mm: (N,) float64 distance between their centres (mm); NaN for unknown slices.
        outlier: (N,) bool residual beyond ``outlier_deg`` or ``outlier_mm`` after the fit.
        weights: (N,) float64 the slices' robust weights in the last fit, in [0, 1] (0 for
            unknown slices and packets without a trajectory).
        packets: (Q,) int64 the packet ids, ascending.
        packet_index: (N,) int64 each slice's packet, an index into ``packets``.
        references: (Q, 4, 4) float64 each packet's reference ``Ref`` (module docstring; the
            identity where no slice is known).
        known_slices: (Q,) int64 known slices per packet.
        fitted: (Q,) bool whether a trajectory was fitted (at least ``min_slices`` known).
    """

    poses: Tensor
    residual_deg: Tensor
    residual_mm: Tensor
    outlier: Tensor
    weights: Tensor
    packets: Tensor
    packet_index: Tensor
    references: Tensor
    known_slices: Tensor
    fitted: Tensor


def packet_times(
    slices: SliceSet, packets: int, times: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Each slice's interleaved packet and its time within the packet.

    Packet ``p`` of a stack holds ``k = p, p + packets, p + 2 packets, ...`` (``k`` the slice's
    index in its file), acquired in that order (:func:`svr.reconstruction.acquisition.packet_key`).

    Args:
        slices: The slices (``stack_ids``, ``slice_indices``).
        packets: Interleaved packets per stack, >= 1 (1: sequential acquisition).
        times: (N,) acquisition times (any unit, e.g. seconds), or ``None`` for the slice's
            position in its packet's acquisition order, ``k // packets`` (slices dropped from the
            set leave gaps in time).

    Returns:
        ``(packet, time)``: (N,) int64 packet ids (one per stack and packet) and (N,) float64
        times, on the slices' device.

    Raises:
        ValueError: Naming the argument, if ``packets`` < 1 or ``times`` is not (N,) finite.
    """
    if not (isinstance(packets, int) and not isinstance(packets, bool) and packets >= 1):
        raise ValueError(f"packet_times(): 'packets' must be an int >= 1, got {packets!r}")
    packet = packet_key(slices, packets)
    if times is None:
        return packet, (slices.slice_indices // packets).to(torch.float64)
    if tuple(times.shape) != (len(slices),) or not bool(times.isfinite().all()):
        raise ValueError(
            f"packet_times(): 'times' must be ({len(slices)},) finite, got {tuple(times.shape)}"
        )
    return packet, times.to(device=packet.device, dtype=torch.float64)


def _check(
    poses: Tensor, packet: Tensor, time: Tensor, known: Tensor | None, nominal: Tensor | None
) -> None:
    """Raise ValueError naming the first argument of :func:`fit_trajectory` that is malformed."""
    n = len(poses) if isinstance(poses, Tensor) and poses.dim() == 3 else -1
    for name, value, shape in (
        ("poses", poses, (n, 4, 4)),
        ("packet", packet, (n,)),
        ("time", time, (n,)),
        ("known", known, (n,)),
        ("nominal", nominal, (n, 4, 4)),
    ):
        if value is not None and (not isinstance(value, Tensor) or tuple(value.shape) != shape):
            got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            raise ValueError(f"fit_trajectory(): '{name}' must have shape {shape}, got {got}")
    if packet.dtype.is_floating_point or packet.dtype == torch.bool:
        raise ValueError(f"fit_trajectory(): 'packet' must be integer, got {packet.dtype}")
    if known is not None and known.dtype != torch.bool:
        raise ValueError(f"fit_trajectory(): 'known' must be bool, got {known.dtype}")
    for name, value in (("poses", poses), ("time", time), ("nominal", nominal)):
        if value is not None and not (value.is_floating_point() and bool(value.isfinite().all())):
            raise ValueError(f"fit_trajectory(): '{name}' must be finite floats")


def _padded(index: Tensor, groups: int) -> tuple[Tensor, Tensor]:
    """Each item's (group, slot) in a (groups, M) padded layout of items grouped by ``index``."""
    order = torch.argsort(index, stable=True)
    counts = torch.bincount(index, minlength=groups)
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.empty_like(index)
    slot[order] = torch.arange(len(index), device=index.device) - starts[index[order]]
    return slot, counts


def _group_mean(poses: Tensor, index: Tensor, weight: Tensor, groups: int) -> Tensor:
    """(groups, 4, 4) robust mean pose of each group's items of positive weight (else its first)."""
    slot, counts = _padded(index, groups)
    size = max(int(counts.max()), 1) if len(index) else 1
    stacked = torch.eye(4, dtype=torch.float64, device=poses.device).repeat(groups, size, 1, 1)
    w = torch.zeros(groups, size, dtype=torch.float64, device=poses.device)
    stacked[index, slot], w[index, slot] = poses, weight
    w[:, 0] = torch.where(w.sum(1) > 0, w[:, 0], torch.ones_like(w[:, 0]))  # no weight: item 0
    return robust_mean_pose(stacked, w)


def _basis(time: Tensor, index: Tensor, groups: int, spacing: float) -> tuple[Tensor, Tensor]:
    """Uniform cubic B-spline basis per group: (N, K) values and (groups, K) used columns."""
    big = torch.finfo(torch.float64).max
    start = torch.full((groups,), big, dtype=torch.float64, device=time.device)
    end = torch.full((groups,), -big, dtype=torch.float64, device=time.device)
    start = start.scatter_reduce(0, index, time, "amin")
    end = end.scatter_reduce(0, index, time, "amax")
    segments = torch.ceil((end - start) / spacing).clamp_min(1).to(torch.int64)
    x = (time - start[index]) / spacing
    seg = torch.minimum(x.floor().to(torch.int64), segments[index] - 1).clamp_min(0)
    u = x - seg
    values = (
        torch.stack(
            [(1 - u) ** 3, 3 * u**3 - 6 * u**2 + 4, -3 * u**3 + 3 * u**2 + 3 * u + 1, u**3], dim=1
        )
        / 6
    )
    k = int(segments.max()) + 3 if groups else 3
    out = time.new_zeros(len(time), k)
    out.scatter_(1, seg[:, None] + torch.arange(4, device=time.device), values)
    used = torch.arange(k, device=time.device) < segments[:, None] + 3
    return out, used


def _solve(
    basis: Tensor,
    used: Tensor,
    index: Tensor,
    weight: Tensor,
    y: Tensor,
    penalty: float,
    order: int,
) -> Tensor:
    """(N, 6) weighted P-spline fit of ``y`` per group, evaluated at every item."""
    groups, k = used.shape
    wb = weight[:, None] * basis
    gram = y.new_zeros(groups, k, k).index_add_(0, index, wb[:, :, None] * basis[:, None, :])
    rhs = y.new_zeros(groups, k, 6).index_add_(0, index, wb[:, :, None] * y[:, None, :])
    diff = torch.eye(k, dtype=y.dtype, device=y.device)
    for _ in range(order):
        diff = diff[1:] - diff[:-1]  # (k - order, k) differences of the coefficients
    live = used[:, order:].to(y.dtype)  # differences within a group's own columns
    gram = gram + penalty * (diff.T[None] * live[:, None, :]) @ diff
    scale = gram.diagonal(dim1=1, dim2=2).amax(1).clamp_min(1.0)
    pad = (~used).to(y.dtype) + _RIDGE * scale[:, None]
    gram = gram + torch.diag_embed(pad)
    coefficients = torch.linalg.solve(gram, rhs)
    return (basis[:, :, None] * coefficients[index]).sum(1)


def fit_trajectory(
    poses: Tensor,
    packet: Tensor,
    time: Tensor,
    config: TrajectoryConfig | None = None,
    *,
    known: Tensor | None = None,
    nominal: Tensor | None = None,
) -> TrajectoryFit:
    """Fit a smooth rigid motion of time to each packet's slice poses, robustly (module docstring).

    Packets are fitted independently. A packet with fewer than ``config.min_slices`` known
    slices gets no trajectory: its known slices keep their poses (residual 0, never outliers)
    and its unknown slices take the robust mean of the known ones (transported to their own
    nominal place when ``nominal`` is given). A packet with no known slice is returned
    unchanged. Every computation is in float64 on the poses' device; no Python loop runs over
    slices or packets.

    Args:
        poses: (N, 4, 4) slice poses (slice-plane mm -> any one frame).
        packet: (N,) integer packet id of each slice (:func:`packet_times`).
        time: (N,) float acquisition time of each slice (any unit; ``config.knot_spacing`` is in
            it).
        config: The fit's settings; default :class:`TrajectoryConfig()`.
        known: (N,) bool slices whose input pose is an estimate (default all); the others are
            not fitted and get the trajectory's pose at their time.
        nominal: (N, 4, 4) poses the slices would have without motion, in any one frame (e.g.
            the scanner's, :attr:`SliceSet.scanner_poses`), or ``None`` to fit the poses as they
            are (module docstring, step 1).

    Returns:
        The fitted poses, residuals, outlier flags and per-packet information.

    Raises:
        ValueError: Naming the argument, for a wrong shape or dtype, or non-finite values.
    """
    config = TrajectoryConfig() if config is None else config
    _check(poses, packet, time, known, nominal)
    moved = _transported(poses, packet, time, nominal)
    known = torch.ones(len(poses), dtype=torch.bool) if known is None else known
    return _fit_transported(moved, known.to(moved.T.device), config)


class _Transported(NamedTuple):
    """Poses transported to their packets' centre planes (module docstring, step 1).

    ``T`` the poses, ``U`` transported, ``carry`` (``U_i -> T_i``), ``t`` the times, ``packets``
    the ids and ``packet_index`` each slice's packet (an index into ``packets``).
    """

    T: Tensor
    U: Tensor
    carry: Tensor
    t: Tensor
    packets: Tensor
    packet_index: Tensor


def _transported(
    poses: Tensor, packet: Tensor, time: Tensor, nominal: Tensor | None
) -> _Transported:
    """Step 1 of the module docstring, in float64 on the poses' device."""
    T = poses.to(torch.float64)
    device = T.device
    N = torch.eye(4, dtype=torch.float64, device=device).expand_as(T)
    N = N if nominal is None else nominal.to(device=device, dtype=torch.float64)
    packets, index = torch.unique(packet.to(device), return_inverse=True)
    ones = torch.ones(len(T), dtype=torch.float64, device=device)
    G = _group_mean(N, index, ones, len(packets))  # nominal centre plane of each packet
    carry = se3_compose(se3_inverse(G)[index], N)  # G^-1 o N_i: U_i -> T_i
    U = se3_compose(T, se3_inverse(carry))
    t = time.to(device=device, dtype=torch.float64)
    return _Transported(T, U, carry, t, packets, index)


def _fit_transported(
    moved: _Transported, known: Tensor, config: TrajectoryConfig, ref: Tensor | None = None
) -> TrajectoryFit:
    """Steps 2-5 of the module docstring.

    ``ref``: the packets' references, or ``None`` for the robust mean of each packet's known
    transported poses.
    """
    T, U, carry, t, packets, index = moved
    groups = len(packets)
    count = torch.bincount(index[known], minlength=groups)
    fitted = count >= config.min_slices
    if ref is None:
        ref = _group_mean(U, index, known.to(torch.float64), groups)
    y = se3_to_vector(se3_compose(se3_inverse(ref)[index], U))

    basis, used = _basis(t, index, groups, float(config.knot_spacing))
    order = config.penalty_order
    penalty = float(config.smoothness) / float(config.knot_spacing) ** (2 * order - 1)
    fit_known = known & fitted[index]
    weight = fit_known.to(torch.float64)
    thresholds = (math.radians(config.outlier_deg), float(config.outlier_mm))
    for step in range(config.irls_iterations + 1):
        chart = _solve(
            basis, used, index, weight.clamp_min(_WEIGHT_FLOOR) * fit_known, y, penalty, order
        )
        out = se3_compose(se3_compose(ref[index], vector_to_se3(chart)), carry)
        angle = rotation_angle(out, T)
        shift = (out[:, :3, 3] - T[:, :3, 3]).norm(dim=-1)
        r = torch.maximum(angle / thresholds[0], shift / thresholds[1])
        if step == config.irls_iterations:
            break
        if step < config.irls_iterations // 2:
            weight = torch.clamp(1.0 / r.clamp_min(1e-300), max=1.0)  # Huber
        else:
            weight = (1.0 - r**2).clamp_min(0.0) ** 2  # Tukey's biweight
        weight = weight * fit_known

    # Packets without a trajectory: known slices stay, unknown ones take the known ones' mean.
    fallback = se3_compose(ref[index], carry)
    out = torch.where(
        fitted[index, None, None], out, torch.where(known[:, None, None], T, fallback)
    )
    out = torch.where((count > 0)[index, None, None], out, T)
    nan, zero = torch.full_like(angle, math.nan), torch.zeros_like(angle)
    return TrajectoryFit(
        poses=out,
        residual_deg=torch.where(known, torch.where(fit_known, angle.rad2deg(), zero), nan),
        residual_mm=torch.where(known, torch.where(fit_known, shift, zero), nan),
        outlier=fit_known & (r > 1.0),
        weights=weight * fit_known,
        packets=packets,
        packet_index=index,
        references=torch.where((count > 0)[:, None, None], ref, torch.eye(4).to(ref)),
        known_slices=count,
        fitted=fitted,
    )


def fit_slice_trajectory(
    slices: SliceSet,
    packets: int,
    config: TrajectoryConfig | None = None,
    *,
    known: Tensor | None = None,
    times: Tensor | None = None,
) -> TrajectoryFit:
    """:func:`fit_trajectory` of a slice set's poses, per interleaved packet of each stack.

    The slices' scanner poses are the nominal ones (the poses' frame may be any).

    Args:
        slices: The slices with their current poses.
        packets: Interleaved packets per stack (:func:`packet_times`).
        config: The fit's settings; default :class:`TrajectoryConfig()`.
        known: (N,) bool slices whose pose is an estimate (default all).
        times: (N,) acquisition times, or ``None`` for the order within the packet.

    Returns:
        The fit; ``slices.with_poses(fit.poses)`` places every slice on its trajectory.
    """
    packet, time = packet_times(slices, packets, times)
    return fit_trajectory(
        slices.poses, packet, time, config, known=known, nominal=slices.scanner_poses
    )


def leave_one_out_deg(
    slices: SliceSet,
    packets: int,
    grid: tuple[float, ...] = SMOOTHNESS_GRID,
    config: TrajectoryConfig | None = None,
) -> Tensor:
    """Each slice's pose predicted by its packet's other slices, at each smoothness of ``grid``.

    Each slice is left out in turn (the slices of one time in every packet at once) and its pose
    predicted by its packet's trajectory through the others (:func:`fit_slice_trajectory`, with
    the transport and each packet's chart centre computed once, from all its slices, and shared
    by every fit: leaving one slice out would move the centre by a fraction of a degree).

    Args:
        slices: The slices with their current poses (estimates), scanner poses as nominal.
        packets: Interleaved packets per stack (:func:`packet_times`).
        grid: The smoothness values, each >= 0.
        config: The fit's other settings (its ``smoothness`` is replaced); default
            :class:`TrajectoryConfig()`.

    Returns:
        (G, N) float64 the rotation angle (degrees) between each slice's pose and its prediction
        at each ``grid`` value, capped at :data:`LOO_CAP_DEG`, on ``slices.device``.

    Raises:
        ValueError: If ``grid`` is empty (and as :func:`fit_slice_trajectory`).
    """
    if not grid:
        raise ValueError("leave_one_out_deg(): 'grid' must hold at least one value")
    config = TrajectoryConfig() if config is None else config
    packet, time = packet_times(slices, packets)
    _check(slices.poses, packet, time, None, slices.scanner_poses)
    moved = _transported(slices.poses, packet, time, slices.scanner_poses)
    every = torch.ones(len(slices), dtype=torch.float64, device=moved.T.device)
    ref = _group_mean(moved.U, moved.packet_index, every, len(moved.packets))
    errors = moved.T.new_zeros(len(grid), len(slices))
    for i, smoothness in enumerate(grid):
        trial = replace(config, smoothness=float(smoothness))
        for value in torch.unique(time):
            out = (time == value).to(moved.T.device)
            fit = _fit_transported(moved, ~out, trial, ref)
            angle = rotation_angle(fit.poses[out], moved.T[out]).rad2deg()
            errors[i, out] = angle.clamp(max=LOO_CAP_DEG)
    return errors


def cross_validated_trajectory(
    slices: SliceSet,
    packets: int,
    grid: tuple[float, ...] = SMOOTHNESS_GRID,
    config: TrajectoryConfig | None = None,
) -> tuple[TrajectoryFit, float, Tensor]:
    """:func:`fit_slice_trajectory` at the smoothness that best predicts a left-out slice.

    The smoothness of ``grid`` with the least mean :func:`leave_one_out_deg` over all slices is
    chosen for all packets together. Pose estimates that scatter about a calm head choose the
    stiffest trajectories, which average them; a head that moved between slices more than the
    estimates scatter chooses more flexible ones (though not the most flexible: a cubic spline
    through a left-out slice of a random walk overshoots, so some smoothing predicts best even
    for exact estimates).

    Args:
        slices: The slices with their current poses (estimates), scanner poses as nominal.
        packets: Interleaved packets per stack (:func:`packet_times`).
        grid: The smoothness values to choose from, each >= 0.
        config: The fit's other settings (its ``smoothness`` is replaced); default
            :class:`TrajectoryConfig()`.

    Returns:
        ``(fit, smoothness, errors)``: the fit of every slice at the chosen smoothness, that
        smoothness, and (G,) float64 the mean leave-one-out error (degrees) of each ``grid``
        value.

    Raises:
        ValueError: If ``grid`` is empty (and as :func:`fit_slice_trajectory`).
    """
    if not grid:
        raise ValueError("cross_validated_trajectory(): 'grid' must hold at least one value")
    config = TrajectoryConfig() if config is None else config
    errors = leave_one_out_deg(slices, packets, grid, config).mean(1).cpu()
    best = float(grid[int(errors.argmin())])
    fit = fit_slice_trajectory(slices, packets, replace(config, smoothness=best))
    return fit, best, errors
