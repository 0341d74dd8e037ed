"""Per-slice start errors when the stack-pose network places windows of each packet's slices.

The "in sequence" structure with the network we ship: each interleaved packet cut into windows of
``W`` consecutive slices in acquisition order, each window placed by
:func:`~svr.reconstruction.initialisation.stack_pose.estimate_packet_poses` from its own slices
(the stack's pose a candidate), beside the stack's pose alone and the whole packets (today's
start). ``W = 1`` is the single-slice baseline. Errors against the case's truth after removing
one rigid offset of the whole frame. Result: ``benchmarks/results/slice-refiner.md``.

Usage::

    python benchmarks/experiments/packet_windows.py CASE_DIR [CASE_DIR ...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from svr.geometry import rotation_angle, se3_compose, se3_inverse
from svr.geometry.averaging import robust_mean_pose
from svr.models.stack_pose import load_stack_pose_model
from svr.reconstruction.initialisation.stack_pose import (
    estimate_packet_poses,
    estimate_stack_pose,
)
from svr.reconstruction.slices import SliceSet, extract_slices
from svr.reconstruction.stacks import load_stacks

WINDOWS = (0, 8, 5, 3, 1)  # 0: the whole packet


def truth_poses(case: Path, slices: SliceSet) -> torch.Tensor:
    """(N, 4, 4) each slice's true pose in the atlas frame, from ``truth_slices.json``."""
    truth = json.loads((case / "truth_slices.json").read_text())
    out = []
    for sid, k in zip(slices.stack_ids.tolist(), slices.slice_indices.tolist(), strict=True):
        name = Path(slices.stack_names[sid]).name
        stack = next(s for s in truth["stacks"] if Path(s["file"]).name == name)
        pose = stack["slices"][int(k)]["atlas"]
        matrix = torch.eye(4, dtype=torch.float64)
        matrix[:3, :3] = torch.tensor(pose["R"])
        matrix[:3, 3] = torch.tensor(pose["t"])
        out.append(matrix)
    return torch.stack(out)


def errors_deg(estimate: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """(N,) rotation errors (deg) after the one rigid offset that best aligns the frames."""
    offset = robust_mean_pose(se3_compose(truth, se3_inverse(estimate)))
    return torch.rad2deg(rotation_angle(se3_compose(offset[None], estimate), truth))


def main() -> None:
    """Print each start's per-slice error summary for every case given."""
    torch.set_num_threads(1)
    model = load_stack_pose_model("stack-pose")
    for case in map(Path, sys.argv[1:]):
        stack_paths = sorted((case / "stacks").glob("*.nii.gz"))
        mask_paths = [
            case / "masks" / p.name.replace(".nii.gz", "_mask.nii.gz") for p in stack_paths
        ]
        stacks = load_stacks(stack_paths, mask_paths, 3.0)
        slices = extract_slices(stacks)
        truth = truth_poses(case, slices)
        scanner = slices.poses.double()
        ids = slices.stack_ids
        masks = [s.mask.data > 0.5 for s in stacks]
        stack_transforms = [
            estimate_stack_pose(model, s.image, m, restart_deg=10.0).to_canonical
            for s, m in zip(stacks, masks, strict=True)
        ]
        starts = {"stack": (se3_compose(torch.stack(stack_transforms)[ids], scanner), 0.0)}
        for window in WINDOWS:
            began = time.time()
            transforms = torch.empty(len(slices), 4, 4, dtype=torch.float64)
            for sid, stack in enumerate(stacks):
                k = stack.k_indices.cpu()
                group = k % 2 if window == 0 else (k % 2) * 1000 + (k // 2) // window
                _, group = torch.unique(group, return_inverse=True)
                placed = estimate_packet_poses(
                    model, stack.image, masks[sid], stack_transforms[sid], group
                )
                plane = {int(kk): i for i, kk in enumerate(k.tolist())}
                mine = ids == sid
                rows = [plane[int(kk)] for kk in slices.slice_indices[mine].tolist()]
                transforms[mine] = placed.to_canonical[group[rows]]
            name = f"window {window}" if window else "whole packets"
            starts[name] = (se3_compose(transforms, scanner), time.time() - began)
        for name, (poses, seconds) in starts.items():
            error = errors_deg(poses, truth)
            within10 = 100 * float((error <= 10).double().mean())
            within5 = 100 * float((error <= 5).double().mean())
            print(
                f"{case.name} {name}: median {error.median():.1f} deg, <=10 {within10:.0f}%, "
                f"<=5 {within5:.0f}% ({seconds:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
