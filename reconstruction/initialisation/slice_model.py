"""The ``"learned-slices"`` start: every slice's canonical pose predicted, made rigid per stack.

A slice-pose network (:mod:`svr.models.predict`) predicts the canonical pose ``P_i`` of every
slice independently, so single predictions can be far off. Within a stack the slices are (up to
fetal motion) one rigid body, so each prediction also proposes a scanner -> canonical transform

    A_i = P_i o S_i^-1,

with ``S_i`` the slice's acquisition (scanner-frame) pose. The robust mean ``A_s`` of a stack's
``A_i`` (:func:`svr.geometry.averaging.robust_mean_pose`) gives its consensus poses ``A_s o S_i``,
which a minority of gross outliers cannot move; the robust mean ``A`` over all slices is the one
map that brings scanner-frame poses (e.g. from stack registration) into canonical space. Refined
per slice (:meth:`SliceConsensus.refined_poses`), each slice keeps its own prediction where it
agrees with its stack's consensus and takes the consensus pose where it does not.

Origins (``docs/conventions.md``): :func:`svr.models.predict.predict_plane_poses` returns poses of
the stack's k-planes about the plane centre, voxel ``((I - 1) / 2, (J - 1) / 2, k)`` of the
stack's (cropped) array. A :class:`~svr.reconstruction.slices.SliceSet` slice has its origin at
the centre of its zero-padded array and is indexed by the file's ``k``. With ``C_k`` the k-plane's
scanner pose and ``T_k`` its predicted canonical pose, the slice's predicted pose is
``P_i = T_k o C_k^-1 o S_i``, where ``C_k^-1 o S_i`` is the in-plane shift between the two
origins; hence ``A_i = T_k o C_k^-1``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from svr.geometry import se3_compose, se3_inverse, so3_log
from svr.geometry.averaging import robust_mean_pose
from svr.geometry.mirror import ReflectionPlane, check_planes, orbit_matrices
from svr.models.network import SlicePoseNet
from svr.models.predict import predict_plane_poses
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation.choice import Start, choose_per_stack
from svr.reconstruction.registration import stack_registration
from svr.reconstruction.slices import SliceSet, Stack

__all__ = [
    "SliceConsensus",
    "consensus_start",
    "disambiguate_stack",
    "learned_consensus",
    "slice_model_start",
    "slice_predictions",
]

log = logging.getLogger(__name__)

_PLANE_ATOL = 1e-4  # rad and mm: how far a slice may lie off its stack's k-plane


@dataclass(frozen=True)
class SliceConsensus:
    """Learned slice poses of a :class:`~svr.reconstruction.slices.SliceSet` and their consensus.

    All poses are float64 on the slice set's device and map slice-plane mm (origin at the centre
    of the slice set's padded array) to the canonical frame; transforms map scanner mm to
    canonical mm.

    Attributes:
        predicted_poses: (N, 4, 4) each slice's predicted pose ``P_i``: the member of its
            prediction's mirror orbit that its stack chose (the prediction itself for a model
            without symmetry planes).
        consensus_poses: (N, 4, 4) ``A_s o S_i``: the slice's scanner pose ``S_i`` moved by its
            stack's transform, so the slices of a stack stay rigid with each other.
        stack_transforms: (S, 4, 4) ``A_s``, the robust mean of ``P_i o S_i^-1`` over the slices
            of stack ``s``; all NaN for a stack with no slice in the slice set.
        global_transform: (4, 4) ``A``, the robust mean of ``P_i o S_i^-1`` over all slices.
        rotation_deviation_deg: (N,) angle between each prediction's rotation and its consensus
            pose's (degrees), to report outlier predictions.
        translation_deviation_mm: (N,) distance between each prediction's slice centre and its
            consensus pose's (mm).
        raw_predicted_poses: (N, 4, 4) the network's predictions as they came.
        orbit_member: (N,) int64 which orbit member each slice took (0: its prediction, ``k``:
            its twin about the model's plane ``k - 1``): non-zero means the stack flipped it.
        stack_support: (S,) fraction of each stack's slices that support its transform (within
            the bounds); NaN for a stack with no slice.
        supporting: (N,) bool whether each slice supports its stack's transform.
    """

    predicted_poses: Tensor
    consensus_poses: Tensor
    stack_transforms: Tensor
    global_transform: Tensor
    rotation_deviation_deg: Tensor
    translation_deviation_mm: Tensor
    raw_predicted_poses: Tensor
    orbit_member: Tensor
    stack_support: Tensor
    supporting: Tensor

    def flipped(self, stack_ids: Tensor) -> Tensor:
        """(S,) int64 number of slices per stack that took a mirror twin of their prediction."""
        count = torch.zeros(len(self.stack_support), dtype=torch.long, device=stack_ids.device)
        return count.index_add(0, stack_ids, (self.orbit_member != 0).long().to(stack_ids.device))

    def outliers(self, max_rotation_deg: float, max_translation_mm: float) -> Tensor:
        """(N,) bool: predictions farther from their consensus pose than either bound."""
        return (self.rotation_deviation_deg > max_rotation_deg) | (
            self.translation_deviation_mm > max_translation_mm
        )

    def refined_poses(self, max_rotation_deg: float, max_translation_mm: float) -> Tensor:
        """(N, 4, 4) each slice's own prediction, or its consensus pose where that is an outlier.

        Args:
            max_rotation_deg: Largest rotation (degrees) between a kept prediction and its
                consensus pose, >= 0.
            max_translation_mm: Largest distance (mm) between their slice centres, >= 0.

        Raises:
            ValueError: If a bound is negative or not finite.
        """
        for name, value in (
            ("max_rotation_deg", max_rotation_deg),
            ("max_translation_mm", max_translation_mm),
        ):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"refined_poses(): {name!r} must be finite and >= 0, got {value!r}"
                )
        outlier = self.outliers(max_rotation_deg, max_translation_mm)
        return torch.where(outlier[:, None, None], self.consensus_poses, self.predicted_poses)


def _stack_predictions(
    model: SlicePoseNet,
    stack: Stack,
    scanner_poses: Tensor,
    file_k: Tensor,
    batch_size: int,
) -> Tensor:
    """``P_i = T_k o S_k^-1 o S_i`` for the given slices of one stack (module docstring).

    Args:
        model: The network, in eval mode.
        stack: The stack.
        scanner_poses: (M, 4, 4) float64 CPU scanner poses ``S_i`` of its slices in the slice set.
        file_k: (M,) int64 CPU file k-plane index of each of those slices.
        batch_size: Slices per forward pass.

    Returns:
        (M, 4, 4) float64 CPU predicted canonical poses of the slices.

    Raises:
        ValueError: Naming the stack, if a slice has no prediction or does not lie on the k-plane
            that its index names.
    """
    planes = predict_plane_poses(
        model, stack.image, stack.mask, batch_size=batch_size, name=stack.name
    )
    row_of = {int(k): row for row, k in enumerate(stack.k_indices.cpu()[planes.indices].tolist())}
    missing = [int(k) for k in file_k.tolist() if int(k) not in row_of]
    if missing:
        raise ValueError(
            f"slice_predictions(): stack {stack.name!r}: no prediction for the slices "
            f"k = {missing} of 'slices' (the stack's mask is empty there); were the slices cut "
            "from 'stacks'?"
        )
    rows = torch.tensor([row_of[int(k)] for k in file_k.tolist()], dtype=torch.long)
    shift = se3_compose(se3_inverse(planes.plane_poses[rows]), scanner_poses)
    off_plane = torch.maximum(
        (shift[:, :3, :3] - torch.eye(3, dtype=torch.float64)).abs().amax(dim=(1, 2)),
        shift[:, 2, 3].abs(),
    )
    if bool((off_plane > _PLANE_ATOL).any()):
        raise ValueError(
            f"slice_predictions(): stack {stack.name!r}: slices of 'slices' do not lie on the "
            "k-planes of the stack they name; were the slices cut from 'stacks'?"
        )
    return se3_compose(planes.poses[rows], shift)


def slice_predictions(
    model: SlicePoseNet,
    stacks: list[Stack],
    slices: SliceSet,
    batch_size: int = 64,
    max_rotation_deg: float = 30.0,
    max_translation_mm: float = 20.0,
) -> SliceConsensus:
    """Predict every slice's canonical pose and the per-stack rigid consensus of the predictions.

    A model trained up to the mirror twin (``model.config.symmetry_planes``) has each stack
    choose, per slice, between the prediction and its twin (:func:`learned_consensus`).

    Args:
        model: The slice-pose network, in eval mode (:func:`svr.models.predict.load_pose_model`),
            with its configuration ``model.config``.
        stacks: The stacks the slices were cut from, in the order of ``slices.stack_names``.
        slices: The slices (:func:`svr.reconstruction.slices.extract_slices`); their
            ``scanner_poses`` are used, whatever frame ``poses`` is in.
        batch_size: Slices per forward pass, >= 1.
        max_rotation_deg: Rotation bound (degrees) of a slice's support for its stack, > 0.
        max_translation_mm: Slice-centre distance bound (mm) of support, > 0.

    Returns:
        The predicted and consensus poses, transforms and deviations (:class:`SliceConsensus`),
        on ``slices.device``.

    Raises:
        ValueError: If ``stacks`` does not match ``slices.stack_names``, a slice has no
            prediction (its mask is empty in the stack) or does not lie on its stack's k-plane,
            ``slices`` is empty, or ``batch_size`` < 1.
    """
    names = tuple(stack.name for stack in stacks)
    if names != slices.stack_names:
        raise ValueError(
            "slice_predictions(): 'stacks' must be the stacks of 'slices', in order: got "
            f"{list(names)}, the slices name {list(slices.stack_names)}"
        )
    if len(slices) == 0:
        raise ValueError("slice_predictions(): 'slices' is empty")
    if not (isinstance(batch_size, int) and batch_size >= 1):
        raise ValueError(
            f"slice_predictions(): 'batch_size' must be an int >= 1, got {batch_size!r}"
        )
    scanner = slices.scanner_poses.to(torch.float64).cpu()
    stack_ids = slices.stack_ids.cpu()
    file_k = slices.slice_indices.cpu()
    predicted = torch.empty_like(scanner)
    for sid, stack in enumerate(stacks):
        members = torch.nonzero(stack_ids == sid).flatten()
        if len(members) > 0:
            predicted[members] = _stack_predictions(
                model, stack, scanner[members], file_k[members], batch_size
            )
    return learned_consensus(
        slices,
        predicted,
        model.config.symmetry_planes,
        max_rotation_deg,
        max_translation_mm,
    )


def _pose_residuals(
    hypotheses: Tensor, scanner: Tensor, candidates: Tensor
) -> tuple[Tensor, Tensor]:
    """Angles (deg) and centre distances (mm) of candidates from each hypothesis's poses.

    Args:
        hypotheses: (H, 4, 4) scanner -> canonical transforms ``A_h``.
        scanner: (M, 4, 4) the slices' scanner poses ``S_i``.
        candidates: (K, M, 4, 4) each slice's candidate canonical poses.

    Returns:
        (H, M, K) rotation angles (degrees) and (H, M, K) distances (mm) between ``A_h o S_i``
        and candidate ``k`` of slice ``i``.
    """
    implied = hypotheses[:, None] @ scanner[None]  # (H, M, 4, 4)
    relative = (
        implied[:, :, None, :3, :3].transpose(-1, -2)
        @ candidates.transpose(0, 1)[None, :, :, :3, :3]
    )
    angle = torch.rad2deg(so3_log(relative).norm(dim=-1))
    distance = (implied[:, :, None, :3, 3] - candidates.transpose(0, 1)[None, :, :, :3, 3]).norm(
        dim=-1
    )
    return angle, distance


def _nearest_members(
    transform: Tensor,
    scanner: Tensor,
    candidates: Tensor,
    max_rotation_deg: float,
    max_translation_mm: float,
) -> tuple[Tensor, Tensor]:
    """Each slice's candidate nearest ``transform o S_i`` and whether it is within the bounds.

    Returns:
        (M,) int64 chosen candidate and (M,) bool support.
    """
    angle, distance = _pose_residuals(transform[None], scanner, candidates)
    cost = (angle[0] / max_rotation_deg).square() + (distance[0] / max_translation_mm).square()
    choice = cost.argmin(dim=-1)
    rows = torch.arange(len(choice))
    inlier = (angle[0, rows, choice] <= max_rotation_deg) & (
        distance[0, rows, choice] <= max_translation_mm
    )
    return choice, inlier


def disambiguate_stack(
    candidates: Tensor,
    scanner: Tensor,
    max_rotation_deg: float,
    max_translation_mm: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """A stack's scanner -> canonical transform by a robust vote over its slices' pose candidates.

    Every slice brings ``K`` candidate canonical poses (its prediction and its mirror twins); each
    candidate ``C_ki`` proposes the stack transform ``C_ki o S_i^-1``. A hypothesis's support is the
    number of slices with a candidate within both bounds of the pose the hypothesis gives them
    (RANSAC over all ``K M`` proposals, ties broken by the smaller summed normalised residual). A
    twin reverses the stack's slice order along its normal, so the twin of one slice proposes a
    transform that only its neighbours within about half the translation bound support: the true
    transform wins once most slices have one good candidate, whichever member it is. Each slice then
    takes its candidate nearest to the winning hypothesis, and the transform is the robust mean
    (:func:`svr.geometry.averaging.robust_mean_pose`) of the chosen candidates of the supporting
    slices, after which the choice is made once more against that mean.

    Args:
        candidates: (K, M, 4, 4) float64 candidate canonical poses of the stack's M slices
            (index 0 the predictions themselves).
        scanner: (M, 4, 4) float64 their scanner poses ``S_i``.
        max_rotation_deg: Rotation bound of support (degrees), > 0.
        max_translation_mm: Slice-centre distance bound of support (mm), > 0.

    Returns:
        ``(transform, choice, inlier)``: the (4, 4) transform, the (M,) int64 chosen candidate of
        each slice and the (M,) bool support of each slice by the transform.
    """
    k, m = candidates.shape[:2]
    hypotheses = (candidates @ se3_inverse(scanner)[None]).reshape(k * m, 4, 4)
    angle, distance = _pose_residuals(hypotheses, scanner, candidates)
    cost = (angle / max_rotation_deg).square() + (distance / max_translation_mm).square()
    within = (angle <= max_rotation_deg) & (distance <= max_translation_mm)
    support = within.any(dim=-1).sum(dim=-1).to(torch.float64)
    best_cost = cost.min(dim=-1).values.clamp_max(2.0).sum(dim=-1)
    best = int(torch.argmax(support - best_cost / (2.0 * m + 1.0)))
    transform = hypotheses[best]
    for _ in range(2):
        choice, inlier = _nearest_members(
            transform, scanner, candidates, max_rotation_deg, max_translation_mm
        )
        chosen = candidates[choice, torch.arange(m)]
        members = inlier if bool(inlier.any()) else torch.ones_like(inlier)
        transform = robust_mean_pose(se3_compose(chosen[members], se3_inverse(scanner[members])))
    choice, inlier = _nearest_members(
        transform, scanner, candidates, max_rotation_deg, max_translation_mm
    )
    return transform, choice, inlier


def learned_consensus(
    slices: SliceSet,
    predicted: Tensor,
    planes: Sequence[ReflectionPlane] = (),
    max_rotation_deg: float = 30.0,
    max_translation_mm: float = 20.0,
) -> SliceConsensus:
    """The per-stack and global robust consensus of canonical slice-pose predictions.

    With mirror ``planes`` (a model trained up to the twin, ``ModelConfig.symmetry_planes``)
    each prediction stands for its orbit ``{P_i, twin(P_i)}``, and the stack's slice order
    decides which member each slice takes (:func:`disambiguate_stack`).

    Args:
        slices: The slices; their ``scanner_poses`` are used, whatever frame ``poses`` is in.
        predicted: (N, 4, 4) each slice's predicted canonical pose ``P_i`` (origin at the centre
            of the slice set's padded array, like ``slices.poses``).
        planes: Canonical-frame mirror planes of the model (empty: no twins).
        max_rotation_deg: Rotation bound (degrees) within which a slice supports its stack's
            transform, > 0.
        max_translation_mm: Slice-centre distance bound (mm) of support, > 0.

    Returns:
        The (disambiguated) predictions with their consensus poses, transforms, support and
        deviations (:class:`SliceConsensus`), float64 on ``slices.device``.

    Raises:
        ValueError: If ``predicted`` is not (N, 4, 4) for the N slices, is not finite,
            ``slices`` is empty, or a bound is not a positive finite number.
    """
    if len(slices) == 0:
        raise ValueError("learned_consensus(): 'slices' is empty")
    if not isinstance(predicted, Tensor) or tuple(predicted.shape) != (len(slices), 4, 4):
        raise ValueError(
            f"learned_consensus(): 'predicted' must be a ({len(slices)}, 4, 4) tensor, got "
            f"{tuple(getattr(predicted, 'shape', ())) or type(predicted).__name__}"
        )
    if not bool(predicted.isfinite().all()):
        raise ValueError("learned_consensus(): 'predicted' holds non-finite values")
    for name, value in (
        ("max_rotation_deg", max_rotation_deg),
        ("max_translation_mm", max_translation_mm),
    ):
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ValueError(f"learned_consensus(): {name!r} must be finite and > 0, got {value!r}")
    planes = check_planes(planes, "learned_consensus")
    scanner = slices.scanner_poses.to(torch.float64).cpu()
    raw = predicted.to(torch.float64).cpu()
    orbit = orbit_matrices(raw, planes)  # (K, N, 4, 4)
    stack_ids = slices.stack_ids.cpu()
    num_stacks = len(slices.stack_names)
    stack_transforms = torch.full((num_stacks, 4, 4), math.nan, dtype=torch.float64)
    support = torch.full((num_stacks,), math.nan, dtype=torch.float64)
    member = torch.zeros(len(slices), dtype=torch.long)
    inlier = torch.zeros(len(slices), dtype=torch.bool)
    for sid in range(num_stacks):
        rows = torch.nonzero(stack_ids == sid).flatten()
        if len(rows) == 0:
            continue
        transform, choice, ok = disambiguate_stack(
            orbit[:, rows], scanner[rows], max_rotation_deg, max_translation_mm
        )
        stack_transforms[sid], member[rows], inlier[rows] = transform, choice, ok
        support[sid] = ok.to(torch.float64).mean()
    chosen = orbit[member, torch.arange(len(slices))]
    consensus = se3_compose(stack_transforms[stack_ids], scanner)
    relative = consensus[:, :3, :3].transpose(-1, -2) @ chosen[:, :3, :3]
    to_canonical = se3_compose(chosen, se3_inverse(scanner))
    device = slices.device
    return SliceConsensus(
        predicted_poses=chosen.to(device),
        consensus_poses=consensus.to(device),
        stack_transforms=stack_transforms.to(device),
        global_transform=robust_mean_pose(
            to_canonical[inlier] if bool(inlier.any()) else to_canonical
        ).to(device),
        rotation_deviation_deg=torch.rad2deg(so3_log(relative).norm(dim=-1)).to(device),
        translation_deviation_mm=(chosen[:, :3, 3] - consensus[:, :3, 3]).norm(dim=-1).to(device),
        raw_predicted_poses=raw.to(device),
        orbit_member=member.to(device),
        stack_support=support.to(device),
        supporting=inlier.to(device),
    )


def _canonical_frame(
    learned: SliceConsensus, registered: Tensor, slices: SliceSet, trusted: Tensor
) -> Tensor | None:
    """``G``: registered (template) frame -> canonical, from the trusted stacks' supporting slices.

    The robust mean of ``P_i o X_i^-1`` over the slices that support their stack's transform in
    the stacks with enough support, ``X_i`` their registered poses; ``None`` if there are none.
    """
    use = learned.supporting & trusted[slices.stack_ids]
    if not bool(use.any()):
        return None
    chosen = learned.predicted_poses[use].to(torch.float64).cpu()
    inverse = se3_inverse(registered[use].to(torch.float64).cpu())
    return robust_mean_pose(se3_compose(chosen, inverse)).to(registered)


def consensus_start(
    slices: SliceSet, learned: SliceConsensus, config: ReconstructionConfig
) -> Start:
    """Learned slice poses or stack registration, per stack, chosen so as never to do harm.

    1. **Support.** A stack whose slices mostly disagree with their consensus (support below
       ``config.initialisation.slice_min_support``; :func:`disambiguate_stack`) means the model
       is unsure of it: it keeps stack registration, and the log and QA say so.
    2. **Canonical frame.** Stack registration is moved into canonical space by ``G``, the robust
       mean over the trusted stacks' supporting slices of (chosen prediction) o (registered
       pose)^-1, so that the output is in atlas orientation whichever start each stack keeps. With
       no trusted stack the predictions' global transform is used, and the log warns that the
       orientation is unreliable.
    3. **NCC per stack.** A trusted stack keeps its learned poses (each slice its own prediction,
       or the consensus pose where that is an outlier: :meth:`SliceConsensus.refined_poses`)
       when they match their simulation from the other stacks' scattered-data volume at least as
       well (mean NCC, :func:`~svr.reconstruction.registration.stack_ncc` with ``leave_out``)
       as the registered poses do, as NeSVoR chooses between SVoRT and registration.
    4. **Joint check.** The mixed start is kept only if its slice-weighted mean NCC is not below
       that of stack registration alone; otherwise every stack starts from registration.

    Args:
        slices: All slices, at their scanner poses.
        learned: The slices' (disambiguated) predicted canonical poses and their consensus
            (:func:`slice_predictions`).
        config: Settings.

    Returns:
        The slices at their initial canonical poses, the choice per stack and notes per stack.
    """
    init = config.initialisation
    outliers = learned.outliers(init.slice_max_deviation_deg, init.slice_max_deviation_mm)
    log.info(
        "cnn: %d of %d slice predictions disagree with their stack's consensus (> %g deg or "
        "%g mm) and take the consensus pose",
        int(outliers.sum()),
        len(slices),
        init.slice_max_deviation_deg,
        init.slice_max_deviation_mm,
    )
    support = learned.stack_support.cpu()
    flipped = learned.flipped(slices.stack_ids).cpu()
    trusted = (support >= init.slice_min_support).to(slices.device)
    registered, _ = stack_registration(
        slices, config.initialisation_grid_mm, config.initialisation.template
    )
    frame = _canonical_frame(learned, registered, slices, trusted)
    if frame is None:
        log.warning(
            "cnn: no stack has enough support (>= %.0f%% of its slices); the learned "
            "initialisation is unsure and the output's atlas orientation is unreliable",
            100 * init.slice_min_support,
        )
        frame = learned.global_transform.to(registered)
    candidates = {
        "cnn": learned.refined_poses(init.slice_max_deviation_deg, init.slice_max_deviation_mm),
        "stack": frame @ registered,
    }
    heads = [
        f"support {100 * float(support[sid]):.0f}%, {int(flipped[sid])} flipped"
        for sid in range(len(slices.stack_names))
    ]
    start = choose_per_stack(slices, candidates, trusted, heads, config)
    return start._replace(from_scanner=frame.to(torch.float64).cpu())


def slice_model_start(
    slices: SliceSet, stacks: Sequence[Stack], model: SlicePoseNet, config: ReconstructionConfig
) -> Start:
    """Every slice predicted by a slice-pose network, made rigid per stack, chosen per stack.

    Args:
        slices: All slices, at their scanner poses.
        stacks: The stacks they were cut from (same order as ``slices.stack_names``).
        model: The slice-pose network with its configuration ``model.config``.
        config: Settings (the ``slice_*`` bounds of ``config.initialisation``, template, grid).

    Returns:
        The slices at their starting canonical poses, the choice and notes per stack.
    """
    init = config.initialisation
    learned = slice_predictions(
        model,
        list(stacks),
        slices,
        max_rotation_deg=init.slice_max_deviation_deg,
        max_translation_mm=init.slice_max_deviation_mm,
    )
    return consensus_start(slices, learned, config)
