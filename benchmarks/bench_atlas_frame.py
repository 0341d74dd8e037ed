"""How close an atlas of a neighbouring age can bring a volume to its true atlas frame.

``--registration cnn`` ends by a rigid fit of the finished volume to an atlas of about the fetus's
age (:func:`svr.reconstruction.atlas_frame.atlas_transform`). The benchmarks never give it the
atlas the case was simulated from, but a neighbouring age (``--atlas-offset 1``). This measures
what that choice alone costs, independent of the learned poses:

* **atlas against atlas**: each atlas of the set fitted rigidly to its neighbours from the
  identity (both are in canonical space): the angle between the two ages' canonical frames as
  the fit sees them;
* **the case's volume at its true frame**: each ``cnn`` output of a ``bench_reconstruct.py`` run
  relabelled into its true atlas frame (the robust mean of ``T_i o P_i^-1`` over its slices, as
  :func:`bench_common.true_frame_correction`), then fitted to the atlases of neighbouring ages from
  the identity: how far the fit moves a volume that is already right. The pipeline cannot end
  closer to the true frame than this on that atlas. The brain mask of a volume is where it is
  not zero (``reconstruct`` writes it through its coverage mask);
* **from any start**: the same volume turned by ``--turns`` degrees about random axes, then
  brought into the frame of the neighbouring-age atlas (``--atlas-offset``) by
  :func:`svr.reconstruction.atlas_frame.atlas_transform`: the error against the true frame, and
  the time it took. A real scan's stacks can
  leave the volume tens of degrees from canonical when the model is unsure of them.

Run from the repository root (after ``bench_reconstruct.py ... --registrations cnn --out RUN``)::

    python benchmarks/bench_atlas_frame.py --runs RUN [--cases sb24-large ...]
        [--simulated ga23-traj0.5-turn ...] [--threads 1] [--results PATH.md]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch
from bench_common import ATLAS, SHARED, case_age, neighbour_atlas, true_frame_correction

from svr.geometry import rotation_angle, se3_compose, se3_inverse, so3_exp
from svr.image import Image, load_nifti
from svr.reconstruction.atlas_fit import KEEP_MARGIN, AtlasFitConfig, atlas_levels, fit_to_atlas
from svr.reconstruction.atlas_frame import COARSE_FIT, atlas_starts, atlas_transform
from svr.sampling.volume import CanonicalVolume, atlas_volume_paths, load_canonical_volume

ROOT = Path(__file__).resolve().parents[1]
IDENTITY = torch.eye(4, dtype=torch.float64)


def degrees(transform: torch.Tensor) -> float:
    """Rotation angle of a (4, 4) transform, degrees."""
    return math.degrees(rotation_angle(transform, IDENTITY))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, required=True, help="a bench_reconstruct.py --out")
    parser.add_argument("--cases", nargs="*", default=["sb24-large", "sb28-moderate"])
    parser.add_argument("--simulated", nargs="*", default=[])
    parser.add_argument("--cases-dir", type=Path, default=ROOT / "runs" / "simulated-cases")
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument("--atlas", type=Path, default=ATLAS)
    parser.add_argument("--turns", type=float, nargs="*", default=[0.0, 30.0, 60.0, 120.0, 180.0])
    parser.add_argument("--atlas-offset", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--margins",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="fit every start finely and report the right frame's NCC against the best wrong one",
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--results", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    pairs = atlas_volume_paths(args.atlas)
    names = [v.parent.name for v, _ in pairs]
    ages = [float(name[2:4]) for name in names]
    atlases: dict[int, CanonicalVolume] = {}

    def atlas(index: int) -> CanonicalVolume:
        if index not in atlases:
            atlases[index] = load_canonical_volume(*pairs[index])
        return atlases[index]

    lines = [
        "## Atlas against atlas (each fitted to the next age from the identity)",
        "",
        "| atlas | fitted to | turn (deg) | shift (mm) | NCC |",
        "|---|---|---:|---:|---:|",
    ]
    for i in range(len(pairs) - 1):
        j = i + 1
        moving = atlas(i)
        fitted, ncc = fit_to_atlas(moving.image, moving.mask, IDENTITY, atlas(j))
        lines.append(
            f"| {names[i]} | {names[j]} | {degrees(fitted):.1f} | "
            f"{float(fitted[:3, 3].norm()):.1f} | {ncc:.3f} |"
        )
        print(lines[-1], flush=True)

    lines += [
        "",
        "## The case's cnn output placed at its true frame, fitted to neighbouring ages",
        "",
        "| case | output frame error | atlas | fit from the true frame turns (deg) | "
        "and shifts (mm) | NCC |",
        "|---|---|---|---:|---:|---:|",
    ]
    folders = [args.data / c for c in args.cases] + [args.cases_dir / c for c in args.simulated]
    for case in folders:
        stem = args.runs / f"{case.name}-cnn-adaptive"
        volume = load_nifti(Path(f"{stem}.nii.gz"))
        correction = true_frame_correction(case, Path(f"{stem}.csv"))
        error = degrees(correction)
        shift = float(correction[:3, 3].norm())
        placed = Image(volume.data, correction.to(volume.affine) @ volume.affine)
        data = volume.data.float()
        mask = data != 0  # the coverage mask the volume was written through
        age = case_age(case)
        near = sorted(
            (i for i, a in enumerate(ages) if abs(a - age) <= 1.0),
            key=lambda i: (ages[i], names[i]),
        )
        for i in near:
            fitted, ncc = fit_to_atlas(placed, mask, IDENTITY, atlas(i))
            own = " (the case's own)" if ages[i] == age else ""
            lines.append(
                f"| {case.name} | {error:.1f} deg / {shift:.1f} mm | {names[i]}{own} | "
                f"{degrees(fitted):.1f} | {float(fitted[:3, 3].norm()):.1f} | {ncc:.3f} |"
            )
            print(lines[-1], flush=True)

    def case_output(case: Path) -> tuple[Image, torch.Tensor, torch.Tensor, CanonicalVolume]:
        """A case's cnn output, its true-frame correction, coverage mask and neighbouring atlas."""
        stem = args.runs / f"{case.name}-cnn-adaptive"
        volume = load_nifti(Path(f"{stem}.nii.gz"))
        correction = true_frame_correction(case, Path(f"{stem}.csv"))
        mask = volume.data.float() != 0  # the coverage mask the volume was written through
        atlas_of = load_canonical_volume(
            *neighbour_atlas(case_age(case), args.atlas_offset, args.atlas)
        )
        return volume, correction, mask, atlas_of

    if args.margins:
        lines += [
            "",
            "## How much better the right frame fits than a wrong one (every start fitted finely)",
            "",
            "Every start of `atlas_transform` fitted with `COARSE_FIT`, then with the final "
            "`AtlasFitConfig`; a frame within 20 deg of the true one is right. `KEEP_MARGIN` "
            f"(the NCC by which another frame must beat the volume's own) is {KEEP_MARGIN:g}.",
            "",
            "| case | own frame error (deg) | own frame NCC | best right NCC | best wrong NCC "
            "(start, error) | right - wrong |",
            "|---|---:|---:|---:|---|---:|",
        ]
        for case in folders:
            volume, correction, mask, atlas_of = case_output(case)
            starts = atlas_starts(volume, mask)
            levels = atlas_levels(atlas_of, COARSE_FIT)
            final = AtlasFitConfig()
            reuse = levels if final.blur_mm == COARSE_FIT.blur_mm else None
            fits = []
            for name, start in starts.items():
                coarse, _ = fit_to_atlas(volume, mask, start, atlas_of, COARSE_FIT, levels)
                fine, ncc = fit_to_atlas(volume, mask, coarse, atlas_of, final, reuse)
                fits.append((name, ncc, degrees(se3_compose(fine, se3_inverse(correction)))))
            right = [f for f in fits if f[2] < 20.0]
            wrong = [f for f in fits if f[2] >= 20.0]
            own = fits[0]
            best_right = max((f[1] for f in right), default=float("nan"))
            worst = max(wrong, key=lambda f: f[1]) if wrong else ("-", float("nan"), 0.0)
            lines.append(
                f"| {case.name} | {own[2]:.1f} | {own[1]:.3f} | {best_right:.3f} | "
                f"{worst[1]:.3f} ({worst[0]}, {worst[2]:.0f}) | {best_right - worst[1]:+.3f} |"
            )
            print(lines[-1], flush=True)
    if args.turns:
        gen = torch.Generator().manual_seed(args.seed)
        lines += [
            "",
            f"## From any start: the volume turned, then atlas_transform (atlas offset "
            f"{args.atlas_offset:+g} weeks)",
            "",
            "| case | turn (deg) | error (deg) | centre error (mm) | start | time (s) |",
            "|---|---:|---:|---:|---|---:|",
        ]
        for case in folders:
            volume, correction, mask, atlas_of = case_output(case)
            for turn in args.turns:
                axis = torch.nn.functional.normalize(
                    torch.randn(3, generator=gen, dtype=torch.float64), dim=0
                )
                moved_by = IDENTITY.clone()
                moved_by[:3, :3] = so3_exp(axis * math.radians(turn))
                turned = Image(volume.data, moved_by.to(volume.affine) @ volume.affine)
                to_true = se3_compose(correction, se3_inverse(moved_by))
                began = time.perf_counter()
                found, start, _, _ = atlas_transform(turned, mask, atlas_of)
                seconds = time.perf_counter() - began
                error = se3_compose(found, se3_inverse(to_true))
                lines.append(
                    f"| {case.name} | {turn:g} | {degrees(error):.1f} | "
                    f"{float(error[:3, 3].norm()):.1f} | {start} | {seconds:.1f} |"
                )
                print(lines[-1], flush=True)
    text = "\n".join(lines)
    if args.results is not None:
        command = "python benchmarks/bench_atlas_frame.py " + " ".join(sys.argv[1:])
        args.results.write_text(
            "# How close a neighbouring-age atlas brings a volume to its true frame\n\n"
            f"Command: `{command}`\n\n{text}\n",
            encoding="utf-8",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
