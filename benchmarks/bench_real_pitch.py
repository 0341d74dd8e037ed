"""Can an atlas tell a real reconstruction's pitch? An independent check of the output frames.

The real scan's output frame is measured against a reference frame whose views were looked at
(``bench_real_frame.py``). Roll and yaw are checked by the brain's mirror symmetry
(``bench_real_midplane.py``); pitch, the turn about the left-right axis, is not. This measures,
with SimpleITK only (no library code), three things:

1. **The frames of two outputs, checked against their volumes.** Each canonical output's frame
   ``G`` (canonical mm -> the stacks' scanner mm, :func:`bench_common.scanner_from_canonical`)
   predicts how its volume lies relative to another output's: ``G_a^-1 G_b``. The volumes are
   registered to each other directly (rigid, correlation) and the two rotations compared.
2. **Where the pitch of each output would go on an atlas.** Each atlas (fixed, its brain mask
   dilated) is registered rigidly to the output (Mattes mutual information, three resolutions)
   from starts turned about the left-right axis by -10..+10 degrees; the table gives where each
   fit ends (its pitch) and the metric there. A sharp optimum sends every start to one pitch;
   a flat one leaves each fit near its start.
3. **A control:** the same on an atlas brain of one family (in its canonical frame) against an
   atlas of another.

Every image is resampled onto a grid of its own world axes (RAS mm) before SimpleITK sees it, so
physical points are the NIfTI world's (no LPS conversion). Run from the repository root, after
``bench_real_frame.py`` wrote its outputs (about 5 minutes on one core)::

    python benchmarks/bench_real_pitch.py --volumes runs/real-frame/real-cnn-manual-1t.nii.gz \
        runs/real-frame/real-cnn-auto-1t.nii.gz --atlases FIDON/GA28_operated CRL/GA28_crl \
        WU/GA28_wu [--pair VOLUME ATLAS ...] --control WU/GA28_wu CRL/GA28_crl [--results FILE]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
from pathlib import Path

import numpy as np
import SimpleITK as sitk  # noqa: N813 (the usual alias)
from bench_common import scanner_from_canonical, write_results
from bench_real_frame import REFERENCE
from midplane_oracle import world_image
from scipy.spatial.transform import Rotation

PITCH_STARTS_DEG = (-10.0, -5.0, 0.0, 5.0, 10.0)
"""Starting turns of each atlas fit about the left-right (canonical x) axis, degrees."""


def _matrix(transform: sitk.Euler3DTransform) -> np.ndarray:
    """(4, 4) the transform's map of fixed points to moving points (physical mm)."""
    rotation = np.array(transform.GetMatrix()).reshape(3, 3)
    centre, shift = np.array(transform.GetCenter()), np.array(transform.GetTranslation())
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = centre + shift - rotation @ centre
    return out


def register(
    fixed: sitk.Image,
    moving: sitk.Image,
    pitch_deg: float = 0.0,
    fixed_mask: sitk.Image | None = None,
    metric: str = "mi",
) -> tuple[float, np.ndarray]:
    """Rigid registration: (final metric, (4, 4) transform of fixed points to moving points).

    The start is turned about x by ``pitch_deg`` about the images' centres of mass.
    """
    start = sitk.Euler3DTransform(
        sitk.CenteredTransformInitializer(
            fixed, moving, sitk.Euler3DTransform(), sitk.CenteredTransformInitializerFilter.MOMENTS
        )
    )
    start.SetRotation(math.radians(pitch_deg), 0.0, 0.0)
    method = sitk.ImageRegistrationMethod()
    if metric == "mi":
        method.SetMetricAsMattesMutualInformation(32)
    else:
        method.SetMetricAsCorrelation()
    if fixed_mask is not None:
        method.SetMetricFixedMask(fixed_mask)
    method.SetMetricSamplingStrategy(method.RANDOM)
    method.SetMetricSamplingPercentage(0.3, 1)
    method.SetInterpolator(sitk.sitkLinear)
    method.SetOptimizerAsRegularStepGradientDescent(1.0, 1e-5, 300, relaxationFactor=0.6)
    method.SetOptimizerScalesFromPhysicalShift()
    method.SetShrinkFactorsPerLevel([4, 2, 1])
    method.SetSmoothingSigmasPerLevel([2.0, 1.0, 0.0])
    method.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    method.SetInitialTransform(start, inPlace=True)
    method.Execute(fixed, moving)
    return float(method.GetMetricValue()), _matrix(start)


def rotvec_deg(rotation: np.ndarray) -> np.ndarray:
    """(3,) rotation vector (degrees) of a (3, 3) rotation: about x (pitch), y, z."""
    return np.degrees(Rotation.from_matrix(rotation).as_rotvec())


def _fmt(v: np.ndarray) -> str:
    return ", ".join(f"{x:+.1f}" for x in v)


def frame_rows(volumes: list[Path], reference: np.ndarray) -> list[str]:
    """Table 1: each output's frame against the reference, and each pair checked on volumes."""
    frames = [
        scanner_from_canonical(v.with_name(v.name.replace(".nii.gz", ".csv"))) for v in volumes
    ]
    rows = [
        "| output | frame vs reference: turn about x, y, z (deg) | angle (deg) |",
        "|---|---|---:|",
    ]
    for volume, frame in zip(volumes, frames, strict=True):
        turn = rotvec_deg(reference[:3, :3].T @ frame[:3, :3])
        rows.append(f"| {volume.name} | {_fmt(turn)} | {np.linalg.norm(turn):.1f} |")
    rows += [
        "",
        "| fixed | moving | predicted by the frames: turn about x, y, z (deg) | registered "
        "volumes (correlation) | difference (deg) |",
        "|---|---|---|---|---:|",
    ]
    for i in range(len(volumes)):
        for j in range(i + 1, len(volumes)):
            predicted = np.linalg.inv(frames[j]) @ frames[i]  # canonical_i -> canonical_j
            fixed, moving = world_image(volumes[i]), world_image(volumes[j])
            value, found = register(fixed, moving, fixed_mask=fixed > 0, metric="correlation")
            gap = np.linalg.norm(rotvec_deg(predicted[:3, :3].T @ found[:3, :3]))
            rows.append(
                f"| {volumes[i].name} | {volumes[j].name} | {_fmt(rotvec_deg(predicted[:3, :3]))} "
                f"| {_fmt(rotvec_deg(found[:3, :3]))} ({-value:.3f}) | {gap:.1f} |"
            )
            print(rows[-1], flush=True)
    return rows


def pitch_row(volume: Path, atlas: Path) -> str:
    """Table 2's row: where each pitch start of ``atlas``'s fit to ``volume`` ends."""
    fixed = world_image(atlas / "srr.nii.gz")
    mask = world_image(atlas / "srr.nii.gz", mask=atlas / "mask.nii.gz") > 0.5
    mask = sitk.BinaryDilate(mask, [3, 3, 3])
    moving = world_image(volume)
    ends, metrics = [], []
    for start in PITCH_STARTS_DEG:
        value, found = register(fixed, moving, start, mask)
        ends.append(rotvec_deg(found[:3, :3])[0])
        metrics.append(-value)
    best = int(np.argmax(metrics))
    cells = " ".join(f"{s:+.0f}->{e:+.1f}" for s, e in zip(PITCH_STARTS_DEG, ends, strict=True))
    name = volume.parent.name if volume.name == "srr.nii.gz" else volume.name
    row = (
        f"| {name} | {atlas.name} | {cells} | {max(ends) - min(ends):.1f} | "
        f"{ends[best]:+.1f} | {max(metrics):.3f} | {max(metrics) - min(metrics):.3f} |"
    )
    print(row, flush=True)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--volumes",
        type=Path,
        nargs="+",
        default=[],
        help="the real scan's canonical outputs of svr reconstruct (their .csv beside): their "
        "frames against the reference and each other, and their pitch on each of --atlases",
    )
    parser.add_argument(
        "--atlases",
        type=Path,
        nargs="+",
        default=[],
        help="atlas age folders (srr.nii.gz, mask.nii.gz)",
    )
    parser.add_argument(
        "--pair",
        type=Path,
        nargs=2,
        action="append",
        default=[],
        metavar=("VOLUME", "ATLAS"),
        help="also the pitch of another volume on its atlas (repeatable): a simulated brain's",
    )
    parser.add_argument(
        "--control",
        type=Path,
        nargs=2,
        metavar=("BRAIN", "ATLAS"),
        help="an atlas age folder as the volume, and an atlas of another family",
    )
    parser.add_argument("--reference", type=Path, default=REFERENCE)
    parser.add_argument("--results", type=Path, help="also write the tables here (markdown)")
    args = parser.parse_args()
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    reference = np.asarray(
        json.loads(args.reference.read_text(encoding="utf-8"))["scanner_from_canonical"]
    )
    lines = frame_rows(args.volumes, reference) if args.volumes else []
    lines += [
        "",
        "| volume | atlas | pitch start -> end (deg) | spread of the ends (deg) | pitch at the "
        "best metric (deg) | best mutual information | its range over the starts |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for volume in args.volumes:
        lines += [pitch_row(volume, atlas) for atlas in args.atlases]
    lines += [pitch_row(volume, atlas) for volume, atlas in args.pair]
    if args.control is not None:
        lines.append(pitch_row(args.control[0] / "srr.nii.gz", args.control[1]))
    text = "\n".join(lines)
    print(text)
    if args.results is not None:
        write_results(
            args.results,
            "Can an atlas tell the real scan's pitch?",
            text,
            f" ({datetime.date.today().isoformat()}, the 2-core VM, one thread)",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
