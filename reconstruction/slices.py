"""Stacks and slices as the reconstruction sees them: every slice its own rigid body.

Conventions (``docs/conventions.md``): a slice's pose maps slice-plane mm ``(u, v, 0)`` (``u`` along
array axis 0, ``v`` along axis 1, origin at the array centre ``((H - 1) / 2, (W - 1) / 2)``) to the
target frame (``"scanner"`` or ``"canonical"``). A :class:`SliceSet` holds all slices of all
stacks zero-padded to one ``(H, W)``; padding moves the array centre, so each slice also keeps
``plane_offsets_mm``, the position of its array centre in the coordinates of its stack's k-plane
(origin at voxel ``((I - 1) / 2, (J - 1) / 2, k)``), to report poses of the original k-planes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from svr.frames import FRAMES, Frame
from svr.image import Image, stack_slice_poses
from svr.validation import check_choice

__all__ = [
    "SliceSet",
    "Stack",
    "array_poses",
    "extract_slices",
    "mask_centre",
    "mask_points",
    "moved_from_stack",
    "plane_poses",
]

# SliceSet fields that hold one entry per slice (moved and indexed together).
_PER_SLICE_FIELDS = (
    "images",
    "masks",
    "spacing_mm",
    "thickness_mm",
    "poses",
    "stack_ids",
    "slice_indices",
    "plane_offsets_mm",
    "scanner_poses",
)


@dataclass(frozen=True)
class Stack:
    """One acquired thick-slice stack, ready to be cut into slices.

    Attributes:
        name: The file it came from (used in messages and output tables).
        image: (I, J, K) float32 intensities, normalised, zero outside the mask; k indexes slices.
        mask: (I, J, K) bool brain mask on the same grid (same affine).
        thickness_mm: Slice thickness (FWHM of the through-plane PSF) in mm.
        k_indices: (K,) int64 index of each k-plane in the file the stack was read from (cropping
            may drop planes).
        full_shape: (I, J) in-plane size of the file's array, whose centre defines the slice
            origin of the poses that are reported.
        crop_origin: (i0, j0) voxel of the file's array at the crop's voxel (0, 0).
    """

    name: str
    image: Image
    mask: Image
    thickness_mm: float
    k_indices: Tensor
    full_shape: tuple[int, int]
    crop_origin: tuple[int, int] = (0, 0)


@dataclass(frozen=True)
class SliceSet:
    """N slices of common size (H, W), each with its own pose.

    Attributes:
        images: (N, H, W) float32 intensities, zero outside the mask and in the padding.
        masks: (N, H, W) bool brain masks.
        spacing_mm: (N, 2) float64 in-plane pixel spacing along array axes 0 and 1 (mm).
        thickness_mm: (N,) float64 slice thickness (through-plane PSF FWHM, mm).
        poses: (N, 4, 4) float64 slice plane (origin at the array centre) -> ``frame``.
        frame: ``"scanner"`` or ``"canonical"``.
        stack_ids: (N,) int64 index into ``stack_names``.
        slice_indices: (N,) int64 k-plane index in the stack's file.
        plane_offsets_mm: (N, 2) float64 ``(u, v)`` of the array centre in the k-plane's slice
            coordinates (origin at the file's plane centre).
        scanner_poses: (N, 4, 4) float64 acquisition poses (scanner frame), never changed.
        stack_names: The stacks' file names.
    """

    images: Tensor
    masks: Tensor
    spacing_mm: Tensor
    thickness_mm: Tensor
    poses: Tensor
    frame: Frame
    stack_ids: Tensor
    slice_indices: Tensor
    plane_offsets_mm: Tensor
    scanner_poses: Tensor
    stack_names: tuple[str, ...]

    def __post_init__(self) -> None:
        if self.images.dim() != 3:
            raise ValueError(
                f"SliceSet: 'images' must be (N, H, W), got {tuple(self.images.shape)}"
            )
        n = self.images.shape[0]
        check_choice("SliceSet", "frame", self.frame, FRAMES)
        for name, shape in (
            ("masks", tuple(self.images.shape)),
            ("spacing_mm", (n, 2)),
            ("thickness_mm", (n,)),
            ("poses", (n, 4, 4)),
            ("stack_ids", (n,)),
            ("slice_indices", (n,)),
            ("plane_offsets_mm", (n, 2)),
            ("scanner_poses", (n, 4, 4)),
        ):
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(
                    f"SliceSet: '{name}' must have shape {shape}, "
                    f"got {tuple(getattr(self, name).shape)}"
                )

    def __len__(self) -> int:
        return self.images.shape[0]

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) pixels."""
        return (self.images.shape[1], self.images.shape[2])

    @property
    def device(self) -> torch.device:
        """The device of the slice data."""
        return self.images.device

    def to(self, device: torch.device | str) -> SliceSet:
        """A copy on ``device``."""
        return replace(
            self,
            **{name: getattr(self, name).to(device) for name in _PER_SLICE_FIELDS},
        )

    def with_poses(self, poses: Tensor, frame: Frame | None = None) -> SliceSet:
        """A copy with new (N, 4, 4) poses (and optionally a new frame)."""
        return replace(self, poses=poses.to(self.poses), frame=frame or self.frame)

    def subset(self, keep: Tensor) -> SliceSet:
        """The slices selected by a (N,) bool mask or an index tensor."""
        return replace(
            self,
            **{name: getattr(self, name)[keep] for name in _PER_SLICE_FIELDS},
        )

    def stack_slices(self, stack_id: int) -> Tensor:
        """(M,) indices of the slices of stack ``stack_id``."""
        return torch.nonzero(self.stack_ids == stack_id).flatten()


def _shifted_in_plane(poses: Tensor, shift_mm: Tensor) -> Tensor:
    """``T o Trans(u, v, 0)`` for (N, 4, 4) poses and (N, 2) in-plane shifts, float64."""
    T = poses.to(torch.float64)
    shift = torch.zeros_like(T[:, :3, 3])
    shift[:, :2] = shift_mm.to(T)
    out = T.clone()
    out[:, :3, 3] = T[:, :3, 3] + (T[:, :3, :3] @ shift[..., None])[..., 0]
    return out


def plane_poses(slices: SliceSet, poses: Tensor | None = None) -> Tensor:
    """Poses of the slices' original k-planes (origin at the file's plane centre).

    Args:
        slices: The slices.
        poses: (N, 4, 4) poses of the slices' arrays; default ``slices.poses``.

    Returns:
        (N, 4, 4) float64 ``T o Trans(-offset)``: the pose a pose table reports for ``(file, k)``.
    """
    return _shifted_in_plane(slices.poses if poses is None else poses, -slices.plane_offsets_mm)


def array_poses(slices: SliceSet, planes: Tensor) -> Tensor:
    """Inverse of :func:`plane_poses`: poses of the slices' arrays from those of their k-planes.

    Args:
        slices: The slices.
        planes: (N, 4, 4) poses of the files' k-planes (e.g. read from a pose table).

    Returns:
        (N, 4, 4) float64 ``T_plane o Trans(+offset)`` (origin at the array centre).
    """
    return _shifted_in_plane(planes, slices.plane_offsets_mm)


def mask_points(slices: SliceSet, keep: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Every mask pixel of the kept slices placed at its slice's pose.

    Pixel ``(a, b)`` of a slice sits at ``u = (a - (H - 1) / 2) * spacing_u``, ``v = (b - (W - 1)
    / 2) * spacing_v`` in the slice plane, as the projector places it.

    Args:
        slices: The slices with their poses.
        keep: (N,) bool slices to use (default all).

    Returns:
        ``(points, slice_of)``: (P, 3) float64 positions in mm in ``slices.frame``, and (P,) the
        slice each belongs to.

    Raises:
        ValueError: If ``keep`` is not (N,).
    """
    masks = slices.masks
    if keep is not None:
        if tuple(keep.shape) != (len(slices),):
            raise ValueError(
                f"mask_points(): 'keep' must have shape ({len(slices)},), got {tuple(keep.shape)}"
            )
        masks = masks & keep.to(slices.device)[:, None, None]
    index = torch.nonzero(masks)  # (P, 3): slice, a, b
    n, (h, w) = index[:, 0], slices.size
    spacing = slices.spacing_mm.to(torch.float64)[n]
    u = (index[:, 1] - (h - 1) / 2).to(torch.float64) * spacing[:, 0]
    v = (index[:, 2] - (w - 1) / 2).to(torch.float64) * spacing[:, 1]
    T = slices.poses.to(torch.float64)[n]
    return T[:, :3, 3] + u[:, None] * T[:, :3, 0] + v[:, None] * T[:, :3, 1], n


def mask_centre(slices: SliceSet, keep: Tensor | None = None) -> Tensor:
    """The centre of the brain the slices' masks cover, in the slices' frame.

    Every mask pixel of every kept slice is placed at its pose (:func:`mask_points`) and
    weighted by the volume it stands for (pixel area times thickness, so that stacks of finer
    pixels do not count more); the weighted mean is returned.

    Args:
        slices: The slices with their poses.
        keep: (N,) bool slices to use (default all).

    Returns:
        (3,) float64 centre in mm, in ``slices.frame``.

    Raises:
        ValueError: If the kept slices have no mask pixel, or ``keep`` is not (N,).
    """
    points, n = mask_points(slices, keep)
    if len(points) == 0:
        raise ValueError("mask_centre(): the kept slices have no mask pixel")
    weights = (
        slices.spacing_mm.to(torch.float64)[n].prod(dim=1)
        * slices.thickness_mm.to(torch.float64)[n]
    )
    return (points * weights[:, None]).sum(dim=0) / weights.sum()


def extract_slices(stacks: list[Stack]) -> SliceSet:
    """Cut stacks into slices, drop those with an empty mask, and pad them to one size.

    Args:
        stacks: Prepared stacks (:func:`svr.reconstruction.stacks.prepare_stacks`).

    Returns:
        The slices in the scanner frame, ordered by stack then k.

    Raises:
        ValueError: If ``stacks`` is empty or no slice has a nonempty mask.
    """
    if not stacks:
        raise ValueError("extract_slices(): 'stacks' is empty")
    kept = []
    for sid, stack in enumerate(stacks):
        has_brain = stack.mask.data.flatten(0, 1).any(dim=0)
        ks = torch.nonzero(has_brain).flatten()
        kept.append((sid, stack, ks))
    if sum(len(ks) for _, _, ks in kept) == 0:
        raise ValueError("extract_slices(): every slice of every stack has an empty mask")
    height = max(stack.image.shape[0] for _, stack, ks in kept if len(ks))
    width = max(stack.image.shape[1] for _, stack, ks in kept if len(ks))
    parts: dict[str, list[Tensor]] = {
        k: [] for k in ("img", "msk", "sp", "th", "T", "sid", "k", "off")
    }
    for sid, stack, ks in kept:
        if not len(ks):
            continue
        i_n, j_n, _ = stack.image.shape
        pad_i, pad_j = (height - i_n) // 2, (width - j_n) // 2
        img = stack.image.data.new_zeros((len(ks), height, width))
        msk = torch.zeros((len(ks), height, width), dtype=torch.bool, device=img.device)
        img[:, pad_i : pad_i + i_n, pad_j : pad_j + j_n] = stack.image.data[:, :, ks].permute(
            2, 0, 1
        )
        msk[:, pad_i : pad_i + i_n, pad_j : pad_j + j_n] = stack.mask.data[:, :, ks].permute(
            2, 0, 1
        )
        # Padded voxel (a, b, k) is cropped voxel (a - pad_i, b - pad_j, k).
        shift = torch.eye(4, dtype=torch.float64, device=stack.image.affine.device)
        shift[0, 3], shift[1, 3] = -pad_i, -pad_j
        affine = stack.image.affine.to(torch.float64) @ shift
        grid = Image(img.new_zeros(1).expand(height, width, stack.image.shape[2]), affine)
        T = stack_slice_poses(grid)[ks.to(affine.device)]
        spacing = affine[:3, :3].norm(dim=0)[:2].cpu()
        centre_in_file = torch.tensor(
            [(height - 1) / 2 - pad_i, (width - 1) / 2 - pad_j], dtype=torch.float64
        ) + torch.tensor(stack.crop_origin, dtype=torch.float64)
        file_centre = (torch.tensor(stack.full_shape, dtype=torch.float64) - 1) / 2
        offsets = (centre_in_file - file_centre) * spacing
        parts["img"].append(img)
        parts["msk"].append(msk)
        parts["sp"].append(spacing.expand(len(ks), 2))
        parts["th"].append(torch.full((len(ks),), float(stack.thickness_mm), dtype=torch.float64))
        parts["T"].append(T)
        parts["sid"].append(torch.full((len(ks),), sid, dtype=torch.int64))
        parts["k"].append(stack.k_indices.to(torch.int64).cpu()[ks.cpu()])
        parts["off"].append(offsets.expand(len(ks), 2))
    device = parts["img"][0].device
    poses = torch.cat(parts["T"]).to(device)
    return SliceSet(
        images=torch.cat(parts["img"]),
        masks=torch.cat(parts["msk"]),
        spacing_mm=torch.cat(parts["sp"]).to(device),
        thickness_mm=torch.cat(parts["th"]).to(device),
        poses=poses,
        frame="scanner",
        stack_ids=torch.cat(parts["sid"]).to(device),
        slice_indices=torch.cat(parts["k"]).to(device),
        plane_offsets_mm=torch.cat(parts["off"]).to(device),
        scanner_poses=poses.clone(),
        stack_names=tuple(stack.name for stack in stacks),
    )


def moved_from_stack(slices: SliceSet) -> Tensor:
    """(N,) each slice's turn (degrees) away from its stack's rigid pose: how far it moved alone.

    Each slice implies a transform of its stack, ``P_i o S_i^-1`` (its pose times its scanner
    pose's inverse); the stack's rigid pose is the robust mean of its slices' transforms
    (:func:`svr.geometry.averaging.robust_mean_pose`), and a slice's value is the angle between
    its own transform and that mean. Zero for every slice of a stack that moved as one body.

    Args:
        slices: The slices at their poses.

    Returns:
        (N,) float64 angles in degrees, on the CPU.
    """
    from svr.geometry import rotation_angle, se3_compose, se3_inverse
    from svr.geometry.averaging import robust_mean_pose

    implied = se3_compose(
        slices.poses.to(torch.float64).cpu(), se3_inverse(slices.scanner_poses.double().cpu())
    )
    ids = slices.stack_ids.cpu()
    out = torch.zeros(len(slices), dtype=torch.float64)
    for sid in range(len(slices.stack_names)):
        mine = ids == sid
        if bool(mine.any()):
            mean = robust_mean_pose(implied[mine])
            out[mine] = torch.rad2deg(rotation_angle(implied[mine], mean.expand_as(implied[mine])))
    return out
