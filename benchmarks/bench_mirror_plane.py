"""The brain's mirror plane in reconstructed volumes: the verdict's evidence, file by file.

For each volume (a ``svr reconstruct`` output, canonical or scanner frame; voxels > 0 are the
brain) this prints the best mirror plane near the frame's ``x = 0``
(:func:`svr.sampling.mirror_planes.measure_reflection_plane`, what levels a canonical output) and
in any orientation (:func:`svr.sampling.mirror_planes.search_reflection_plane`, what the verdict
falls back to): each one's correlation, its angle from ``x = 0`` and its seconds. With
``--psnr-from`` the yardstick's PSNR of each volume is read from the ``bench_reconstruct.py``
logs given (the line after the one that wrote it), so that the correlation can be set beside
the volume's quality. The verdict calls a volume whose best plane anywhere correlates below
:data:`svr.reconstruction.midplane.MIDPLANE_MIN_CORRELATION` not a recognisable brain.

    python benchmarks/bench_mirror_plane.py runs/*/*-cnn-*.nii.gz \
        --psnr-from runs/bench-*.log [--results OUT.md]
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

import torch
from bench_common import write_results

from svr.geometry.mirror import SAGITTAL
from svr.image import load_nifti
from svr.reconstruction.midplane import MIDPLANE_MIN_CORRELATION, symmetry_volume
from svr.sampling.mirror_planes import measure_reflection_plane, search_reflection_plane
from svr.sampling.volume import CanonicalVolume

WROTE = re.compile(r"wrote (\S+\.nii\.gz)")
SCORE = re.compile(r"\S+ \w+: \{'psnr': ([-\d.]+)")


def psnr_by_volume(logs: list[Path]) -> dict[str, float]:
    """PSNR of each volume a ``bench_reconstruct.py`` log wrote, by the path it printed."""
    found: dict[str, float] = {}
    for log in logs:
        last = None
        for line in log.read_text(encoding="utf-8", errors="replace").splitlines():
            wrote, score = WROTE.match(line), SCORE.match(line)
            if wrote:
                last = wrote.group(1)
            elif score and last:
                found[last], last = float(score.group(1)), None
    return found


def brain(path: Path) -> CanonicalVolume:
    """The volume's voxels > 0 as the brain (``symmetry_volume``)."""
    volume = load_nifti(path)
    brain = symmetry_volume(volume, volume.data > 0)
    if brain is None:
        raise SystemExit(f"{path}: fewer than 100 voxels > 0; not a reconstructed volume")
    return brain


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("volumes", type=Path, nargs="+")
    parser.add_argument("--psnr-from", type=Path, nargs="*", default=[])
    parser.add_argument("--results", type=Path, help="also write the table here (markdown)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    psnr = psnr_by_volume(args.psnr_from)
    rows = []
    for path in args.volumes:
        volume = brain(path)
        began = time.perf_counter()
        near = measure_reflection_plane(volume)
        middle = time.perf_counter()
        anywhere = search_reflection_plane(volume)
        ended = time.perf_counter()
        score = psnr.get(str(path))
        rows.append(
            f"| {path} | {'' if score is None else f'{score:.2f}'} | "
            f"{near.correlation:.3f} | {near.plane.angle_to_deg(SAGITTAL):.1f} | "
            f"{middle - began:.1f} | {anywhere.correlation:.3f} | "
            f"{anywhere.plane.angle_to_deg(SAGITTAL):.1f} | {ended - middle:.1f} | "
            f"{'no' if anywhere.correlation < MIDPLANE_MIN_CORRELATION else 'yes'} |"
        )
        print(rows[-1], flush=True)
    text = "\n".join(
        [
            "| volume | PSNR (dB) | near x = 0: correlation | tilt (deg) | s | any orientation: "
            "correlation | tilt (deg) | s | a clear plane |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---|",
            *rows,
        ]
    )
    print(text)
    if args.results is not None:
        write_results(args.results, "The brain's mirror plane in reconstructed volumes", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
