"""Files a reconstruction writes: the volume, the slice transforms, a NeSVoR-style slice folder.

Every writer is atomic (a reader never sees a partial file or folder, a failure leaves any
existing output untouched) and refuses to replace an existing output unless ``overwrite``.

* :func:`write_volume`: a float32 NIfTI volume.
* :func:`write_transforms`: a pose table (:mod:`svr.pose_io`, ``.csv`` or ``.json``), one row
  per slice in the slice set's order: the stack file as given, the slice's k index in that file,
  the pose of the file's k-plane (origin at the plane centre, :func:`plane_poses`) as 6-vector
  and matrix, and the frame; for a :class:`ReconstructionResult` also the columns ``ncc`` (the
  slice's NCC with its simulation from the volume), ``weight`` (EM slice inlier probability),
  ``excluded`` (left out of the volume) and ``moved_deg`` (how far the slice turned away from its
  stack's rigid pose, :func:`~svr.reconstruction.slices.moved_from_stack`).
* :func:`write_slices_folder`: ``0.nii.gz, 1.nii.gz, ...`` (one slice ``(H, W, 1)`` each, posed
  by its affine) and ``mask_0.nii.gz, ...``, the slice-folder format of NeSVoR that
  :func:`svr.models.predict.load_slice_folder` reads. File ``n`` is row ``n`` of the transforms
  table.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import Tensor

from svr.files import atomic_directory
from svr.image import Image, save_nifti
from svr.pose_io import matrices_to_table, write_pose_table
from svr.reconstruction.result import ReconstructionResult, Verdict
from svr.reconstruction.slices import SliceSet, moved_from_stack, plane_poses
from svr.stamp import verdict_stamp

__all__ = ["slice_affines", "write_slices_folder", "write_transforms", "write_volume"]


def write_volume(
    image: Image,
    path: str | os.PathLike[str],
    overwrite: bool = False,
    verdict: Verdict | None = None,
) -> Path:
    """Write a volume as float32 NIfTI (sform and qform set to its affine), atomically.

    Args:
        image: The volume (any device, any floating dtype).
        path: A ``.nii`` or ``.nii.gz`` file name.
        overwrite: Whether an existing file may be replaced.
        verdict: The reconstruction's verdict, stamped in the header's ``descrip``
            (:mod:`svr.stamp`) for the steps after it; ``None`` for none.

    Returns:
        The written path.

    Raises:
        ImageError: If the name does not end in .nii or .nii.gz.
        OutputExistsError: If the file exists and ``overwrite`` is false.
        FileNotFoundError: If the folder does not exist.
    """
    stamp = "" if verdict is None else verdict_stamp(verdict.status, verdict.frame)
    return save_nifti(image.to("cpu", torch.float32), path, overwrite, stamp)


def write_transforms(
    result_or_slices: ReconstructionResult | SliceSet,
    path: str | os.PathLike[str],
    overwrite: bool = False,
) -> Path:
    """Write every slice's pose as a pose table (see the module docstring), atomically.

    Args:
        result_or_slices: A reconstruction result (poses plus ``ncc``, ``weight`` and ``excluded``
            columns) or a slice set (poses only).
        path: A ``.csv`` or ``.json`` file name.
        overwrite: Whether an existing file may be replaced.

    Returns:
        The written path.

    Raises:
        ValueError: If the suffix is not ``.csv`` or ``.json``.
        OutputExistsError: If the file exists and ``overwrite`` is false.
    """
    if isinstance(result_or_slices, ReconstructionResult):
        slices = result_or_slices.slices
        extra = {
            "ncc": result_or_slices.slice_ncc.double().tolist(),
            "weight": result_or_slices.slice_weights.double().tolist(),
            "excluded": result_or_slices.excluded.bool().tolist(),
            "moved_deg": moved_from_stack(result_or_slices.slices).tolist(),
        }
    else:
        slices, extra = result_or_slices, {}
    names = slices.stack_names
    table = matrices_to_table(
        [names[int(sid)] for sid in slices.stack_ids.cpu()],
        slices.slice_indices.cpu(),
        plane_poses(slices).cpu(),
        slices.frame,
    )
    return write_pose_table(table, path, overwrite, extra_columns=extra)


def slice_affines(slices: SliceSet) -> Tensor:
    """(N, 4, 4) voxel -> world affines of the slices as ``(H, W, 1)`` images.

    Column 0 is ``R[:, 0] * spacing_u``, column 1 ``R[:, 1] * spacing_v``, column 2
    ``R[:, 2] * thickness``, and the translation places voxel ``(0, 0, 0)`` at
    ``T (-(H - 1) / 2 * spacing_u, -(W - 1) / 2 * spacing_v, 0)``, so that pixel ``(a, b)`` sits
    at its world position and :func:`svr.image.stack_slice_poses` gives back the pose.

    Args:
        slices: The slices, posed in their frame.

    Returns:
        float64 affines on the CPU.
    """
    T = slices.poses.to("cpu", torch.float64)
    spacing = slices.spacing_mm.to("cpu", torch.float64)
    scales = torch.cat([spacing, slices.thickness_mm.to("cpu", torch.float64)[:, None]], dim=1)
    h, w = slices.size
    corner = torch.zeros(len(slices), 3, dtype=torch.float64)
    corner[:, 0] = -(h - 1) / 2 * spacing[:, 0]
    corner[:, 1] = -(w - 1) / 2 * spacing[:, 1]
    affines = torch.eye(4, dtype=torch.float64).repeat(len(slices), 1, 1)
    affines[:, :3, :3] = T[:, :3, :3] * scales[:, None, :]
    affines[:, :3, 3] = T[:, :3, 3] + (T[:, :3, :3] @ corner[..., None])[..., 0]
    return affines


def write_slices_folder(
    slices: SliceSet,
    folder: str | os.PathLike[str],
    overwrite: bool = False,
    keep: Tensor | None = None,
) -> Path:
    """Write the slices as a NeSVoR-style slice folder, atomically (see the module docstring).

    Slice ``n`` (row ``n`` of the slice set) becomes ``n.nii.gz``, its ``(H, W)`` float32
    intensities as an ``(H, W, 1)`` image with :func:`slice_affines`' affine, and its mask
    ``mask_n.nii.gz`` (0/1 float32) on the same grid.

    Args:
        slices: The slices with their poses (any device).
        folder: The folder to create.
        overwrite: Whether an existing folder may be replaced.
        keep: (N,) bool, the slices to write (e.g. those not excluded); the others' numbers are
            left out, so numbers still match the rows of the transforms table. Default: all.

    Returns:
        The folder.

    Raises:
        ValueError: If ``keep`` does not have one entry per slice.
        OutputExistsError: If the folder exists and ``overwrite`` is false.
        FileNotFoundError: If its parent folder does not exist.
    """
    if keep is not None and tuple(keep.shape) != (len(slices),):
        raise ValueError(
            f"write_slices_folder(): 'keep' must have shape ({len(slices)},), "
            f"got {tuple(keep.shape)}"
        )
    rows = range(len(slices)) if keep is None else torch.nonzero(keep.cpu()).flatten().tolist()
    affines = slice_affines(slices)
    images = slices.images.detach().to("cpu", torch.float32)
    masks = slices.masks.detach().to("cpu", torch.float32)
    with atomic_directory(folder, overwrite) as tmp:
        for n in rows:
            save_nifti(Image(images[n, :, :, None], affines[n]), tmp / f"{n}.nii.gz")
            save_nifti(Image(masks[n, :, :, None], affines[n]), tmp / f"mask_{n}.nii.gz")
    return Path(folder)
