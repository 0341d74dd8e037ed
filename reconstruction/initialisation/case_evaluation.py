"""The learned start measured per slice on simulated cases with known truth.

A simulated case (``svr simulate``'s output folder, the layout of the bench cases:
``stacks/*.nii.gz``, ``masks/*_mask.nii.gz``, ``truth_slices.json``, ``case.json``,
``gt_volume.nii.gz`` and ``gt_mask.nii.gz``) knows every slice's true pose. :func:`load_case`
reads it as the reconstruction does (:func:`~svr.reconstruction.stacks.load_stacks`, then
:func:`~svr.reconstruction.slices.extract_slices`) with, per slice, its true canonical pose and
the ground-truth volume in canonical space; :func:`packet_starts` places every slice as
``svr reconstruct --registration cnn`` starts it, by its packet's transform from the stack-pose
network alone (:func:`~svr.reconstruction.initialisation.learned.network_placement`), before any
registration. ``svr evaluate --cases`` scores those starts with the paper's Table 3 metrics.

Frames (``docs/conventions.md``): poses map slice-plane mm of a file's k-plane (origin at the
plane's centre) to canonical mm, the atlas frame translated by ``-atlas_centre_mm``
(``case.json``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from svr.geometry import rotation_angle, se3_compose, se3_inverse
from svr.image import Image, load_nifti
from svr.models.stack_pose import StackPoseNet
from svr.reconstruction.initialisation.choice import placed_by_packets
from svr.reconstruction.initialisation.learned import network_placement
from svr.reconstruction.slices import SliceSet, Stack, extract_slices, plane_poses
from svr.reconstruction.stacks import load_stacks
from svr.sampling.simulate import pose_from_json
from svr.sampling.volume import CanonicalVolume, canonicalize

__all__ = ["CaseError", "SimulatedCase", "load_case", "packet_starts"]

FRAME_TOLERANCE = 1e-3
"""Largest disagreement (rad, and mm / 100) between the slices' scanner -> atlas transforms."""


class CaseError(ValueError):
    """A simulated case folder that cannot be read: the message names the file and the problem."""


class SimulatedCase(NamedTuple):
    """A simulated case as the reconstruction sees it, with its truth.

    Attributes:
        name: The folder's name.
        stacks: The prepared stacks (scanner frame).
        slices: Their slices at their scanner poses.
        truth: (N, 4, 4) float64 each slice's true canonical pose (of its file's k-plane).
        volume: The ground-truth brain in canonical space (the frame of ``truth``).
    """

    name: str
    stacks: list[Stack]
    slices: SliceSet
    truth: Tensor
    volume: CanonicalVolume


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        problem = "missing (not a simulated case folder: see svr simulate)"
        raise CaseError(f"{path}: {problem}") from None
    except (OSError, ValueError) as err:
        raise CaseError(f"{path}: unreadable JSON ({err})") from err


def load_case(folder: str | os.PathLike[str]) -> SimulatedCase:
    """Read a simulated case folder (module docstring) with every slice's truth.

    Args:
        folder: The case's folder.

    Returns:
        The case; the slices are the stacks' (cropped to their masks, as reconstruction does).

    Raises:
        CaseError: Naming the file, for a missing or unreadable file, a stack without its mask
            or truth, or slices whose truths disagree on the scanner -> atlas transform.
        ImageError: For an unreadable image (from the readers).
    """
    root = Path(folder)
    info = _read_json(root / "case.json")
    truth_file = root / "truth_slices.json"
    truth = {Path(s["file"]).name: s["slices"] for s in _read_json(truth_file)["stacks"]}
    stack_paths = sorted((root / "stacks").glob("*.nii*"))
    if not stack_paths:
        raise CaseError(f"{root / 'stacks'}: no stacks (*.nii.gz)")
    mask_paths = []
    for path in stack_paths:
        stem = path.name.split(".nii")[0]
        mask_path = next(iter(sorted((root / "masks").glob(f"{stem}_mask.nii*"))), None)
        if mask_path is None:
            raise CaseError(f"{root / 'masks'}: no {stem}_mask.nii.gz for {path}")
        if path.name not in truth:
            raise CaseError(f"{truth_file}: no entry for {path.name}")
        mask_paths.append(mask_path)
    thickness = info.get("thickness")
    stacks = load_stacks(stack_paths, mask_paths, thickness)
    slices = extract_slices(stacks)
    atlas, scanner = [], []
    for sid, k in zip(slices.stack_ids.tolist(), slices.slice_indices.tolist(), strict=True):
        entry = truth[Path(slices.stack_names[sid]).name][int(k)]
        atlas.append(pose_from_json(entry["atlas"]))
        scanner.append(pose_from_json(entry["scanner"]))
    atlas_poses, scanner_poses = torch.stack(atlas), torch.stack(scanner)
    # The ground truth volume lies in the scanner frame; every slice's truth gives the same
    # scanner -> atlas transform.
    each = se3_compose(atlas_poses, se3_inverse(scanner_poses))
    spread = max(
        float(rotation_angle(each, each[:1].expand_as(each)).max()),
        float((each[:, :3, 3] - each[:1, :3, 3]).norm(dim=1).max()) / 100.0,
    )
    if spread > FRAME_TOLERANCE:
        raise CaseError(
            f"{truth_file}: the slices' atlas and scanner poses disagree ({spread:.3g})"
        )
    centre = torch.tensor(info["atlas_centre_mm"], dtype=torch.float64)
    atlas_from_scanner = each[0]
    volume, mask = load_nifti(root / "gt_volume.nii.gz"), load_nifti(root / "gt_mask.nii.gz")
    affine = atlas_from_scanner @ volume.affine.to(torch.float64)
    scaled = canonicalize(
        Image(volume.data, affine), Image(mask.data, affine), name=str(root / "gt_volume.nii.gz")
    )
    affine[:3, 3] -= centre
    canonical = CanonicalVolume(
        Image(scaled.image.data, affine), scaled.mask, centre, scaled.intensity_scale
    )
    atlas_poses[:, :3, 3] -= centre
    return SimulatedCase(root.name, stacks, slices, atlas_poses, canonical)


def packet_starts(
    model: StackPoseNet, case: SimulatedCase, packets: int, restart_deg: float
) -> Tensor:
    """(N, 4, 4) float64 each slice's canonical start: its packet placed by the network alone.

    Args:
        model: The stack-pose network.
        case: The case (:func:`load_case`).
        packets: Interleaved packets per stack (1: each slice placed by its stack's transform).
        restart_deg: The network's restarts about each stack's choice (degrees).

    Returns:
        The poses of the slices' k-planes, comparable with ``case.truth``.
    """
    placement = network_placement(case.stacks, model, packets, restart_deg)
    per_packet = placement.packet_to_canonical
    if per_packet is None:
        per_packet = placement.to_canonical[:, None]
    return plane_poses(case.slices, placed_by_packets(case.slices, per_packet))
