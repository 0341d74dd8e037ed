"""Where the yardstick's score of one array depends on its frame: its registration, step by step.

``../shared/tools/score_recon.py`` registers a reconstruction to the case's truth (candidate
orientations scored at 3 mm, a short registration of the best eight, then a multi-resolution one
of the best two, each from its candidate start) before it scores it. For each volume given (the
same array written in two frames: a canonical output and its relabelled scanner-frame copy from
``bench_reconstruct.py``), this prints the registration metric (SimpleITK's correlation, negated)
of the best three coarse candidates, of the two final registrations, and the PSNR the tool
reports. Reads the shared tool's functions; changes nothing.

    python benchmarks/experiments/yardstick_registration.py CASE VOLUME [VOLUME ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk  # noqa: N813 (the usual alias)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_common import SHARED


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("case", type=Path, help="a case folder with the truth")
    parser.add_argument("volumes", type=Path, nargs="+", help="reconstructions of that case")
    parser.add_argument("--tools", type=Path, default=SHARED / "tools")
    args = parser.parse_args()
    sys.path.insert(0, str(args.tools))
    import score_recon as tool  # the shared yardstick

    gt = tool._read(str(args.case / "gt_volume.nii.gz"))
    mask = sitk.Cast(sitk.ReadImage(str(args.case / "gt_mask.nii.gz")), sitk.sitkUInt8)
    info = json.loads((args.case / "case.json").read_text(encoding="utf-8"))
    rotation = np.array(info["scanner_from_atlas_R"])
    flip = np.diag([-1.0, -1.0, 1.0])
    for volume in args.volumes:
        rec = tool._read(str(volume))
        starts = [np.eye(3), flip @ rotation.T @ flip, flip @ rotation @ flip, rotation, rotation.T]
        starts += [r for r in tool._cube_rotations() if not np.allclose(r, np.eye(3))]
        starts += tool._axes_rotations(gt, mask, rec) + list(tool._grid_rotations())
        scored = sorted((v, i) for i, v in enumerate(tool._evaluate_many(gt, mask, rec, starts)))
        coarse = sorted(
            (tool._register(gt, mask, rec, starts[i], [4], 60)[0], i) for _, i in scored[:8]
        )
        final = [tool._register(gt, mask, rec, starts[i], [4, 2, 1], 300)[0] for _, i in coarse[:2]]
        psnr = tool.score(str(volume), str(args.case))["psnr"]
        print(
            f"{volume.name}: coarse best {', '.join(f'{v:.4f}' for v, _ in coarse[:3])}; "
            f"final {', '.join(f'{v:.4f}' for v in final)}; PSNR {psnr:.2f} dB",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
