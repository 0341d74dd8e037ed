"""Can the slice refiner learn the rotation at all? Train and validate it on one brain.

A diagnostic of ``calibrate_slice_refiner.py`` (an experiment, not shipped): fresh packets of one
atlas brain every step, validated on a fixed draw of the *same* brain, so that no generalisation
across brains is asked of it. With ``--overfit`` a single fixed batch is trained on instead (does
the network fit its labels at all).

    python benchmarks/experiments/refiner_one_brain.py --brain GA27_operated --head coords \
        --max-turn 10 --minutes 16
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import slice_refiner_train as training
import torch
from calibrate_slice_refiner import _volumes

from svr.models.slice_refiner import SliceRefinerConfig, SliceRefinerNet


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--brain", type=Path, required=True, help="an atlas age's folder")
    parser.add_argument("--head", choices=["regress", "coords"], default="coords")
    parser.add_argument("--max-turn", type=float, default=10.0, help="residual range (deg)")
    parser.add_argument("--minutes", type=float, default=16.0)
    parser.add_argument("--overfit", action="store_true", help="one fixed batch of 4 packets")
    parser.add_argument(
        "--pure-rotation", action="store_true", help="residuals that are rotations alone"
    )
    parser.add_argument(
        "--shift-mm", type=float, default=0.0, help="with --pure-rotation: shifts too (std, mm)"
    )
    parser.add_argument("--save", type=Path, help="write the trained weights here (a state dict)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = SliceRefinerConfig(head=args.head)
    config = training.RefinerTrainingConfig(
        max_turn_deg=args.max_turn,
        pure_rotation=args.pure_rotation,
        pure_rotation_shift_mm=args.shift_mm,
        # without shifts the data's metric is singular: the default one (L = 20 mm) instead
        metric="default" if args.pure_rotation else "data",
    )
    brains = training.prepare_brains(_volumes([args.brain]))
    fixed = training.draw_packets(brains, model, config, torch.Generator().manual_seed(5))
    validation = (
        fixed
        if args.overfit
        else training.draw_packets(
            brains,
            model,
            training.RefinerTrainingConfig(
                packets_per_step=24,
                max_turn_deg=args.max_turn,
                pure_rotation=args.pure_rotation,
                pure_rotation_shift_mm=args.shift_mm,
            ),
            torch.Generator().manual_seed(999),
        )
    )
    net = SliceRefinerNet(model)
    loss_of = training.loss_function(
        model.representation, training.metric_weights(brains, model, config)
    )
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-3)
    start = torch.rad2deg(validation.residuals[validation.valid][:, :3].norm(dim=1))
    shift = validation.residuals[validation.valid][:, 3:].norm(dim=1)
    print(
        f"validation: {int(validation.valid.sum())} slices, rotation median {start.median():.2f}"
        f" deg, translation median {shift.median():.2f} mm",
        flush=True,
    )
    began, step = time.time(), 0
    while time.time() - began < 60.0 * args.minutes:
        step += 1
        batch = (
            fixed
            if args.overfit
            else training.draw_packets(brains, model, config, torch.Generator().manual_seed(step))
        )
        outputs = training._outputs(net, batch)
        loss = loss_of(outputs[batch.valid], batch.labels[batch.valid])
        if args.head == "coords":
            loss = loss + training.COORDS_WEIGHT * training._coords_loss(net, batch)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step % 500 == 0:
            rotation, translation = training.residual_errors(net.eval(), validation)
            net.train()
            print(
                f"step {step} {time.time() - began:.0f}s loss {float(loss.detach()):.4f} "
                f"rotation median {rotation.median():.2f} p90 {rotation.quantile(0.9):.2f} deg, "
                f"translation median {translation.median():.2f} mm",
                flush=True,
            )
    if args.save is not None:
        args.save.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"head": args.head, "state_dict": net.state_dict()}, args.save)
    rotation, translation = training.residual_errors(net.eval(), validation)
    print(
        f"final step {step}: rotation median {rotation.median():.2f} deg, translation median "
        f"{translation.median():.2f} mm"
    )


if __name__ == "__main__":
    main()
