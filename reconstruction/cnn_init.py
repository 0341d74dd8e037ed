"""Learned pose initialisation: CNN slice poses, made rigid per stack, against stack registration.

This module holds all of it: the predictions made rigid per stack by robust averaging
(:func:`cnn_slice_poses`) and the per-stack choice between them and stack registration
(:func:`learned_initialisation`).

A slice-pose network (:mod:`svr.models.predict`) predicts the canonical pose ``P_i`` of every slice
independently, so single predictions can be far off. Within a stack the slices are (up to fetal
motion) one rigid body, so each prediction also proposes a scanner -> canonical transform

    A_i = P_i o S_i^-1,

with ``S_i`` the slice's acquisition (scanner-frame) pose. The robust mean ``A_s`` of a stack's
``A_i`` (:func:`svr.geometry.averaging.robust_mean_pose`) gives its consensus poses ``A_s o S_i``,
which a minority of gross outliers cannot move; the robust mean ``A`` over all slices is the one map
that brings scanner-frame poses (e.g. from stack registration) into canonical space. Refined per
slice (:meth:`CnnInitialisation.refined_poses`), each slice keeps its own prediction where it agrees
with its stack's consensus and takes the consensus pose where it does not, so the learned
initialisation follows the motion of single slices that a rigid stack pose cannot.

Frames and origins (``docs/conventions.md``): :func:`svr.models.predict.predict_plane_poses` returns
poses of the stack's k-planes about the plane centre, voxel ``((I - 1) / 2, (J - 1) / 2, k)`` of the
stack's (cropped) array, indexed by that array's ``k``. A
:class:`~svr.reconstruction.slices.SliceSet` slice has its origin at the centre of its zero-padded
array and is indexed by the file's ``k`` (``Stack.k_indices``). With ``C_k`` the k-plane's scanner
pose and ``T_k`` its predicted canonical pose (both returned by the prediction), the slice's
predicted pose is ``P_i = T_k o C_k^-1 o S_i``, where ``C_k^-1 o S_i`` is the in-plane shift
between the two origins; hence ``A_i = T_k o C_k^-1``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from svr.geometry import rotation_angle, se3_compose, se3_inverse, so3_log
from svr.geometry.averaging import robust_mean_pose
from svr.geometry.mirror import ReflectionPlane, check_planes, orbit_matrices
from svr.models.network import SlicePoseNet
from svr.models.predict import predict_plane_poses
from svr.models.stack_pose import (
    StackPoseNet,
    atlas_levels,
    estimate_packet_poses,
    estimate_stack_pose,
)
from svr.reconstruction.atlas_frame import preferred_atlas
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.registration import stack_ncc, stack_registration
from svr.reconstruction.slices import SliceSet, Stack
from svr.sampling.volume import CanonicalVolume, as_atlases

__all__ = [
    "AGREE_DEG",
    "CnnInitialisation",
    "LearnedStart",
    "agreeing_stacks",
    "cnn_slice_poses",
    "disambiguate_stack",
    "learned_consensus",
    "learned_initialisation",
    "stack_pose_initialisation",
]

log = logging.getLogger(__name__)

_PLANE_ATOL = 1e-4  # rad and mm: how far a slice may lie off its stack's k-plane


@dataclass(frozen=True)
class CnnInitialisation:
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
            f"cnn_slice_poses(): stack {stack.name!r}: no prediction for the slices k = {missing} "
            "of 'slices' (the stack's mask is empty there); were the slices cut from 'stacks'?"
        )
    rows = torch.tensor([row_of[int(k)] for k in file_k.tolist()], dtype=torch.long)
    shift = se3_compose(se3_inverse(planes.plane_poses[rows]), scanner_poses)
    off_plane = torch.maximum(
        (shift[:, :3, :3] - torch.eye(3, dtype=torch.float64)).abs().amax(dim=(1, 2)),
        shift[:, 2, 3].abs(),
    )
    if bool((off_plane > _PLANE_ATOL).any()):
        raise ValueError(
            f"cnn_slice_poses(): stack {stack.name!r}: slices of 'slices' do not lie on the "
            "k-planes of the stack they name; were the slices cut from 'stacks'?"
        )
    return se3_compose(planes.poses[rows], shift)


def cnn_slice_poses(
    model: SlicePoseNet,
    stacks: list[Stack],
    slices: SliceSet,
    batch_size: int = 64,
    max_rotation_deg: float = 30.0,
    max_translation_mm: float = 20.0,
) -> CnnInitialisation:
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
        The predicted and consensus poses, transforms and deviations (:class:`CnnInitialisation`),
        on ``slices.device``.

    Raises:
        ValueError: If ``stacks`` does not match ``slices.stack_names``, a slice has no
            prediction (its mask is empty in the stack) or does not lie on its stack's k-plane,
            ``slices`` is empty, or ``batch_size`` < 1.
    """
    names = tuple(stack.name for stack in stacks)
    if names != slices.stack_names:
        raise ValueError(
            "cnn_slice_poses(): 'stacks' must be the stacks of 'slices', in order: got "
            f"{list(names)}, the slices name {list(slices.stack_names)}"
        )
    if len(slices) == 0:
        raise ValueError("cnn_slice_poses(): 'slices' is empty")
    if not (isinstance(batch_size, int) and batch_size >= 1):
        raise ValueError(f"cnn_slice_poses(): 'batch_size' must be an int >= 1, got {batch_size!r}")
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
) -> CnnInitialisation:
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
        deviations (:class:`CnnInitialisation`), float64 on ``slices.device``.

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
    return CnnInitialisation(
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


class LearnedStart(NamedTuple):
    """What :func:`learned_initialisation` chose.

    Attributes:
        slices: The slices at their initial canonical poses.
        choice: Per stack, ``"cnn"`` or ``"stack"``.
        notes: Per stack, why (support, flipped slices, NCC), for the log and the QA figure.
    """

    slices: SliceSet
    choice: tuple[str, ...]
    notes: tuple[str, ...]


def _canonical_frame(
    learned: CnnInitialisation, registered: Tensor, slices: SliceSet, trusted: Tensor
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


def _mean_ncc(per_stack: Tensor, slices: SliceSet) -> float:
    """Slice-weighted mean of (S,) per-stack NCCs."""
    counts = torch.bincount(slices.stack_ids.cpu(), minlength=len(per_stack)).to(per_stack)
    return float((per_stack.cpu() * counts.cpu()).sum() / counts.sum().clamp_min(1))


def learned_initialisation(
    slices: SliceSet, learned: CnnInitialisation, config: ReconstructionConfig
) -> LearnedStart:
    """Learned slice poses or stack registration, per stack, chosen so as never to do harm.

    1. **Support.** A stack whose slices mostly disagree with their consensus (support below
       ``config.cnn_min_support``; :func:`svr.reconstruction.cnn_init.disambiguate_stack`) means the
       model is unsure of it: it keeps stack registration, and the log and QA say so.
    2. **Canonical frame.** Stack registration is moved into canonical space by ``G``, the robust
       mean over the trusted stacks' supporting slices of (chosen prediction) o (registered
       pose)^-1, so that the output is in atlas orientation whichever start each stack keeps. With
       no trusted stack the predictions' global transform is used, and the log warns that the
       orientation is unreliable.
    3. **NCC per stack.** A trusted stack keeps its learned poses (each slice its own prediction,
       or the consensus pose where that is an outlier: :meth:`CnnInitialisation.refined_poses`)
       when they match their simulation from the other stacks' scattered-data volume at least as
       well (mean NCC, :func:`~svr.reconstruction.registration.stack_ncc` with ``leave_out``)
       as the registered poses do, as NeSVoR chooses between SVoRT and registration.
    4. **Joint check.** The mixed start is kept only if its slice-weighted mean NCC is not below
       that of stack registration alone; otherwise every stack starts from registration.

    Args:
        slices: All slices, at their scanner poses.
        learned: The slices' (disambiguated) predicted canonical poses and their consensus
            (:func:`svr.reconstruction.cnn_init.cnn_slice_poses`).
        config: Settings.

    Returns:
        The slices at their initial canonical poses, the choice per stack and notes per stack.
    """
    outliers = learned.outliers(config.cnn_max_deviation_deg, config.cnn_max_deviation_mm)
    log.info(
        "cnn: %d of %d slice predictions disagree with their stack's consensus (> %g deg or "
        "%g mm) and take the consensus pose",
        int(outliers.sum()),
        len(slices),
        config.cnn_max_deviation_deg,
        config.cnn_max_deviation_mm,
    )
    support = learned.stack_support.cpu()
    flipped = learned.flipped(slices.stack_ids).cpu()
    trusted = (support >= config.cnn_min_support).to(slices.device)
    registered, _ = stack_registration(slices, config.output_resolution_mm, config.template)
    frame = _canonical_frame(learned, registered, slices, trusted)
    if frame is None:
        log.warning(
            "cnn: no stack has enough support (>= %.0f%% of its slices); the learned "
            "initialisation is unsure and the output's atlas orientation is unreliable",
            100 * config.cnn_min_support,
        )
        frame = learned.global_transform.to(registered)
    candidates = {
        "cnn": learned.refined_poses(config.cnn_max_deviation_deg, config.cnn_max_deviation_mm),
        "stack": frame @ registered,
    }
    heads = [
        f"support {100 * float(support[sid]):.0f}%, {int(flipped[sid])} flipped"
        for sid in range(len(slices.stack_names))
    ]
    return _choose_per_stack(slices, candidates, trusted, heads, config)


def _choose_per_stack(
    slices: SliceSet,
    candidates: dict[str, Tensor],
    trusted: Tensor,
    heads: Sequence[str],
    config: ReconstructionConfig,
) -> LearnedStart:
    """Per stack, the candidate poses with the best NCC, then the joint check against ``"stack"``.

    A stack's NCC under a candidate is that of its slices with their simulation from the other
    stacks' volume, all at the candidate's poses (:func:`stack_ncc` with ``leave_out``): scored
    against its own slices as well, a stack placed more freely (its packets apart) fits itself
    better even where one packet is the wrong twin.

    Args:
        slices: All slices.
        candidates: Name -> (N, 4, 4) canonical poses of every slice; ``"stack"`` (stack
            registration) is required, the others are learned starts.
        trusted: (S,) bool, stacks that may keep a learned start (the others keep ``"stack"``).
        heads: Per stack, what the learned estimate says of itself (for the notes).
        config: Settings.

    Returns:
        The slices at the chosen poses, the choice and the notes per stack.
    """
    # The learned candidates are only scored when some stack may keep them.
    scores = {
        name: stack_ncc(
            slices.with_poses(poses, "canonical"), config.output_resolution_mm, leave_out=True
        )
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
            # Learned starts first: a tie keeps the learned start, as before.
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
        mixed = _mean_ncc(
            stack_ncc(
                slices.with_poses(poses, "canonical"), config.output_resolution_mm, leave_out=True
            ),
            slices,
        )
        alone = _mean_ncc(scores["stack"], slices)
        if mixed < alone:
            log.info(
                "cnn: the mixed start (mean NCC %.3f) fits worse than stack registration alone "
                "(%.3f); every stack starts from registration",
                mixed,
                alone,
            )
            poses = candidates["stack"]
            notes = [f"{n}; joint check failed ({mixed:.3f} < {alone:.3f})" for n in notes]
            choice = ["stack"] * len(choice)
    return LearnedStart(slices.with_poses(poses, "canonical"), tuple(choice), tuple(notes))


AGREE_DEG = 45.0
"""Stacks whose learned canonical frames lie within this of each other agree (a wrong twin is
150-180 degrees off)."""


def agreeing_stacks(to_canonical: Tensor, stack_ids: Tensor, weights: Tensor) -> Tensor:
    """The stacks in the largest group of agreeing frames, by weight.

    A robust mean over all stacks' slices tolerates fewer than half in gross error; where the
    stacks split into a frame and its twin (a model that turns some stacks front to back), the
    mean of the two lands between them, tens of degrees from either (measured: 90 degrees on the
    real scan, three stacks against three). Each stack's frame is the robust mean over its
    slices; each stack gathers the weight of the stacks within :data:`AGREE_DEG` of it, and the
    heaviest stack's group is returned (the lowest index on a tie). Where all stacks agree, that
    is every stack.

    Args:
        to_canonical: (N, 4, 4) a transform per slice into canonical space (mm).
        stack_ids: (N,) each slice's stack, 0 .. S-1.
        weights: (S,) each stack's vote, > 0 (for example the model's confidence).

    Returns:
        (S,) bool, the stacks of the chosen group.
    """
    present = torch.stack([(stack_ids == s).any() for s in range(len(weights))])
    identity = torch.eye(4, dtype=torch.float64)
    frames = torch.stack(
        [
            robust_mean_pose(to_canonical[stack_ids == s]) if bool(here) else identity
            for s, here in enumerate(present)
        ]
    )
    angles = torch.rad2deg(rotation_angle(frames[:, None], frames[None, :]))
    near = (angles <= AGREE_DEG) & present[None, :] & present[:, None]
    votes = (near.to(torch.float64) * weights.to(torch.float64)[None, :]).sum(1)
    return near[int(torch.argmax(votes))]


def stack_pose_initialisation(
    slices: SliceSet,
    stacks: Sequence[Stack],
    model: StackPoseNet | None,
    config: ReconstructionConfig,
    atlas: CanonicalVolume | Sequence[CanonicalVolume] | None = None,
) -> LearnedStart:
    """Every stack placed in canonical space from its own data, or stack registration, per stack.

    1. **Per-stack poses.** Each stack's scanner -> canonical frame ``E_s`` comes from its own
       slices and mask (:func:`svr.models.stack_pose.estimate_stack_pose`: mask-axis hypotheses,
       refined by the stack-pose model and chosen by its score; without a model, chosen by
       agreement with the atlas and fitted to it). No template stack: a fetus that turned
       between stacks is placed stack by stack. A slice's placed pose is ``E_s o S_i``
       (``S_i`` its scanner pose).
    2. **Per-packet poses** (with a model and ``config.packets`` > 1). Each interleaved packet's
       frame from its own slices (:func:`svr.models.stack_pose.estimate_packet_poses`: the
       stack's frame and the packet's own mask-axis hypotheses, refined on the packet and the
       best-scored kept), for a fetus that moved within a stack, or a stack whose own frame is a
       wrong twin that its packets are not.
    3. **Candidates, each refined by stack registration.** ``"cnn"``: stack registration
       started from the placed poses, which are within a few degrees of each other even where
       the fetus turned between stacks, so that the same-subject registration only refines how
       the stacks sit together; ``"packets"``: the same from each slice placed by its packet's
       frame; ``"stack"``: stack registration from the scanner poses, as ``--registration
       stack``. Registration moves stack ``s`` by ``M_s`` in the template's frame; each
       candidate is brought into canonical space by ``G``, the robust mean of ``E o M_s^-1``
       over the slices (``E`` the slice's learned frame), so the output is in atlas orientation
       whichever start each stack keeps, and no single stack's estimate sets it.
    4. **Safe choice.** Per stack by NCC against the other stacks, then the joint check (as
       :func:`learned_initialisation`).

    Args:
        slices: All slices, at their scanner poses.
        stacks: The stacks they were cut from (same order as ``slices.stack_names``).
        model: The stack-pose network, or ``None`` (then ``atlas`` is required).
        config: Settings.
        atlas: A brain of about the fetus's age in canonical space, several (the preferred
            first: each stack follows it unless another fits the stack clearly better,
            :func:`svr.reconstruction.atlas_frame.preferred_atlas`), or ``None``; used per stack
            only without a model.

    Returns:
        The slices at their initial canonical poses, the choice and notes per stack.
    """
    scanner = slices.poses.to(torch.float64).cpu()
    ids = slices.stack_ids.cpu()
    frames, heads, scores = [], [], []
    # With a model, each stack's pose is the model's alone and the atlas only sets the output's
    # frame (align_to_atlas): fitting every stack to the atlas as well put fewer held-out stacks
    # within 10 degrees (81 % against 89 %) and gained nothing after reconstruction
    # (benchmarks/results/learned-stack-poses-recon-no-stack-fit.md).
    per_stack = (
        as_atlases(atlas, "stack_pose_initialisation")
        if model is None and atlas is not None
        else (None,)
    )
    levels = [None if item is None else atlas_levels(item) for item in per_stack]
    packets = config.packets if model is not None else 1
    packet_frames = torch.empty(len(stacks), packets, 4, 4, dtype=torch.float64)
    for sid, stack in enumerate(stacks):
        mask = stack.mask.data > 0.5
        # Without the restarts about the chosen frame: they put more held-out stacks within 10
        # degrees (89.5 % against 84.6 %), but the reconstructions they started were lower on
        # four of the six bench cases (ga23 -0.57 dB, ga29 -0.23 dB; stack-pose-restarts.md).
        # Without a model and with several atlases: the first's unless another's fits the
        # stack clearly better (NCC, as for the output frame).
        per_atlas = [
            estimate_stack_pose(model, stack.image, mask, atlas=item, levels=level, restart_deg=0.0)
            for item, level in zip(per_stack, levels, strict=True)
        ]
        estimate = per_atlas[preferred_atlas([e.score for e in per_atlas])]
        frames.append(estimate.frame)
        scores.append(float(estimate.score))
        head = f"{estimate.method}, score {estimate.score:.2f}"
        log.info("%s: stack pose by %s (score %.3f)", stack.name, estimate.method, estimate.score)
        if packets > 1:
            assert model is not None
            per_packet = estimate_packet_poses(
                model, stack.image, mask, estimate.frame, stack.k_indices.cpu() % packets
            )
            packet_frames[sid] = estimate.frame  # for packets without a plane in this stack
            packet_frames[sid, : len(per_packet.frames)] = per_packet.frames
            turns = [math.degrees(rotation_angle(f, estimate.frame)) for f in per_packet.frames]
            head += "; packets " + ", ".join(f"{t:.0f} deg" for t in turns)
            log.info(
                "%s: packets %s from the stack's frame (own hypothesis: %s)",
                stack.name,
                ", ".join(f"{t:.1f}" for t in turns),
                per_packet.own.tolist(),
            )
        heads.append(head)
    frame_of = torch.stack(frames)  # (S, 4, 4) scanner -> canonical
    placed = se3_compose(frame_of[ids], scanner)
    # Each stack's vote for the output frame: the model's confidence in its frame (one each
    # without a model, whose scores are atlas NCCs).
    votes = (
        torch.sigmoid(torch.tensor(scores, dtype=torch.float64))
        if model is not None
        else torch.ones(len(stacks), dtype=torch.float64)
    )

    def in_canonical(start: Tensor, placed: Tensor) -> Tensor:
        """Stack registration from ``start``, moved by the agreeing stacks' learned frame."""
        registered, _ = stack_registration(
            slices.with_poses(start.to(slices.poses)), config.output_resolution_mm, config.template
        )
        registered = registered.to(torch.float64).cpu()
        # Stack s moved by M_s: E_s o M_s^-1 = placed_i o registered_i^-1 for its slices.
        each = se3_compose(placed, se3_inverse(registered))
        group = agreeing_stacks(each, ids, votes)
        if not bool(group.all()):
            log.warning(
                "the stacks disagree on the canonical frame by more than %.0f deg (a wrong twin?): "
                "the output frame follows %s",
                AGREE_DEG,
                ", ".join(stacks[s].name for s in range(len(stacks)) if group[s]),
            )
        to_canonical = robust_mean_pose(each[group[ids]])
        return se3_compose(to_canonical[None], registered).to(slices.poses)

    candidates = {"cnn": in_canonical(placed, placed)}
    if packets > 1:
        by_packet = se3_compose(packet_frames[ids, slices.slice_indices.cpu() % packets], scanner)
        candidates["packets"] = in_canonical(by_packet, by_packet)
    candidates["stack"] = in_canonical(scanner, placed)
    trusted = torch.ones(len(stacks), dtype=torch.bool, device=slices.device)
    return _choose_per_stack(slices, candidates, trusted, heads, config)
