"""Learned stack poses in canonical space: geometric hypotheses refined by a local 3D CNN.

The global part of a stack's orientation comes from structure, the local part is learned:

1. **Hypotheses** (:func:`mask_axis_hypotheses`): the principal axes of the stack's brain mask
   give the brain's axes (fetal brains are longest front to back, then left to right, then top to
   bottom), up to their signs and, where two lengths are close, their order: 8 candidate frames.
2. **Refinement** (:class:`StackPoseNet`): the stack resampled in a candidate frame
   (:func:`svr.sampling.blocks.block_inputs`) goes through a small 3D CNN that predicts the
   residual rigid transform to the true canonical frame (within about 40 degrees and a few
   centimetres), applied and iterated; the same network scores how likely the frame is right.
3. **Choice**: the hypothesis whose refined frame scores highest.

Two heads share the encoder, both trained with the SE(3) geodesic loss on the final stack pose:

* ``"regress"``: a rotation vector and a translation, regressed from the flattened features;
  for the baselines of the loss comparison, the residual in another registered representation
  (``representation``: PoseNet's quaternion, Anchor Points, 6D), trained with that
  representation's loss on the residual;
* ``"coords"``: per-cell canonical coordinates with confidences on a coarse grid, turned into
  the residual by a differentiable weighted rigid fit (:func:`svr.geometry.weighted_rigid_fit`),
  with an auxiliary loss on the coordinates.

Frames and poses follow :mod:`svr.sampling.blocks`: a *frame* ``E`` maps scanner mm to canonical
mm, a *stack pose* ``P = E o F`` maps the stack frame ``F`` to canonical mm.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, NamedTuple, get_args

import torch
from scipy.ndimage import gaussian_filter
from torch import Tensor, nn

from svr.errors import ConfigFieldError
from svr.geometry import (
    rotation_angle,
    se3_compose,
    so3_exp,
    vector_to_se3,
    weighted_rigid_fit,
)
from svr.geometry.averaging import robust_mean_pose
from svr.image import Image, sample_world, voxel_to_world
from svr.models.checkpoint import (
    CHECKPOINT_CONFIG,
    CheckpointError,
    latest_checkpoint,
    load_checkpoint,
)
from svr.models.heads import PoseHead
from svr.models.pretrained import stack_pose_model_path
from svr.representation_registry import REPRESENTATIONS, Representation
from svr.sampling.blocks import BlockGrid, block_inputs, coarsen_stack, stack_frame
from svr.sampling.volume import CanonicalVolume
from svr.validation import (
    check_choice,
    check_instance,
    check_int,
    check_number,
    check_number_tuple,
)

__all__ = [
    "STACK_POSE_MODEL",
    "AtlasFitConfig",
    "PacketPoseEstimate",
    "StackPoseConfig",
    "StackPoseEstimate",
    "StackPoseNet",
    "StackPoseOutput",
    "atlas_agreement",
    "atlas_levels",
    "estimate_packet_poses",
    "estimate_stack_pose",
    "fit_to_atlas",
    "load_stack_pose_model",
    "mask_axis_hypotheses",
    "restart_frames",
]

Head = Literal["regress", "coords"]

STACK_POSE_MODEL = "stack-pose"
"""The name that stands for the stack-pose model shipped in the package."""


@dataclass(frozen=True)
class StackPoseConfig:
    """The stack-pose network.

    Attributes:
        head: ``"regress"`` or ``"coords"`` (see the module docstring).
        width: Channels of the first stage (doubled at each of the three stages), >= 4.
        grid_size: Block voxels per side, a multiple of 8, >= 16.
        grid_spacing_mm: Block voxel spacing (mm).
        in_plane_mm: Stacks are averaged in-plane to about this spacing first (mm).
        translation_scale_mm: The network's translation outputs are in units of this (mm).
        representation: What the ``"regress"`` head outputs, a registered name
            (:data:`svr.representation_registry.REPRESENTATIONS`): ``"se3"`` (the rotation vector
            and translation, trained with the SE(3) geodesic loss on the final pose: the shipped
            model) or a baseline trained with its own loss on the residual.
        hidden_norm: Batch normalisation before the ReLU of the hidden layer that the heads
            share. Without it (the models trained before it, which load so) the hidden units
            can all stop firing in the first steps, a run that never learns (measured), and most
            of them did so even in runs that learned.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range (``representation`` other than ``"se3"`` with the ``"coords"`` head).
    """

    head: Head = "regress"
    width: int = 16
    grid_size: int = 32
    grid_spacing_mm: float = 4.0
    in_plane_mm: float = 2.0
    translation_scale_mm: float = 10.0
    representation: Representation = "se3"
    hidden_norm: bool = True

    def __post_init__(self) -> None:
        owner = "StackPoseConfig"
        check_instance(owner, "hidden_norm", self.hidden_norm, bool)
        check_choice(owner, "head", self.head, get_args(Head))
        check_choice(owner, "representation", self.representation, tuple(REPRESENTATIONS))
        check_int(owner, "width", self.width, minimum=4)
        check_int(owner, "grid_size", self.grid_size, minimum=16)
        for name in ("grid_spacing_mm", "in_plane_mm", "translation_scale_mm"):
            check_number(owner, name, getattr(self, name), gt=0)
        if self.grid_size % 8:
            raise ConfigFieldError(owner, "grid_size", "a multiple of 8", self.grid_size)
        if self.head == "coords" and self.representation != "se3":
            raise ConfigFieldError(
                owner, "representation", "se3 with the coords head", self.representation
            )

    @property
    def grid(self) -> BlockGrid:
        """The block grid."""
        return BlockGrid(self.grid_size, self.grid_spacing_mm, self.in_plane_mm)

    def to_dict(self) -> dict:
        """JSON-ready fields."""
        return asdict(self)


def _stage(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv3d(c_in, c_out, 3, stride=2, padding=1, bias=False),
        nn.BatchNorm3d(c_out),
        nn.ReLU(inplace=True),
        nn.Conv3d(c_out, c_out, 3, padding=1, bias=False),
        nn.BatchNorm3d(c_out),
        nn.ReLU(inplace=True),
    )


class StackPoseOutput(NamedTuple):
    """What :class:`StackPoseNet` predicts for a batch of B blocks.

    Attributes:
        residual: (B, 4, 4) residual transforms (the block's canonical frame -> the true
            canonical frame, mm).
        score: (B,) logits that the frame is within the refinement's reach.
        coords: (B, N, 4) per-cell predicted canonical coordinates (mm) and confidence logits for
            the ``"coords"`` head, else ``None``.
        raw: (B, D) the ``"regress"`` head's outputs in its representation's label units (the
            residual's labels, :class:`svr.models.heads.PoseHead`), else ``None``.
    """

    residual: Tensor
    score: Tensor
    coords: Tensor | None
    raw: Tensor | None


class StackPoseNet(nn.Module):
    """Block -> residual transform to the canonical frame, and a score for the frame.

    Input ``(B, 3, S, S, S)`` blocks (:func:`svr.sampling.blocks.block_inputs`); three stages of two
    3D convolutions (the first with stride 2) to ``(4w, S/8, S/8, S/8)`` features.
    """

    cells: Tensor
    """(N, 3) the coordinate head's cell centres in the block frame (mm)."""

    def __init__(self, config: StackPoseConfig) -> None:
        super().__init__()
        self.config = config
        w, s = config.width, config.grid_size
        self.stages = nn.ModuleList([_stage(3, w), _stage(w, 2 * w), _stage(2 * w, 4 * w)])
        flat = 4 * w * (s // 8) ** 3
        norm = [nn.BatchNorm1d(8 * w)] if config.hidden_norm else []
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(flat, 8 * w), *norm, nn.ReLU(inplace=True))
        self.score = nn.Linear(8 * w, 1)
        if config.head == "regress":
            self.pose = PoseHead(8 * w, config.representation, config.translation_scale_mm)
            self._register_load_state_dict_pre_hook(_rename_legacy_pose_keys)
        else:
            self.decode = nn.Upsample(scale_factor=2, mode="trilinear", align_corners=False)
            last = nn.Conv3d(2 * w, 4, 1)
            assert last.bias is not None
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
            self.coords = nn.Sequential(
                nn.Conv3d(6 * w, 2 * w, 3, padding=1), nn.ReLU(inplace=True), last
            )
            g = config.grid
            cells = BlockGrid(s // 4, g.spacing_mm * 4, g.in_plane_mm).points(torch.float32)
            self.register_buffer("cells", cells.reshape(-1, 3), persistent=False)

    def forward(self, blocks: Tensor) -> StackPoseOutput:
        """Predict.

        Args:
            blocks: (B, 3, S, S, S) float blocks.

        Returns:
            The residuals, scores and the head's own outputs.
        """
        features = []
        x = blocks
        for stage in self.stages:
            x = stage(x)
            features.append(x)
        hidden = self.fc(x)
        score = self.score(hidden)[:, 0]
        scale = self.config.translation_scale_mm
        if self.config.head == "regress":
            raw = self.pose(hidden)
            return StackPoseOutput(vector_to_se3(self.pose.to_pose(raw)), score, None, raw)
        up = torch.cat([self.decode(features[2]), features[1]], dim=1)
        raw = self.coords(up).flatten(2).transpose(1, 2)  # (B, N, 4)
        cells = self.cells.to(raw)
        coords = torch.cat([cells + raw[..., :3] * scale, raw[..., 3:]], dim=-1)
        weights = torch.sigmoid(raw[..., 3]) + 1e-4
        residual = weighted_rigid_fit(cells.expand_as(coords[..., :3]), coords[..., :3], weights)
        return StackPoseOutput(residual, score, coords, None)


def _rename_legacy_pose_keys(state_dict: dict, prefix: str, *args: object) -> None:
    """Load checkpoints written before the head was a :class:`PoseHead` (``pose.weight``)."""
    for name in ("weight", "bias"):
        old = f"{prefix}pose.{name}"
        if old in state_dict:
            state_dict[f"{prefix}pose.linear.{name}"] = state_dict.pop(old)


def mask_axis_hypotheses(points: Tensor, weights: Tensor | None = None) -> Tensor:
    """Candidate canonical frames from the principal axes of a brain mask.

    The longest axis is taken as the brain's front-back (canonical y), the middle one as left-right
    (x) and the shortest as top-bottom (z), or with x and z swapped (their lengths are close in
    young brains); each with the 4 sign choices that keep the frame right-handed.

    Args:
        points: (N, 3) world positions (mm) of the mask's voxels, N >= 4.
        weights: (N,) non-negative weights (mask fractions), default 1.

    Returns:
        (8, 4, 4) float64 frames (scanner mm -> canonical mm), each mapping the mask's centroid to
        the canonical origin.
    """
    if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] < 4:
        raise ValueError(
            "mask_axis_hypotheses(): 'points' must have shape (N >= 4, 3), got "
            f"{tuple(points.shape)}"
        )
    p = points.to(torch.float64)
    w = torch.ones(p.shape[0], dtype=torch.float64) if weights is None else weights.double()
    w = w / w.sum()
    centre = (w[:, None] * p).sum(0)
    d = p - centre
    _, vectors = torch.linalg.eigh((w[:, None] * d).T @ d)  # ascending: shortest first
    short, middle, longest = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    frames = []
    for x_axis in (middle, short):
        for sx, sy in ((1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)):
            x, y = sx * x_axis, sy * longest
            rows = torch.stack([x, y, torch.linalg.cross(x, y)])
            frame = torch.eye(4, dtype=torch.float64)
            frame[:3, :3] = rows
            frame[:3, 3] = -rows @ centre
            frames.append(frame)
    return torch.stack(frames)


@dataclass(frozen=True)
class AtlasFitConfig:
    """The rigid fit of a stack to an atlas (the classical chain's refinement).

    Attributes:
        blur_mm: Gaussian blur (standard deviation, mm) of the atlas at each level, coarse first.
        iterations: L-BFGS iterations per level, >= 1.
        max_points: Most mask voxels used (an even subsample of the rest), >= 100.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    blur_mm: tuple[float, ...] = (4.0, 2.0)
    iterations: int = 30
    max_points: int = 20000

    def __post_init__(self) -> None:
        owner = "AtlasFitConfig"
        blur = check_number_tuple(
            owner, "blur_mm", self.blur_mm, ge=0, allow_empty=False, allow_list=True
        )
        check_int(owner, "iterations", self.iterations, minimum=1)
        check_int(owner, "max_points", self.max_points, minimum=100)
        object.__setattr__(self, "blur_mm", blur)


def _mask_samples(stack: Image, mask: Tensor, max_points: int) -> tuple[Tensor, Tensor]:
    """World points (N, 3) float64 of a stack's mask voxels and their standardised intensities."""
    inside = mask > 0.5
    idx = torch.nonzero(inside).to(torch.float64)
    values = stack.data[inside].double()
    if len(idx) > max_points:
        keep = torch.linspace(0, len(idx) - 1, max_points).round().long()
        idx, values = idx[keep], values[keep]
    values = (values - values.mean()) / values.std().clamp_min(1e-9)
    return voxel_to_world(stack.affine, idx), values


def atlas_levels(atlas: CanonicalVolume, config: AtlasFitConfig | None = None) -> list[Image]:
    """The blurred copies of an atlas that :func:`fit_to_atlas` registers to, coarse first.

    Computing them once and passing them to several fits saves the blurring (about 1 s for a
    0.8 mm atlas) in each.

    Args:
        atlas: The atlas brain in canonical space.
        config: The fit's settings (their ``blur_mm``; default :class:`AtlasFitConfig`).

    Returns:
        One image per level of ``config.blur_mm``.
    """
    config = config or AtlasFitConfig()
    return [_blurred(atlas, sigma) for sigma in config.blur_mm]


def _blurred(atlas: CanonicalVolume, sigma_mm: float) -> Image:
    if sigma_mm <= 0:
        return atlas.image
    spacing = atlas.image.spacing.double().cpu().numpy()
    data = gaussian_filter(atlas.image.data.double().cpu().numpy(), sigma_mm / spacing)
    return Image(torch.from_numpy(data).float(), atlas.image.affine)


def _ncc(a: Tensor, b: Tensor) -> Tensor:
    a = a - a.mean(-1, keepdim=True)
    return (a * b).mean(-1) / a.std(-1).clamp_min(1e-9)


def atlas_agreement(
    stack: Image, mask: Tensor, frames: Tensor, atlas: CanonicalVolume, max_points: int = 20000
) -> Tensor:
    """How well each candidate frame puts the stack on the atlas: NCC over the mask's voxels.

    Args:
        stack: (I, J, K) stack in its scanner frame.
        mask: (I, J, K) brain mask on its grid.
        frames: (H, 4, 4) candidate frames (scanner mm -> canonical mm).
        atlas: A brain of about the same age in canonical space.
        max_points: Most mask voxels used.

    Returns:
        (H,) float64 normalised cross-correlations in [-1, 1].
    """
    points, values = _mask_samples(stack, mask, max_points)
    canonical = (
        points @ frames[:, :3, :3].transpose(1, 2).double() + frames[:, None, :3, 3].double()
    )
    sampled = sample_world(atlas.image, canonical.float()).double()
    return _ncc(sampled, values)


def fit_to_atlas(
    stack: Image,
    mask: Tensor,
    frame: Tensor,
    atlas: CanonicalVolume,
    config: AtlasFitConfig | None = None,
    levels: list[Image] | None = None,
) -> tuple[Tensor, float]:
    """Refine a stack's frame by rigid registration of its masked voxels to an atlas (NCC).

    The stack moves as one rigid body about the canonical origin; L-BFGS on the rotation vector
    and shift of the correction, coarse to fine over blurred copies of the atlas.

    Args:
        stack: (I, J, K) stack in its scanner frame.
        mask: (I, J, K) brain mask on its grid.
        frame: (4, 4) starting frame (scanner mm -> canonical mm).
        atlas: A brain of about the same age in canonical space.
        config: Levels and iterations.
        levels: The atlas's blurred copies for ``config`` (:func:`atlas_levels`), or ``None`` to
            make them here.

    Returns:
        The refined (4, 4) float64 frame and its NCC with the atlas at the finest level.

    Raises:
        ValueError: If ``levels`` does not have one image per level of ``config.blur_mm``.
    """
    config = config or AtlasFitConfig()
    if levels is None:
        levels = atlas_levels(atlas, config)
    if len(levels) != len(config.blur_mm):
        raise ValueError(
            f"fit_to_atlas(): 'levels' must have {len(config.blur_mm)} images (one per blur "
            f"level), got {len(levels)}"
        )
    points, values = _mask_samples(stack, mask, config.max_points)
    start = points @ frame[:3, :3].T.double() + frame[:3, 3].double()
    params = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    ncc = 0.0
    for level in levels:
        optimiser = torch.optim.LBFGS(
            [params], lr=1.0, max_iter=config.iterations, line_search_fn="strong_wolfe"
        )

        def closure(level: Image = level, optimiser: torch.optim.LBFGS = optimiser) -> Tensor:
            optimiser.zero_grad()
            moved = start @ so3_exp(params[:3]).T + params[3:] * 10.0
            loss = -_ncc(sample_world(level, moved), values)
            loss.backward()
            return loss

        optimiser.step(closure)
        with torch.no_grad():
            moved = start @ so3_exp(params[:3]).T + params[3:] * 10.0
            ncc = float(_ncc(sample_world(level, moved), values))
    correction = torch.eye(4, dtype=torch.float64)
    with torch.no_grad():
        correction[:3, :3] = so3_exp(params[:3])
        correction[:3, 3] = params[3:] * 10.0
    return se3_compose(correction, frame.double()), ncc


class StackPoseEstimate(NamedTuple):
    """A stack's estimated canonical pose.

    Attributes:
        pose: (4, 4) float64 stack pose (stack frame mm -> canonical mm).
        frame: (4, 4) float64 frame (the stack's scanner mm -> canonical mm).
        score: What chose it: the model's logit, or the atlas NCC where an atlas chose.
        hypotheses: (H, 4, 4) frames of every hypothesis (refined by the model if given).
        scores: (H,) their scores (model logits, or atlas NCCs where an atlas chose).
        method: How it was made: ``"learned"``, ``"learned+atlas"`` (the model's choice, fitted
            to the atlas), ``"axes+atlas"`` (no model), or ``"learned (atlas fit rejected: ...)"``.
    """

    pose: Tensor
    frame: Tensor
    score: float
    hypotheses: Tensor
    scores: Tensor
    method: str


def restart_frames(frame: Tensor, turn_deg: float) -> Tensor:
    """A frame and six copies turned by ``turn_deg`` either way about each canonical axis.

    The turns are about the canonical origin (the brain's centre): every copy maps the same
    scanner point to it.

    Args:
        frame: (4, 4) frame (scanner mm -> canonical mm).
        turn_deg: The turn (degrees, >= 0).

    Returns:
        (7, 4, 4) float64 frames, ``frame`` first, then +x, -x, +y, -y, +z, -z.

    Raises:
        ValueError: If ``frame`` is not (4, 4) or ``turn_deg`` is negative or not finite.
    """
    if tuple(frame.shape) != (4, 4):
        raise ValueError(f"restart_frames(): 'frame' must be (4, 4), got {tuple(frame.shape)}")
    check_number("restart_frames", "turn_deg", turn_deg, ge=0.0)
    eye = torch.eye(3, dtype=torch.float64)
    axes = torch.stack([eye, -eye], dim=1).reshape(6, 3)  # +x, -x, +y, -y, +z, -z
    turns = torch.eye(4, dtype=torch.float64).repeat(7, 1, 1)
    turns[1:, :3, :3] = so3_exp(axes * math.radians(turn_deg))
    return se3_compose(turns, frame.to(torch.float64))


@torch.no_grad()
def refine_frames(
    model: StackPoseNet,
    stack: Image,
    mask: Tensor,
    frames: Tensor,
    iterations: int = 3,
    present: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Apply the network's residual to candidate frames, ``iterations`` times, and score them.

    Args:
        model: The network (eval mode).
        stack: (I, J, K) stack, already coarsened (:func:`svr.sampling.blocks.coarsen_stack`).
        mask: (I, J, K) float mask on its grid.
        frames: (H, 4, 4) starting frames (scanner -> canonical).
        iterations: Refinement steps, >= 0.
        present: (K,) bool slices to use (default all).

    Returns:
        The (H, 4, 4) float64 refined frames and (H,) float logits scored at them.
    """
    device = next(model.parameters()).device
    grid = model.config.grid
    frames = frames.to(torch.float64)
    score = torch.zeros(frames.shape[0])
    for step in range(iterations + 1):
        blocks = block_inputs(stack, mask, frames, grid, present).to(device)
        residual, logits, _, _ = model(blocks)
        score = logits.float().cpu()
        if step < iterations:
            frames = se3_compose(residual.double().cpu(), frames)
    return frames, score


def estimate_stack_pose(
    model: StackPoseNet | None,
    stack: Image,
    mask: Tensor,
    iterations: int = 3,
    atlas: CanonicalVolume | None = None,
    fit: AtlasFitConfig | None = None,
    in_plane_mm: float = 2.0,
    max_fit_turn_deg: float = 15.0,
    levels: list[Image] | None = None,
    restart_deg: float = 10.0,
) -> StackPoseEstimate:
    """A stack's canonical pose from its own data: mask-axis hypotheses, refined, one chosen.

    With a model, every hypothesis is refined by it and its score chooses one; the chosen frame
    is then refined again from itself and six starts turned by ``restart_deg`` about the
    canonical axes (:func:`restart_frames`), and the robust mean of the seven is kept: on
    simulated stacks of the held-out ages (three draws of 54) it put 89.5 % within 10 degrees
    against 84.6 % (``benchmarks/results/stack-pose-restarts.md``; the reconstruction's start
    does without, ``restart_deg=0``). With an atlas as
    well, the chosen frame is then rigidly fitted to the atlas (:func:`fit_to_atlas`, more
    precise where it converges) unless the fit turns it by more than ``max_fit_turn_deg`` (a
    fit gone to another optimum; the model's frame is kept). Without a model, the hypothesis
    that agrees best with the atlas (NCC, :func:`atlas_agreement`) is chosen and fitted. The
    model's score is the more robust choice: on young brains (GA 21-24), whose atlas has little
    contrast, the atlas's NCC picked a hypothesis 88 degrees off where the model's score picked
    the right one (``benchmarks/results/learned-stack-poses.md``).

    Args:
        model: The trained network, or ``None`` (then ``atlas`` is required).
        stack: (I, J, K) stack in its scanner frame (any in-plane spacing).
        mask: (I, J, K) brain mask on its grid (bool or fractions).
        iterations: Refinement steps per hypothesis.
        atlas: A brain of about the stack's age in canonical space, or ``None``.
        fit: The atlas fit's settings (default :class:`AtlasFitConfig`).
        in_plane_mm: In-plane spacing the stack is averaged to without a model (with one, the
            model's).
        max_fit_turn_deg: With a model and an atlas, the largest turn the atlas fit may make.
        levels: The atlas's blurred copies for ``fit`` (:func:`atlas_levels`), computed once
            for the stacks of one fetus; ``None`` makes them here.
        restart_deg: With a model, the turn (degrees, >= 0) of the restarts about the chosen
            frame; 0 keeps the chosen hypothesis as refined.

    Returns:
        The estimate.

    Raises:
        ValueError: If the mask has fewer than 4 voxels, or neither a model nor an atlas is given.
    """
    if model is None and atlas is None:
        raise ValueError("estimate_stack_pose(): give a 'model', an 'atlas' or both")
    if model is not None:
        model.eval()
        in_plane_mm = model.config.in_plane_mm
    image, fractions = coarsen_stack(stack, mask, in_plane_mm)
    inside = fractions > 0.5
    if int(inside.sum()) < 4:
        raise ValueError("estimate_stack_pose(): the brain mask has fewer than 4 voxels")
    idx = torch.nonzero(inside).to(torch.float64)
    frames = mask_axis_hypotheses(voxel_to_world(image.affine, idx))
    method = "axes"
    if model is not None:
        frames, scores = refine_frames(model, image, fractions, frames, iterations)
        method = "learned"
    if model is None:
        assert atlas is not None
        with torch.no_grad():
            scores = atlas_agreement(image, fractions, frames, atlas).float()
    best = int(torch.argmax(scores))
    frame, score = frames[best], float(scores[best])
    if model is not None and restart_deg > 0:
        restarted, _ = refine_frames(
            model, image, fractions, restart_frames(frame, restart_deg), iterations
        )
        frame = robust_mean_pose(restarted)
    if atlas is not None:
        fitted, ncc = fit_to_atlas(image, fractions, frame, atlas, fit, levels)
        turn = math.degrees(rotation_angle(fitted, frame))
        if model is None or turn <= max_fit_turn_deg:
            frame, method = fitted, method + "+atlas"
            score = ncc if model is None else score
        else:
            method += f" (atlas fit rejected: {turn:.0f} deg away)"
    return StackPoseEstimate(
        pose=se3_compose(frame, stack_frame(stack)),
        frame=frame,
        score=score,
        hypotheses=frames,
        scores=scores,
        method=method,
    )


class PacketPoseEstimate(NamedTuple):
    """The canonical frames of a stack's interleaved packets, each estimated on its own.

    Attributes:
        frames: (P, 4, 4) float64 frame of each packet (scanner mm -> canonical mm).
        scores: (P,) the model's logit for each chosen frame.
        own: (P,) bool, True where a packet's own mask-axis hypothesis scored higher than its
            stack's frame (the packet turned away from its stack, or the stack's frame was wrong).
    """

    frames: Tensor
    scores: Tensor
    own: Tensor


def estimate_packet_poses(
    model: StackPoseNet,
    stack: Image,
    mask: Tensor,
    frame: Tensor,
    packet_of: Tensor,
    iterations: int = 3,
    max_apart_deg: float = 100.0,
) -> PacketPoseEstimate:
    """Each interleaved packet's canonical frame from its own slices, its stack's frame a candidate.

    A packet's slices were acquired in one sweep, so they move together far less than a stack's.
    For each packet, the stack's frame and the 8 mask-axis hypotheses of the packet's own mask
    (:func:`mask_axis_hypotheses`) are refined by the network on the packet's slices only
    (:func:`refine_frames` with ``present``) and the best-scored is kept. Where the fetus turned
    within the stack, or the stack's frame is a wrong twin, a packet's own hypothesis wins (a
    simulated case whose stack was 140 degrees off: both packets within 13 degrees, 72 degrees
    apart). Packets of one stack that end more than ``max_apart_deg`` apart mean that one took a
    wrong twin (on a simulated case, a packet scored its twin, 155 degrees from the other,
    above the right frame); then every packet keeps the stack's frame refined on its slices.

    Args:
        model: The trained network.
        stack: (I, J, K) stack in its scanner frame (any in-plane spacing).
        mask: (I, J, K) brain mask on its grid (bool or fractions).
        frame: (4, 4) the stack's estimated frame (scanner mm -> canonical mm).
        packet_of: (K,) int packet index 0..P-1 of each k-plane.
        iterations: Refinement steps per candidate.
        max_apart_deg: The largest angle between two packets' own frames (degrees).

    Returns:
        The frames and scores of packets 0 to ``packet_of.max()``; a packet with fewer than 4
        mask voxels keeps the stack's frame refined on its slices, one without a plane the
        stack's frame (score NaN).

    Raises:
        ValueError: If ``packet_of`` does not have one entry per k-plane or has negative values.
    """
    k = stack.data.shape[-1]
    if packet_of.shape != (k,) or bool((packet_of < 0).any()):
        raise ValueError(
            f"estimate_packet_poses(): 'packet_of' must be ({k},) non-negative packet indices, "
            f"got shape {tuple(packet_of.shape)}"
        )
    model.eval()
    image, fractions = coarsen_stack(stack, mask, model.config.in_plane_mm)
    frame = frame.to(torch.float64).cpu()
    packet_of = packet_of.cpu()
    count = int(packet_of.max()) + 1
    # Per packet: the best-scored candidate, and the stack's frame refined on the packet (the
    # fallback); a packet without a plane in the (cropped) stack keeps the stack's frame.
    best_frames, stack_frames = frame.repeat(count, 1, 1), frame.repeat(count, 1, 1)
    best_scores = torch.full((count,), float("nan"))
    stack_scores = best_scores.clone()
    own = torch.zeros(count, dtype=torch.bool)
    placed = [p for p in range(count) if bool((packet_of == p).any())]
    for packet in placed:
        present = packet_of == packet
        candidates = frame[None]
        idx = torch.nonzero((fractions > 0.5) & present[None, None, :]).to(torch.float64)
        if idx.shape[0] >= 4:
            hypotheses = mask_axis_hypotheses(voxel_to_world(image.affine, idx))
            candidates = torch.cat([candidates, hypotheses])
        refined, logits = refine_frames(model, image, fractions, candidates, iterations, present)
        best = int(torch.argmax(logits))
        best_frames[packet], best_scores[packet] = refined[best], logits[best]
        stack_frames[packet], stack_scores[packet] = refined[0], logits[0]
        own[packet] = best > 0
    apart = max(
        (
            math.degrees(rotation_angle(best_frames[a], best_frames[b]))
            for i, a in enumerate(placed)
            for b in placed[i + 1 :]
        ),
        default=0.0,
    )
    if apart > max_apart_deg:
        return PacketPoseEstimate(stack_frames, stack_scores, torch.zeros_like(own))
    return PacketPoseEstimate(best_frames, best_scores, own)


def load_stack_pose_model(
    path: str | os.PathLike[str], device: str | torch.device = "cpu"
) -> StackPoseNet:
    """Load a stack-pose network from a checkpoint or model folder (or a run folder: its newest).

    Args:
        path: A folder written by :func:`svr.models.checkpoint.save_checkpoint` whose config has
            ``"architecture": "stack_pose"``, a training run's folder of such checkpoints, or
            :data:`STACK_POSE_MODEL` for the shipped model.
        device: Where to put the network.

    Returns:
        The network in eval mode.

    Raises:
        CheckpointError: If the folder is not a stack-pose checkpoint (nothing in it is executed).
    """
    folder = stack_pose_model_path() if str(path) == STACK_POSE_MODEL else Path(path)
    if not (folder / CHECKPOINT_CONFIG).exists():
        newest = latest_checkpoint(folder)
        if newest is not None:
            folder = newest
    checkpoint = load_checkpoint(folder, map_location=device)
    if checkpoint.config.get("architecture") != "stack_pose":
        raise CheckpointError(
            folder,
            f"not a stack-pose model (architecture {checkpoint.config.get('architecture')!r})",
        )
    try:
        # Models from before the field have no normalisation in the hidden layer.
        config = StackPoseConfig(**{"hidden_norm": False, **checkpoint.config["model"]})
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(folder, f"bad 'model' section in config.json: {exc}") from exc
    net = StackPoseNet(config)
    net.load_state_dict(checkpoint.state_dict)
    return net.to(device).eval()
