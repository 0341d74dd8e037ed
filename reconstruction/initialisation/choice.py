"""What every start in canonical space shares: candidate poses per stack, and the safe choice.

A learned or atlas start (:mod:`~svr.reconstruction.initialisation.learned`,
:mod:`~svr.reconstruction.initialisation.atlas`,
:mod:`~svr.reconstruction.initialisation.slice_model`) proposes, per stack, one or more
candidate poses of its slices in canonical space beside plain stack registration brought into
canonical space. :func:`choose_per_stack` keeps, per stack, the candidate that agrees best with
the *other* stacks, and falls back to stack registration everywhere where the mixture fits worse
than registration alone, so that a learned start never does harm.
:func:`registered_candidate` builds a candidate: stack registration started from placed poses,
moved into canonical space by the frame the agreeing stacks share (:func:`agreeing_stacks`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from svr.geometry import rotation_angle, se3_compose, se3_inverse
from svr.geometry.averaging import robust_mean_pose
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.registration import stack_ncc, stack_registration
from svr.reconstruction.slices import SliceSet

__all__ = [
    "AGREE_DEG",
    "Start",
    "agreed_frame",
    "agreeing_stacks",
    "choose_per_stack",
    "place_stacks",
    "placed_by_packets",
    "register_stacks",
    "registered_candidate",
    "stack_moves",
]

log = logging.getLogger(__name__)

AGREE_DEG = 45.0
"""Stacks whose canonical transforms lie within this (degrees) of each other agree (a wrong twin
is 150-180 degrees off)."""


class Start(NamedTuple):
    """The slices' starting poses, and what each stack kept.

    Attributes:
        slices: The slices at their starting poses (and the frame of those poses).
        choice: Per stack, the start kept (``"scanner"``, ``"stack"``, ``"cnn"``, ``"packets"``).
        notes: Per stack, why (support, the NCC of each candidate), for the log and the QA page;
            empty where there was no choice.
        from_scanner: (4, 4) float64 CPU, for a start in canonical space: the transform from the
            scanner frame (the template stack's, which stack registration keeps) to canonical.
        frame_margin: The learned evidence for the canonical frame (the stack-pose network's
            pooled logits over the runner-up frame's), or ``None``.
    """

    slices: SliceSet
    choice: tuple[str, ...]
    notes: tuple[str, ...] = ()
    from_scanner: Tensor | None = None
    frame_margin: float | None = None


def mean_ncc(per_stack: Tensor, slices: SliceSet) -> float:
    """Slice-weighted mean of (S,) per-stack NCCs."""
    counts = torch.bincount(slices.stack_ids.cpu(), minlength=len(per_stack)).to(per_stack)
    return float((per_stack.cpu() * counts.cpu()).sum() / counts.sum().clamp_min(1))


def choose_per_stack(
    slices: SliceSet,
    candidates: dict[str, Tensor],
    trusted: Tensor,
    heads: Sequence[str],
    config: ReconstructionConfig,
) -> Start:
    """Per stack, the candidate poses with the best NCC, then the joint check against ``"stack"``.

    A stack's NCC under a candidate is that of its slices with their simulation from the other
    stacks' volume, all at the candidate's poses (:func:`stack_ncc` with ``leave_out``): scored
    against its own slices as well, a stack placed more freely (its packets apart) fits itself
    better even where one packet is the wrong twin. A tie keeps the learned candidate. Where the
    stacks kept different candidates, the mixture is kept only if its slice-weighted mean NCC is
    not below that of stack registration alone.

    Args:
        slices: All slices.
        candidates: Name -> (N, 4, 4) canonical poses of every slice; ``"stack"`` (stack
            registration) is required, the others are learned starts.
        trusted: (S,) bool, stacks that may keep a learned start (the others keep ``"stack"``).
        heads: Per stack, what the learned estimate says of itself (for the notes).
        config: Settings (the initialisation grid).

    Returns:
        The slices at the chosen canonical poses, the choice and the notes per stack.
    """
    grid_mm = config.initialisation_grid_mm
    # The learned candidates are only scored when some stack may keep them.
    scores = {
        name: stack_ncc(slices.with_poses(poses, "canonical"), grid_mm, leave_out=True)
        for name, poses in candidates.items()
        if name == "stack" or bool(trusted.any())
    }
    choice, notes = [], []
    poses = candidates["stack"].clone()
    for sid, name in enumerate(slices.stack_names):
        head = heads[sid]
        if not bool(trusted[sid]):
            best, why = "stack", f"cnn unsure ({head})"
        else:
            ncc = {key: float(value[sid]) for key, value in scores.items()}
            best = max(sorted(ncc, key=lambda key: key == "stack"), key=lambda key: ncc[key])
            why = f"{head}, NCC " + " vs ".join(f"{key} {value:.3f}" for key, value in ncc.items())
        members = slices.stack_ids == sid
        poses[members] = candidates[best][members]
        choice.append(best)
        notes.append(why)
        log.info("%s: initialisation %s (%s)", name, best, why)
    # Where every stack kept one candidate, it scored at least ``"stack"`` on each stack, so the
    # joint check cannot fail and is not computed.
    if len(set(choice)) > 1:
        mixed = mean_ncc(
            stack_ncc(slices.with_poses(poses, "canonical"), grid_mm, leave_out=True), slices
        )
        alone = mean_ncc(scores["stack"], slices)
        if mixed < alone:
            log.info(
                "the mixed start (mean NCC %.3f) fits worse than stack registration alone "
                "(%.3f); every stack starts from registration",
                mixed,
                alone,
            )
            poses = candidates["stack"]
            notes = [f"{n}; joint check failed ({mixed:.3f} < {alone:.3f})" for n in notes]
            choice = ["stack"] * len(choice)
    return Start(slices.with_poses(poses, "canonical"), tuple(choice), tuple(notes))


def agreeing_stacks(to_canonical: Tensor, stack_ids: Tensor, weights: Tensor) -> Tensor:
    """The stacks in the largest group of agreeing canonical transforms, by weight.

    A robust mean over all stacks' slices tolerates fewer than half in gross error; where the
    stacks split into a transform and its twin (a model that turns some stacks front to back),
    the mean of the two lands between them, tens of degrees from either. Each stack's transform
    is the robust mean over its slices; each stack gathers the weight of the stacks within
    :data:`AGREE_DEG` of it, and the heaviest stack's group is returned (the lowest index on a
    tie). Where all stacks agree, that is every stack.

    Args:
        to_canonical: (N, 4, 4) a transform per slice into canonical space (mm).
        stack_ids: (N,) each slice's stack, 0 .. S-1.
        weights: (S,) each stack's vote, > 0 (for example the model's confidence).

    Returns:
        (S,) bool, the stacks of the chosen group.
    """
    present = torch.stack([(stack_ids == s).any() for s in range(len(weights))])
    identity = torch.eye(4, dtype=torch.float64)
    transforms = torch.stack(
        [
            robust_mean_pose(to_canonical[stack_ids == s]) if bool(here) else identity
            for s, here in enumerate(present)
        ]
    )
    angles = torch.rad2deg(rotation_angle(transforms[:, None], transforms[None, :]))
    near = (angles <= AGREE_DEG) & present[None, :] & present[:, None]
    votes = (near.to(torch.float64) * weights.to(torch.float64)[None, :]).sum(1)
    return near[int(torch.argmax(votes))]


def register_stacks(slices: SliceSet, start: Tensor, config: ReconstructionConfig) -> Tensor:
    """Stack registration of ``slices`` from ``start`` (the template stack's frame).

    Args:
        slices: All slices.
        start: (N, 4, 4) float64 CPU poses registration starts from.
        config: Settings (the template and the initialisation grid).

    Returns:
        (N, 4, 4) float64 CPU registered poses.
    """
    registered, _ = stack_registration(
        slices.with_poses(start.to(slices.poses)),
        config.initialisation_grid_mm,
        config.initialisation.template,
    )
    return registered.to(torch.float64).cpu()


def stack_moves(slices: SliceSet, start: Tensor, registered: Tensor) -> Tensor:
    """(S, 4, 4) float64 each stack's rigid move ``M_s`` with ``registered_i = M_s o start_i``."""
    ids = slices.stack_ids.cpu()
    each = se3_compose(registered, se3_inverse(start))
    identity = torch.eye(4, dtype=torch.float64)
    return torch.stack(
        [
            robust_mean_pose(each[ids == s]) if bool((ids == s).any()) else identity
            for s in range(len(slices.stack_names))
        ]
    )


def registered_candidate(
    slices: SliceSet,
    registered: Tensor,
    placed: Tensor,
    votes: Tensor,
    frame: Tensor | None = None,
) -> Tensor:
    """Registered poses moved into canonical space by the frame the stacks agree on.

    Registration moved stack ``s`` by ``M_s`` into the template's frame; the result is brought
    into canonical space by ``G``: the given ``frame``, or the robust mean of ``E_i o M_s^-1``
    over the slices of the stacks that agree (:func:`agreeing_stacks`; ``E_i`` the slice's placed
    transform), so the output is in atlas orientation whichever start each stack keeps, and no
    single stack's estimate sets it.

    Args:
        slices: All slices.
        registered: (N, 4, 4) float64 CPU registered poses (:func:`register_stacks`).
        placed: (N, 4, 4) float64 CPU each slice's placed canonical pose ``E_i o S_i``.
        votes: (S,) each stack's weight in the choice of the agreeing group.
        frame: (4, 4) the template frame -> canonical transform, or ``None`` for the agreeing
            stacks' one.

    Returns:
        (N, 4, 4) canonical poses, on the slices' device and dtype.
    """
    if frame is None:
        frame = agreed_frame(slices, registered, placed, votes)
    return se3_compose(frame.to(registered)[None], registered).to(slices.poses)


def agreed_frame(slices: SliceSet, registered: Tensor, placed: Tensor, votes: Tensor) -> Tensor:
    """The template frame -> canonical transform that the agreeing stacks give.

    The robust mean of ``E_i o M_s^-1`` (``placed_i o registered_i^-1``) over the slices of the
    stacks in the largest agreeing group (:func:`agreeing_stacks`).

    Args:
        slices: All slices.
        registered: (N, 4, 4) float64 CPU registered poses.
        placed: (N, 4, 4) float64 CPU each slice's placed canonical pose.
        votes: (S,) each stack's weight in the choice of the group.

    Returns:
        (4, 4) float64 transform.
    """
    ids = slices.stack_ids.cpu()
    each = se3_compose(placed, se3_inverse(registered))
    group = agreeing_stacks(each, ids, votes)
    if not bool(group.all()):
        log.warning(
            "the stacks disagree on the canonical frame by more than %.0f deg (a wrong twin?): "
            "the output frame follows %s",
            AGREE_DEG,
            ", ".join(name for s, name in enumerate(slices.stack_names) if group[s]),
        )
    return robust_mean_pose(each[group[ids]])


def placed_by_packets(slices: SliceSet, packet_to_canonical: Tensor) -> Tensor:
    """Each slice at its scanner pose moved by its packet's transform: the packets' start.

    Args:
        slices: All slices, at their scanner poses.
        packet_to_canonical: (S, P, 4, 4) float64 CPU each packet's scanner -> canonical
            transform; the packet of the slice from k-plane ``k`` is ``k % P``.

    Returns:
        (N, 4, 4) float64 CPU the slices' canonical poses (of their arrays, as ``slices.poses``).
    """
    packet = slices.slice_indices.cpu() % packet_to_canonical.shape[1]
    moved = packet_to_canonical[slices.stack_ids.cpu(), packet]
    return se3_compose(moved, slices.poses.to(torch.float64).cpu())


def place_stacks(
    slices: SliceSet,
    to_canonical: Tensor,
    packet_to_canonical: Tensor | None,
    votes: Tensor,
    heads: Sequence[str],
    config: ReconstructionConfig,
    registered: Tensor | None = None,
    frame: Tensor | None = None,
) -> Start:
    """Stacks (and packets) placed by their own transforms, each refined by stack registration.

    Candidates (:func:`registered_candidate`): ``"cnn"``, stack registration started from each
    slice placed by its stack's transform, which are within a few degrees of each other even
    where the fetus turned between stacks, so that the same-subject registration only refines how
    the stacks sit together; ``"packets"`` (with ``packet_to_canonical``), the same from each
    slice placed by its packet's transform; ``"stack"``, stack registration from the scanner
    poses, brought into canonical space by ``frame`` where given. Then the safe choice per stack
    (:func:`choose_per_stack`).

    Args:
        slices: All slices, at their scanner poses.
        to_canonical: (S, 4, 4) float64 CPU each stack's scanner -> canonical transform.
        packet_to_canonical: (S, P, 4, 4) float64 CPU each packet's transform (packet of slice
            ``k``: ``k % P``), or ``None``.
        votes: (S,) each stack's weight in the choice of the output frame's agreeing group.
        heads: Per stack, what its estimate says of itself (for the notes).
        config: Settings.
        registered: (N, 4, 4) stack registration from the scanner poses, if already computed.
        frame: (4, 4) the registration's template frame -> canonical transform of the
            ``"stack"`` candidate
            (:func:`~svr.reconstruction.initialisation.stack_pose.joint_frame`), or ``None`` for the
            agreeing stacks' one.

    Returns:
        The slices at their starting canonical poses, the choice and notes per stack.
    """
    scanner = slices.poses.to(torch.float64).cpu()
    ids = slices.stack_ids.cpu()
    placed = se3_compose(to_canonical[ids], scanner)
    from_placed = register_stacks(slices, placed, config)
    candidates = {"cnn": registered_candidate(slices, from_placed, placed, votes)}
    if packet_to_canonical is not None:
        by_packet = placed_by_packets(slices, packet_to_canonical)
        from_packets = register_stacks(slices, by_packet, config)
        candidates["packets"] = registered_candidate(slices, from_packets, by_packet, votes)
    if registered is None:
        registered = register_stacks(slices, scanner, config)
    if frame is None:
        frame = agreed_frame(slices, registered, placed, votes)
    candidates["stack"] = registered_candidate(slices, registered, placed, votes, frame)
    trusted = torch.ones(len(slices.stack_names), dtype=torch.bool, device=slices.device)
    start = choose_per_stack(slices, candidates, trusted, heads, config)
    return start._replace(from_scanner=frame.to(torch.float64).cpu())
