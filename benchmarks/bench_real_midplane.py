"""Is a canonical output levelled on the brain's own mid-sagittal plane? An independent check.

Two of an output frame's three degrees of freedom (roll and yaw) are fixed by anatomy alone: the
brain's mid-sagittal plane is the canonical plane ``x = 0``. ``svr reconstruct`` levels its
canonical output on that plane with its own estimator
(:func:`svr.sampling.mirror_planes.measure_reflection_plane`). This measures the plane with one
that shares no code with it (:mod:`midplane_oracle`: SimpleITK's rigid registration of the
volume to its mirror image) and reports, per output, the mirror correlation and the angle
between the brain's mid-sagittal normal and

- the first axis of the output's voxel grid (the frame the volume was reconstructed in, before
  its last turns onto an atlas and onto the mid-sagittal plane), and
- the output's canonical ``x`` axis (its world frame): the roll and yaw error that remains.

``--validate`` first checks the oracle on atlas brains turned by known rotations (its error
against the turned normal, in degrees). Run from the repository root (about 1 minute per
volume, 2-3 per atlas, on one core)::

    python benchmarks/bench_real_midplane.py --validate ATLAS_AGE [...] \
        --volumes OUTPUT.nii.gz [...] [--results PATH]
"""

from __future__ import annotations

import argparse
import datetime
import math
from pathlib import Path

import nibabel as nib
import numpy as np
from bench_common import write_results
from midplane_oracle import midplane_of_array, midplane_of_file
from scipy.ndimage import affine_transform
from scipy.spatial.transform import Rotation

TURNS_DEG = ((0.0, 15.0, 0.0), (0.0, 0.0, 12.0), (10.0, 20.0, -8.0), (5.0, -18.0, 10.0))
"""Known turns (x, y, z Euler angles, degrees) of the validation brains."""


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) between two lines (unit vectors, sign ignored)."""
    return math.degrees(math.acos(min(1.0, abs(float(a @ b)))))


def validation_rows(folders: list[Path], threads: int) -> list[str]:
    """The oracle on each atlas brain as it is and turned by each of :data:`TURNS_DEG`."""
    rows = []
    for folder in folders:
        image = nib.load(str(folder / "srr.nii.gz"))
        mask = np.asarray(nib.load(str(folder / "mask.nii.gz")).dataobj) > 0
        data = np.asarray(image.dataobj, dtype=np.float32) * mask
        spacing = np.linalg.norm(image.affine[:3, :3], axis=0)
        plain = midplane_of_array(data, spacing, threads)
        centre = (np.array(data.shape) - 1) / 2
        for turn in TURNS_DEG:
            rotation = Rotation.from_euler("xyz", turn, degrees=True).as_matrix()
            # out(p) = in(R^T (p - c) + c), in mm: the brain turned by R about the centre
            index = np.diag(1 / spacing) @ rotation.T @ np.diag(spacing)
            turned = affine_transform(data, index, offset=centre - index @ centre, order=1)
            estimate = midplane_of_array(turned, spacing, threads)
            error = _angle_deg(estimate.normal, rotation @ plain.normal)
            expected = _angle_deg(rotation @ plain.normal, np.array([1.0, 0.0, 0.0]))
            rows.append(
                f"| {folder.parent.name}/{folder.name} | {plain.correlation:.3f} | "
                f"{', '.join(f'{t:g}' for t in turn)} | {expected:.1f} | {estimate.tilt_deg:.1f} "
                f"| **{error:.2f}** | {estimate.correlation:.3f} |"
            )
            print(rows[-1], flush=True)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--validate", type=Path, nargs="*", default=[], help="atlas age folders")
    parser.add_argument("--volumes", type=Path, nargs="*", default=[], help="outputs to measure")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--results", type=Path, help="also write the tables here (markdown)")
    args = parser.parse_args()
    lines: list[str] = []
    if args.validate:
        lines += [
            "| brain | its mirror correlation | turn (x, y, z deg) | true tilt (deg) "
            "| measured tilt (deg) | error of the normal (deg) | correlation |",
            "|---|---:|---|---:|---:|---:|---:|",
            *validation_rows(args.validate, args.threads),
            "",
        ]
    rows = []
    for path in args.volumes:
        estimate, normal = midplane_of_file(path, args.threads)
        tilt = _angle_deg(normal, np.array([1.0, 0.0, 0.0]))
        rows.append(
            f"| {path.name} | {estimate.correlation:.3f} | {estimate.tilt_deg:.1f} "
            f"| **{tilt:.1f}** |"
        )
        print(rows[-1], flush=True)
    if rows:
        lines += [
            "| output | mirror correlation | brain's mid-sagittal normal from the grid's first "
            "axis (deg) | from the output's x axis (deg) |",
            "|---|---:|---:|---:|",
            *rows,
        ]
    text = "\n".join(lines)
    print(text)
    if args.results is not None:
        write_results(
            args.results,
            "The real scan's mid-sagittal plane",
            text,
            f" ({datetime.date.today().isoformat()}, the 2-core VM)",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
