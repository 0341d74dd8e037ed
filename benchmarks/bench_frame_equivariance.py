"""Where a canonical-frame output loses against ``stack``: the reconstruction or the yardstick?

Two measurements on one bench case:

1. **Reconstruction under a change of frame.** The same start (the case's stack registration)
   reconstructed twice: in the scanner frame, and with every pose moved by a rigid ``G`` (a turn
   of ``--degrees`` about an oblique axis and a shift), as ``--registration cnn`` does when every
   stack keeps stack registration. The second volume is relabelled back by ``G^-1`` (its affine
   only, no resampling) and both are scored by the shared yardstick. Equal scores mean the grid,
   the rounds and the regularisation do not care which frame they run in.
2. **The yardstick under a change of frame.** One finished volume written again with only its
   affine premultiplied by rigid transforms (random rotations, the atlas orientation of the case,
   and that turned by 16 degrees; all with a shift), each scored. The array is the same, so any
   spread is the yardstick's registration finding different alignments.

Run from the repository root::

    python benchmarks/bench_frame_equivariance.py [--case sb24-large] [--schedule fixed]
        [--degrees 16] [--volume runs/.../sb24-large-stack-adaptive.nii.gz]
        [--results benchmarks/results/frame-equivariance.md]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from bench_common import SHARED, load_case_stacks, run_scorer
from scipy.spatial.transform import Rotation

from svr.image import Image
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.outputs import write_volume
from svr.reconstruction.pipeline import reconstruct_from_poses
from svr.reconstruction.registration import stack_registration
from svr.reconstruction.slices import extract_slices


def rigid(rotation: np.ndarray, shift: tuple[float, float, float]) -> np.ndarray:
    """(4, 4) float64 rigid transform."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = shift
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="sb24-large")
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument("--scorer", type=Path, default=SHARED / "tools" / "score_recon.py")
    parser.add_argument("--schedule", default="fixed", choices=("fixed", "adaptive"))
    parser.add_argument("--degrees", type=float, default=16.0)
    parser.add_argument("--volume", type=Path, help="the finished volume for part 2")
    parser.add_argument("--rotations", type=int, default=4, help="random rotations in part 2")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--results", type=Path)
    args = parser.parse_args()
    case = args.data / args.case
    if not (case / "gt_volume.nii.gz").exists():
        print(f"{case}: bench case with gt_volume.nii.gz not found", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    lines = [
        "# Reconstruction and yardstick under a change of frame",
        "",
        "Command: `python benchmarks/" + " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]) + "`",
        "",
        f"## 1. The same start reconstructed in two frames ({args.case}, {args.schedule} schedule)",
        "",
        "| frame | PSNR (dB) | SSIM | NCC | mean slice NCC |",
        "|---|---:|---:|---:|---:|",
    ]
    print("\n".join(lines), flush=True)
    axis = np.array([0.6, -0.5, 0.62])
    turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(args.degrees))
    G = torch.from_numpy(rigid(turn.as_matrix(), (3.0, -2.0, 5.0)))
    stacks = load_case_stacks(case)
    config = ReconstructionConfig.preset("stack", args.schedule)
    slices = extract_slices(stacks)
    registered, _ = stack_registration(
        slices, config.initialisation_grid_mm, config.initialisation.template
    )
    with tempfile.TemporaryDirectory() as tmp:
        scores = {}
        for name, poses, frame in (
            ("scanner", registered, "scanner"),
            (f"turned by {args.degrees:g} deg (relabelled back)", G.to(registered) @ registered,
             "canonical"),
        ):  # fmt: skip
            result = reconstruct_from_poses(stacks, poses, frame, config, progress=False)
            volume = result.volume
            if frame == "canonical":
                volume = Image(volume.data, torch.linalg.inv(G).to(volume.affine) @ volume.affine)
            path = Path(tmp) / f"{frame}.nii.gz"
            write_volume(volume, path)
            s = scores[name] = run_scorer(args.scorer, path, case)
            line = (
                f"| {name} | {s['psnr']:.3f} | {s['ssim']:.4f} | {s['ncc']:.4f} | "
                f"{float(result.slice_ncc.mean()):.4f} |"
            )
            lines.append(line)
            print(line, flush=True)
        a, b = scores.values()
        verdict = f"Difference {b['psnr'] - a['psnr']:+.3f} dB, SSIM x{b['ssim'] / a['ssim']:.4f}."
        lines += ["", verdict]
        print("\n" + verdict, flush=True)
        if args.volume is not None:
            image = nib.load(args.volume)
            atlas = np.array(json.loads((case / "case.json").read_text())["scanner_from_atlas_R"]).T
            tests = [("identity", np.eye(3))]
            tests += [
                (f"random rotation {k}", Rotation.random(random_state=k).as_matrix())
                for k in range(args.rotations)
            ]
            tests += [
                ("atlas orientation", atlas),
                ("atlas orientation + 16 deg", turn.as_matrix() @ atlas),
            ]
            head = [
                "",
                f"## 2. One volume, only its affine turned (`{args.volume.name}`)",
                "",
                "| affine premultiplied by | angle (deg) | PSNR (dB) | SSIM | NCC |",
                "|---|---:|---:|---:|---:|",
            ]
            lines += head
            print("\n".join(head), flush=True)
            psnrs = []
            for name, rotation in tests:
                path = Path(tmp) / "turned.nii.gz"
                data = np.asarray(image.dataobj)
                transform = rigid(rotation, (20.0, -35.0, 12.0))
                nib.save(nib.Nifti1Image(data, transform @ image.affine), path)
                s = run_scorer(args.scorer, path, case)
                psnrs.append(s["psnr"])
                angle = math.degrees(Rotation.from_matrix(rotation).magnitude())
                line = (
                    f"| {name} | {angle:.0f} | {s['psnr']:.3f} | {s['ssim']:.4f} | {s['ncc']:.4f} |"
                )
                lines.append(line)
                print(line, flush=True)
            spread = f"Same array: PSNR from {min(psnrs):.3f} to {max(psnrs):.3f} dB."
            lines += ["", spread]
            print("\n" + spread, flush=True)
    if args.results is not None:
        args.results.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
