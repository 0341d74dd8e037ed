"""A bench case with its masks loosened as automatic masks of whole-uterus scans are.

Copies a case folder (``stacks/``, ``masks/``, the ground truth) with every stack's mask loosened
by :func:`svr.sampling.artefacts.loose_mask` (the edge moved in and out by a smooth random field up
to ``--reach-mm``, the tissue taken in filled into the stack too), so that
``benchmarks/bench_reconstruct.py --data OUT_PARENT --cases NAME`` scores a reconstruction from
such masks against the same truth. Result: ``benchmarks/results/loose-masks.md``.

Usage::

    python benchmarks/experiments/loose_mask_case.py --case ../shared/data/bench/sb28-moderate \
        --out runs/loose-cases/sb28-moderate-loose10 --reach-mm 10 --seed 0
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import torch

from svr.image import Image, load_nifti, save_nifti
from svr.sampling.artefacts import loose_mask


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", type=Path, required=True, help="a bench case folder")
    parser.add_argument("--out", type=Path, required=True, help="the loosened copy (new)")
    parser.add_argument("--reach-mm", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.out.exists():
        parser.error(f"--out {args.out}: exists; remove it first")
    shutil.copytree(args.case, args.out)
    generator = torch.Generator().manual_seed(args.seed)
    dice = []
    for stack_path in sorted((args.out / "stacks").glob("*.nii.gz")):
        mask_path = args.out / "masks" / stack_path.name.replace(".nii.gz", "_mask.nii.gz")
        stack, mask = load_nifti(stack_path), load_nifti(mask_path)
        exact = mask.data > 0.5
        loose, data = loose_mask(exact, stack.data, stack.spacing, args.reach_mm, generator)
        save_nifti(Image(data, stack.affine), stack_path, overwrite=True)  # the copy
        save_nifti(Image(loose.float(), mask.affine), mask_path, overwrite=True)
        dice.append(float(2 * (loose & exact).sum() / (loose.sum() + exact.sum())))
    print(f"wrote {args.out}: mask Dice with the case's own " + ", ".join(f"{d:.3f}" for d in dice))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
