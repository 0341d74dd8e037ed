"""The deformable step of ``svr segment-volume``: SimpleITK demons (shipped) against a B-spline fit.

One atlas (Wu GA 27) registered to one case (``gt-wu28`` of ``bench_tissue.py --prepare``) on the
1.6 mm registration grid after the same affine step; prints each step's time and the correlation
it reaches::

    python benchmarks/experiments/tissue_bspline.py --iterations 20
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk  # noqa: N813

import svr.tissue.registration as reg
from svr.image import load_nifti
from svr.tissue.sitk_images import to_sitk

ROOT = Path(__file__).resolve().parents[2]


def _brain(volume: Path, mask: Path | None) -> tuple[sitk.Image, sitk.Image]:
    image = load_nifti(volume)
    inside = image.data.numpy() > 0 if mask is None else load_nifti(mask).data.numpy() > 0.5
    grid = reg._down(to_sitk(image.data.numpy() * inside, image.affine.numpy()), 1.6)
    brain = to_sitk(inside.astype(np.uint8), image.affine.numpy())
    return grid, reg.resample_like(brain, grid, interpolator=sitk.sitkNearestNeighbor) > 0.5


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--case", type=Path, default=ROOT / "runs" / "tissue-cases" / "gt-wu28")
    parser.add_argument("--atlas", type=Path, default=Path("/work/atlases/wu/GA27_wu"))
    parser.add_argument("--iterations", type=int, default=20, help="L-BFGS-B iterations")
    parser.add_argument("--mesh-mm", type=float, default=8.0, help="B-spline control spacing")
    args = parser.parse_args()
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    fixed, fixed_mask = _brain(args.case / "volume.nii.gz", None)
    moving, moving_mask = _brain(args.atlas / "srr.nii.gz", args.atlas / "mask.nii.gz")
    affine = reg.affine_register(fixed, moving, fixed_mask, moving_mask, 60)
    moved = reg.resample_like(moving, fixed, affine)
    print(f"affine: NCC {reg.ncc(fixed, moved, fixed_mask):.3f}")
    start = time.perf_counter()
    demons = reg.deformable_register(fixed, moved, fixed_mask, reg.AtlasRegistrationConfig())
    seconds = time.perf_counter() - start
    score = reg.ncc(fixed, reg.resample_like(moved, fixed, demons), fixed_mask)
    print(f"demons (shipped): {seconds:.1f} s, NCC {score:.3f}")
    size = zip(fixed.GetSize(), fixed.GetSpacing(), strict=True)
    mesh = [max(2, round(n * step / args.mesh_mm)) for n, step in size]
    bspline = sitk.BSplineTransformInitializer(fixed, mesh)
    method = reg.correlation_method(fixed_mask)
    method.SetOptimizerAsLBFGSB(
        gradientConvergenceTolerance=1e-5, numberOfIterations=args.iterations
    )
    method.SetInitialTransform(bspline, inPlace=True)
    start = time.perf_counter()
    method.Execute(fixed, moved)
    seconds_b = time.perf_counter() - start
    score_b = reg.ncc(fixed, reg.resample_like(moved, fixed, bspline), fixed_mask)
    print(
        f"B-spline ({bspline.GetNumberOfParameters()} parameters, {args.iterations} iterations): "
        f"{seconds_b:.1f} s, NCC {score_b:.3f}; "
        f"time ratio B-spline / demons {seconds_b / seconds:.1f}"
    )


if __name__ == "__main__":
    main()
