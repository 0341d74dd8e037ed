"""Slice-pose prediction for acquired stacks: slices prepared as the model saw them in training.

Preparation (as SVoRT's in NeSVoR): every slice of a thick-slice stack, an ``(I, J, K)`` image
whose slices are its k-planes with in-plane axes along array axes 0 and 1, is

* masked: with a brain mask, voxels outside it are set to 0 (the training volumes are masked,
  :func:`svr.sampling.volume.canonicalize`) and slices whose mask is empty are dropped. A mask on
  another grid is first resampled onto the stack's (nearest neighbour, by world position);
* normalised: divided by the 99th percentile of the stack's in-mask voxels (without a mask: its
  nonzero voxels), the rule of :mod:`svr.sampling.volume`;
* resampled in-plane (bilinear) to the model's ``spacing_mm`` and cropped or zero-padded to its
  ``input_size``, centred on the centroid of the slice's mask (without a mask: the slice centre).

The prepared slice ``k`` is cut with :func:`svr.sampling.slicer.sample_slices` at its *crop pose*
``C_k``: the rotation of the stack's k-plane (``u`` along array axis 0, ``v`` along axis 1,
normal ``u x v``) and the world position of the crop centre as translation. The model predicts
the canonical pose ``P_k`` of the prepared slice, i.e. about the crop centre. The poses returned
here are those of the stack's own slices as the conventions (``docs/conventions.md``) define
them (origin at the centre of the k-plane, voxel ``((I - 1) / 2, (J - 1) / 2, k)``):
``T_k = P_k o C_k^-1 o S_k``, with ``S_k``
the k-plane's pose in the stack's world frame (:func:`stack_slice_poses`), so a pose table row
``(stack file, k)`` needs no knowledge of the crop.

Slice sets: a ``slices.nii.gz`` written by ``svr sample`` (H, W, N) is a stack like any other. A
NeSVoR-style slice folder (``0.nii.gz, 1.nii.gz, ...``, each one slice ``(I, J, 1)`` posed by its
affine, optionally with ``mask_0.nii.gz, ...``) is read by :func:`load_slice_folder`; its slices
share one intensity scale and are indexed by their file numbers.
"""

from __future__ import annotations

import json
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from torch import Tensor

from svr.geometry import se3_compose, se3_inverse, se3_to_vector, vector_to_se3
from svr.image import (
    Image,
    ImageError,
    intensity_scale,
    load_nifti,
    mask_on_grid,
    stack_slice_poses,
    voxel_to_world,
)
from svr.models.checkpoint import (
    CHECKPOINT_CONFIG,
    Checkpoint,
    CheckpointError,
    load_checkpoint,
    resolve_model_path,
)
from svr.models.network import ModelConfig, SlicePoseNet, build_model
from svr.models.stack_pose import STACK_POSE_MODEL, StackPoseNet, load_stack_pose_model
from svr.pose_io import PoseTable
from svr.sampling.slicer import SliceConfig, sample_slices

__all__ = [
    "PlanePredictions",
    "SliceFile",
    "load_any_pose_model",
    "load_pose_model",
    "load_slice_folder",
    "pose_model_from_checkpoint",
    "pose_model_kind",
    "predict_plane_poses",
    "predict_slice_folder",
    "prepare_stack_slices",
]

log = logging.getLogger(__name__)

_SLICE_FILE = re.compile(r"(\d+)\.nii(\.gz)?")
_MASK_FILE = re.compile(r"mask_(\d+)\.nii(\.gz)?")


@dataclass(frozen=True)
class SliceFile:
    """One slice of a NeSVoR-style slice folder.

    Attributes:
        index: The file number (``3`` for ``3.nii.gz``).
        image: The slice, an ``(I, J, 1)`` image posed by its affine.
        mask: Its mask (``mask_3.nii.gz``), or ``None`` when the folder has none for it.
    """

    index: int
    image: Image
    mask: Image | None


@dataclass(frozen=True)
class _Prepared:
    """Prepared slices of one stack: (N, 1, H, W) slices, (N,) indices, (N, 4, 4) poses."""

    slices: Tensor
    indices: Tensor
    crop_poses: Tensor
    plane_poses: Tensor


def load_pose_model(
    path: str | os.PathLike[str], device: str | torch.device = "cpu"
) -> SlicePoseNet:
    """Load a slice-pose network from a checkpoint folder or the shipped model, for inference.

    Args:
        path: A checkpoint folder written by :func:`svr.models.checkpoint.save_checkpoint` whose
            config has a ``"model"`` section (:meth:`ModelConfig.to_dict`), as ``svr train`` and
            :func:`svr.models.pretrained.export.export_model` write; or the name ``"default"``
            (:data:`svr.models.pretrained.DEFAULT_MODEL`) for the model shipped in the package.
            Weights stored in float16 are cast back to their recorded float32.
        device: Where the network runs.

    Returns:
        The network in eval mode on ``device``; its configuration is ``model.config``.

    Raises:
        CheckpointError: Naming the path, if ``"default"`` is asked for but the shipped model is
            not installed, the checkpoint cannot be read (see
            :func:`~svr.models.checkpoint.load_checkpoint`; nothing in it is executed), or
            :func:`pose_model_from_checkpoint` refuses it.
    """
    checkpoint = load_checkpoint(resolve_model_path(path), map_location=device)
    return pose_model_from_checkpoint(checkpoint, device)


def pose_model_from_checkpoint(
    checkpoint: Checkpoint, device: str | torch.device = "cpu"
) -> SlicePoseNet:
    """Build the slice-pose network that a loaded checkpoint describes, with its weights.

    Args:
        checkpoint: A loaded checkpoint (:func:`~svr.models.checkpoint.load_checkpoint`).
        device: Where the network runs.

    Returns:
        The network in eval mode on ``device``; its configuration is ``model.config``.

    Raises:
        CheckpointError: Naming the checkpoint's folder, if its config has no usable ``"model"``
            section or its weights do not fit the network that section describes.
    """
    path = checkpoint.path
    try:
        config = ModelConfig.from_dict(checkpoint.config["model"])
    except KeyError as err:
        raise CheckpointError(
            path, 'config has no "model" section; not a slice-pose model'
        ) from err
    except (TypeError, ValueError) as err:
        raise CheckpointError(path, f'config "model" section is not usable: {err}') from err
    model = build_model(config).to(device)
    try:
        model.load_state_dict(checkpoint.state_dict)
    except RuntimeError as err:
        summary = " ".join(str(err).split())
        raise CheckpointError(
            path, f"weights do not fit the model in its config: {summary[:300]}"
        ) from err
    return model.eval()


def _foreground(stack: Image, mask: Tensor | None) -> Tensor:
    """Voxel values that set the intensity scale: in-mask, or nonzero without a mask."""
    return stack.data[mask] if mask is not None else stack.data[stack.data != 0]


def _prepare(stack: Image, mask: Tensor | None, config: ModelConfig, scale: float) -> _Prepared:
    """Cut the prepared slices of a stack (see the module docstring).

    Args:
        stack: The ``(I, J, K)`` stack.
        mask: (I, J, K) bool mask on the stack's grid, or ``None``.
        config: The model's input size and spacing.
        scale: Intensity divisor.

    Returns:
        The kept slices with their indices, crop poses ``C_k`` and plane poses ``S_k``.
    """
    plane_poses = stack_slice_poses(stack)
    crop_poses = plane_poses.clone()
    data = stack.data.float() / scale
    indices = torch.arange(stack.shape[2], device=data.device)
    if mask is not None:
        data = torch.where(mask, data, torch.zeros_like(data))
        per_slice = mask.sum(dim=(0, 1))
        indices = indices[per_slice > 0]
        voxels = torch.nonzero(mask).to(torch.float64)  # (M, 3) sorted by (i, j, k)
        centroid_sums = torch.zeros(stack.shape[2], 3, dtype=torch.float64, device=data.device)
        centroid_sums.index_add_(0, voxels[:, 2].long(), voxels)
        centroids = centroid_sums[indices] / per_slice[indices, None].to(torch.float64)
        crop_poses = crop_poses[indices]
        crop_poses[:, :3, 3] = voxel_to_world(stack.affine.to(centroids), centroids)
        plane_poses = plane_poses[indices]
    slice_config = SliceConfig(size=config.input_size, spacing_mm=config.spacing_mm)
    slices = sample_slices(Image(data, stack.affine), crop_poses.to(data.device), slice_config)
    return _Prepared(slices[:, None], indices.cpu(), crop_poses, plane_poses)


def _prepare_stack(
    stack: Image, mask: Image | None, config: ModelConfig, name: str, mask_name: str | None = None
) -> _Prepared:
    """:func:`_prepare` with the mask brought onto the stack's grid and the stack's own scale."""
    on_grid = None if mask is None else mask_on_grid(mask, stack)
    if on_grid is not None and not bool(on_grid.any()):
        if mask_name is None:
            raise ValueError(f"{name}: the mask is empty")
        raise ValueError(f"{mask_name}: the mask does not overlap its stack {name}")
    scale = intensity_scale(_foreground(stack, on_grid), name)
    return _prepare(stack, on_grid, config, scale)


def prepare_stack_slices(
    stack: Image, mask: Image | None, config: ModelConfig
) -> tuple[Tensor, Tensor]:
    """A stack's slices as the model expects them (see the module docstring).

    Args:
        stack: An ``(I, J, K)`` thick-slice stack; slice ``k`` is the k-plane.
        mask: Its brain mask (voxels > 0.5 are brain; any grid, resampled onto the stack's), or
            ``None``.
        config: The model's ``input_size`` ``(H, W)`` and ``spacing_mm``.

    Returns:
        (N, 1, H, W) float32 slices at ``config.spacing_mm`` mm per pixel, pixel ``(a, b)`` at
        ``u = (a - (H - 1) / 2) s``, ``v = (b - (W - 1) / 2) s`` from the crop centre, intensities
        divided by the stack's 99th percentile; and the (N,) long indices ``k`` of the slices kept
        (all of them without a mask, those with a nonempty mask otherwise), on the stack's device.

    Raises:
        ValueError: If the mask is empty, or the intensities to normalise by are not positive.
    """
    prepared = _prepare_stack(stack, mask, config, "stack")
    return prepared.slices, prepared.indices.to(stack.data.device)


def _predict(model: SlicePoseNet, prepared: _Prepared, batch_size: int) -> Tensor:
    """(N, 4, 4) float64 CPU canonical poses of the k-planes: ``T_k = P_k o C_k^-1 o S_k``."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    device = next(model.parameters()).device
    predicted = torch.cat(
        [model.predict_poses(batch.to(device)).cpu() for batch in prepared.slices.split(batch_size)]
    )
    crop_to_plane = se3_compose(se3_inverse(prepared.crop_poses), prepared.plane_poses).cpu()
    return se3_compose(vector_to_se3(predicted.double()), crop_to_plane)


@dataclass(frozen=True)
class PlanePredictions:
    """Predicted canonical poses of a stack's kept k-planes, as tensors (all float64 on the CPU).

    Attributes:
        indices: (N,) int64 ``k`` of each kept plane in the stack's array.
        plane_poses: (N, 4, 4) ``S_k``: the k-plane's slice coordinates (mm, origin at the plane
            centre, :func:`svr.image.stack_slice_poses`) -> the stack's world frame (mm).
        poses: (N, 4, 4) ``T_k``: the same slice coordinates -> the canonical frame (mm).
    """

    indices: Tensor
    plane_poses: Tensor
    poses: Tensor

    def table(self, name: str) -> PoseTable:
        """The predictions as a pose table (for files): one row per kept plane.

        Args:
            name: The stack's file name, written in the table's ``files``.

        Returns:
            ``files`` all ``name``, ``slice_indices`` the k-plane indices, ``poses`` (N, 6)
            float64 pose vectors (rad, mm) of ``T_k``, ``frame`` ``"canonical"``.
        """
        poses = se3_to_vector(self.poses)
        return PoseTable([name] * len(poses), self.indices, poses, "canonical")


def predict_plane_poses(
    model: SlicePoseNet,
    stack: Image,
    mask: Image | None = None,
    batch_size: int = 64,
    name: str = "stack",
    mask_name: str | None = None,
) -> PlanePredictions:
    """Predict the canonical pose of every kept k-plane of a stack, with its scanner pose.

    Args:
        model: The network, in eval mode (:func:`load_pose_model`); ``model.config`` gives the
            input size and spacing its slices are prepared to.
        stack: An ``(I, J, K)`` thick-slice stack (any device; slices are prepared there).
        mask: Its brain mask, or ``None`` (see :func:`prepare_stack_slices`).
        batch_size: Slices per forward pass.
        name: The stack's file name, for error messages.
        mask_name: The mask's file name, for the error when the mask has no voxel on the
            stack's grid.

    Returns:
        The kept planes' indices, scanner poses ``S_k`` and canonical poses ``T_k``.

    Raises:
        ValueError: Naming the stack, for an empty mask or unusable intensities; or a
            ``batch_size`` below 1.
    """
    prepared = _prepare_stack(stack, mask, model.config, name, mask_name)
    poses = _predict(model, prepared, batch_size)
    return PlanePredictions(prepared.indices, prepared.plane_poses.cpu(), poses)


def load_slice_folder(folder: str | os.PathLike[str]) -> list[SliceFile]:
    """Read a NeSVoR-style slice folder: ``N.nii.gz`` slices and optional ``mask_N.nii.gz``.

    Args:
        folder: The folder (``.nii`` files are read too).

    Returns:
        The slices in increasing file number.

    Raises:
        ImageError: Naming the folder or file, if the folder is missing or holds no slice files, a
            number appears twice, a file is unreadable or not a single slice ``(I, J, 1)``.
    """
    root = Path(folder)
    if not root.is_dir():
        raise ImageError(f"{root}: not a slice folder (no such folder)")
    slices: dict[int, Path] = {}
    masks: dict[int, Path] = {}
    for path in sorted(root.iterdir()):
        for pattern, found in ((_SLICE_FILE, slices), (_MASK_FILE, masks)):
            match = pattern.fullmatch(path.name)
            if match is None:
                continue
            number = int(match.group(1))
            if number in found:
                raise ImageError(f"{root}: two files for slice {number} ({found[number].name})")
            found[number] = path
    if not slices:
        raise ImageError(f"{root}: no slice files (0.nii.gz, 1.nii.gz, ...) in the folder")
    out = []
    for number in sorted(slices):
        image = load_nifti(slices[number])
        mask = load_nifti(masks[number]) if number in masks else None
        for file, img in ((slices[number], image), (masks.get(number), mask)):
            if img is not None and img.shape[2] != 1:
                raise ImageError(f"{file}: expected one slice (I, J, 1), got shape {img.shape}")
        out.append(SliceFile(number, image, mask))
    return out


def predict_slice_folder(
    model: SlicePoseNet,
    folder: str | os.PathLike[str],
    batch_size: int = 64,
) -> PoseTable:
    """Predict the canonical pose of every slice of a NeSVoR-style slice folder.

    All slices share one intensity scale (the 99th percentile of their pooled in-mask, or nonzero,
    voxels); slices with an empty mask are dropped.

    Args:
        model: The network, in eval mode (``model.config``: input size and spacing).
        folder: The slice folder (:func:`load_slice_folder`).
        batch_size: Slices per forward pass.

    Returns:
        One row per kept slice: ``files`` all ``str(folder)``, ``slice_indices`` the file numbers,
        ``poses`` (N, 6) float64 canonical poses of the slices (origin at each slice's centre).

    Raises:
        ImageError: For an unreadable folder or slice.
        ValueError: If every mask is empty or the intensities are not positive.
    """
    name = str(folder)
    items = load_slice_folder(folder)
    masks = [None if s.mask is None else mask_on_grid(s.mask, s.image) for s in items]
    kept = [(s, m) for s, m in zip(items, masks, strict=True) if m is None or bool(m.any())]
    if not kept:
        raise ValueError(f"{name}: every slice's mask is empty")
    scale = intensity_scale(torch.cat([_foreground(s.image, m) for s, m in kept]), name)
    parts = [_prepare(s.image, m, model.config, scale) for s, m in kept]
    prepared = _Prepared(
        torch.cat([p.slices for p in parts]),
        torch.tensor([s.index for s, _ in kept], dtype=torch.long),
        torch.cat([p.crop_poses for p in parts]),
        torch.cat([p.plane_poses for p in parts]),
    )
    poses = _predict(model, prepared, batch_size)
    return PoseTable([name] * len(poses), prepared.indices, se3_to_vector(poses), "canonical")


def pose_model_kind(path_or_name: str | os.PathLike[str]) -> Literal["stack-pose", "slice-pose"]:
    """Which kind of pose model a ``--model`` argument names, from its configuration alone.

    Args:
        path_or_name: ``"default"`` or ``"slice-pose"`` (the shipped slice-pose model),
            ``"stack-pose"`` (the shipped stack-pose model) or a checkpoint / training-run folder
            of either kind.

    Returns:
        ``"stack-pose"`` or ``"slice-pose"``.

    Raises:
        CheckpointError: If the folder holds no checkpoint (nothing in it is read but JSON).
    """
    if str(path_or_name) == STACK_POSE_MODEL:
        return "stack-pose"
    folder = resolve_model_path(path_or_name)
    try:
        architecture = json.loads((folder / CHECKPOINT_CONFIG).read_text()).get("architecture")
    except (OSError, ValueError, AttributeError):
        architecture = None
    return "stack-pose" if architecture == "stack_pose" else "slice-pose"


def load_any_pose_model(
    path_or_name: str | os.PathLike[str], device: torch.device | str = "cpu"
) -> SlicePoseNet | StackPoseNet:
    """The pose model a ``--model`` argument names: a stack-pose or a slice-pose network.

    Args:
        path_or_name: As :func:`pose_model_kind` takes it.
        device: Where the network runs.

    Returns:
        A :class:`~svr.models.stack_pose.StackPoseNet` or a
        :class:`~svr.models.network.SlicePoseNet`, in eval mode.

    Raises:
        CheckpointError: If the folder holds neither kind of model (nothing in it is executed).
    """
    if pose_model_kind(path_or_name) == "stack-pose":
        name = STACK_POSE_MODEL if str(path_or_name) == STACK_POSE_MODEL else path_or_name
        folder = name if name == STACK_POSE_MODEL else resolve_model_path(name)
        return load_stack_pose_model(folder, device)
    return load_pose_model(path_or_name, device)
