"""Calibration of the slice refiner (an experiment, not shipped): does its loss move on one core?

Trains :mod:`slice_refiner` on slices cut from the Fidon (odd weeks 21-33) and CRL (even weeks
22-36) atlases and reports, every ``--val-every`` steps, the residual rotation and translation the
network leaves on a fixed validation draw from a held-out family (Wu 2021, weeks 24, 28, 32).
Result: ``benchmarks/results/slice-refiner.md``.

Usage::

    python benchmarks/experiments/calibrate_slice_refiner.py --head coords --minutes 60 \
        --fidon DIR --crl DIR --wu DIR --out runs/refiner
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import slice_refiner_train as training
import torch
from slice_refiner_train import (
    RefinerTrainingConfig,
    draw_packets,
    prepare_brains,
    residual_errors,
    train_slice_refiner,
)

from svr.models.slice_refiner import SliceRefinerConfig, load_slice_refiner
from svr.sampling.volume import CanonicalVolume, load_canonical_volume


def _volumes(folders: list[Path]) -> list[CanonicalVolume]:
    return [load_canonical_volume(f / "srr.nii.gz", f / "mask.nii.gz") for f in folders]


def main() -> None:
    """Train for ``--minutes`` and print the validation residuals as training goes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fidon", type=Path, required=True, help="Fidon 2021 atlas folder")
    parser.add_argument("--crl", type=Path, required=True, help="CRL atlas as GA<weeks>_crl/")
    parser.add_argument("--wu", type=Path, required=True, help="Wu 2021 atlas as GA<weeks>_wu/")
    parser.add_argument(
        "--train-on",
        nargs="+",
        default=["fidon", "crl"],
        choices=("fidon", "crl"),
        help="training families: fidon (CC0, every age but the bench's 24, 28, 32) and crl",
    )
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--context", default="none", choices=("none", "sequence"))
    parser.add_argument("--head", default="regress", choices=("regress", "coords"))
    parser.add_argument("--max-turn", type=float, default=30.0, help="residual range (deg)")
    parser.add_argument("--max-step", type=float, default=6.0, help="slice-to-slice motion (deg)")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--val-every", type=int, default=250)
    parser.add_argument("--out", type=Path, default=None, help="checkpoint folder (resumable)")
    parser.add_argument(
        "--pure-rotation", action="store_true", help="residuals that are rotations alone"
    )
    parser.add_argument(
        "--shift-mm", type=float, default=0.0, help="with --pure-rotation: shifts too (std, mm)"
    )
    parser.add_argument(
        "--other-reference",
        type=float,
        default=0.0,
        help="probability that a packet's reference is a training brain 1-3 weeks apart",
    )
    parser.add_argument(
        "--init",
        type=Path,
        default=None,
        help="warm start: a slice refiner model folder (e.g. models/pretrained/slice_refiner/wide)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the training draws")
    args = parser.parse_args()
    torch.set_num_threads(1)

    def fidon(weeks: int) -> Path:
        return args.fidon / f"GA{weeks}_{'notoperated' if weeks < 25 else 'operated'}"

    if args.train_on == ["fidon"]:
        # the shipped refiner: the atlas whose licence allows shipping weights, bench ages out
        weeks = [("fidon", w) for w in range(21, 35) if w not in (24, 28, 32)]
    else:
        weeks = (
            [("fidon", w) for w in (21, 23, 25, 27, 29, 31, 33)] if "fidon" in args.train_on else []
        )
        if "crl" in args.train_on:
            weeks += [("crl", w) for w in (22, 24, 26, 28, 30, 32, 34, 36)]
    train = [fidon(w) if family == "fidon" else args.crl / f"GA{w}_crl" for family, w in weeks]
    # a brain's references may come from any training brain 1-3 weeks apart (either family)
    partners = [[j for j, (_, v) in enumerate(weeks) if 1 <= abs(v - w) <= 3] for _, w in weeks]
    held_out = [args.wu / f"GA{w}_wu" for w in (24, 28, 32)]
    model = SliceRefinerConfig(context=args.context, head=args.head)
    residuals = {
        "max_turn_deg": args.max_turn,
        "max_step_deg": args.max_step,
        "pure_rotation": args.pure_rotation,
        "pure_rotation_shift_mm": args.shift_mm,
    }
    config = RefinerTrainingConfig(
        steps=args.steps,
        learning_rate=args.lr,
        # without shifts the data's metric is singular: the default one (L = 20 mm) instead
        metric="default" if args.pure_rotation else "data",
        other_reference=args.other_reference,
        seed=args.seed,
        **residuals,
    )
    validation = draw_packets(
        prepare_brains(_volumes(held_out)),
        model,
        RefinerTrainingConfig(packets_per_step=24, **residuals),
        torch.Generator().manual_seed(123),
    )
    start = torch.rad2deg(validation.residuals[validation.valid][:, :3].norm(dim=1))
    print(
        f"validation: {len(start)} slices, residual median {start.median():.1f} deg, "
        f"p90 {start.quantile(0.9):.1f}",
        flush=True,
    )
    began, losses, nets = time.time(), [], []

    class Watched(training.SliceRefinerNet):
        """The network, remembered so that the progress hook can validate it."""

        def __init__(self, *args: object, **kwargs: object) -> None:
            super().__init__(*args, **kwargs)  # type: ignore[arg-type]
            nets.append(self)

    def progress(step: int, loss: float) -> None:
        losses.append(loss)
        if step % args.val_every == 0:
            net = nets[-1]
            net.eval()
            rotation, translation = residual_errors(net, validation)
            net.train()
            recent = losses[-50:]
            print(
                f"step {step} {time.time() - began:.0f}s loss {sum(recent) / len(recent):.4f} "
                f"val rot median {rotation.median():.2f} p90 {rotation.quantile(0.9):.2f} deg, "
                f"trans median {translation.median():.2f} mm",
                flush=True,
            )

    training.SliceRefinerNet = Watched  # type: ignore[misc]
    train_slice_refiner(
        _volumes(train),
        model,
        config,
        args.out,
        minutes=args.minutes,
        progress=progress,
        partners=partners,
        init=None if args.init is None else load_slice_refiner(args.init),
    )
    print(f"steps/s {len(losses) / (time.time() - began):.2f}")


if __name__ == "__main__":
    main()
