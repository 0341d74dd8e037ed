"""The slice refiner iterated in two stages: a shift stage, then a rotation stage (an experiment).

``refiner_one_brain.py`` showed that the ``coords`` refiner learns the shifts of the full draw
but not its rotations, and learns a rotation alone when the shifts are small. This applies saved
refiners one after another on a fixed full draw (the packet's placement error and the head's
motion within it, as ``refiner_one_brain.py`` validates on), each step moving every slice's
current pose by the predicted residual (``T_current <- T_current o D``) and resampling its
reference planes there, and prints the slices' rotation and translation errors after each step
(and its time per slice, one thread, the resampling included).

    python benchmarks/experiments/refiner_two_stage.py --brain sb-fidon2021/GA27_operated
        --stage a=runs/two-stage/stage-a.pt --stage b=runs/two-stage/stage-b.pt
        --schedule a a b b b

A stage is a state dict saved by ``refiner_one_brain.py --save`` or a checkpoint (folder) of
``calibrate_slice_refiner.py --out``; several ``--brain`` folders draw the packets from each (with
``--seed 123``, the held-out family's validation draw of ``calibrate_slice_refiner.py``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import slice_refiner_train as training
import torch
from calibrate_slice_refiner import _volumes
from torch import Tensor

from svr.geometry import se3_compose, se3_error, se3_to_vector, vector_to_se3
from svr.models.slice_refiner import SliceRefinerConfig, SliceRefinerNet, load_slice_refiner


def _load(path: Path) -> SliceRefinerNet:
    if path.is_dir():
        return load_slice_refiner(path).eval()
    saved = torch.load(path, map_location="cpu", weights_only=True)
    net = SliceRefinerNet(SliceRefinerConfig(head=saved["head"]))
    net.load_state_dict(saved["state_dict"])
    return net.eval()


def _errors(scenes: list[training.PacketScene], currents: list[Tensor]) -> tuple[Tensor, Tensor]:
    """Rotation (deg) and translation (mm) errors of the valid slices' current poses."""
    rotations, translations = [], []
    for scene, current in zip(scenes, currents, strict=True):
        error = se3_error(se3_to_vector(current), se3_to_vector(scene.true))[scene.valid]
        rotations.append(torch.rad2deg(error[:, :3].norm(dim=1)))
        translations.append(error[:, 3:].norm(dim=1))
    return torch.cat(rotations), torch.cat(translations)


def _report(
    label: str, scenes: list[training.PacketScene], currents: list[Tensor], seconds: float = 0.0
) -> None:
    rotation, translation = _errors(scenes, currents)
    slices = sum(len(current) for current in currents)
    print(
        f"{label:>12}: rotation median {rotation.median():.2f} p90 {rotation.quantile(0.9):.2f}"
        f" deg, within 5 deg {100 * float((rotation <= 5).double().mean()):.0f} %, translation"
        f" median {translation.median():.2f} mm ({1000 * seconds / slices:.1f} ms per slice)",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--brain", type=Path, nargs="+", required=True, help="atlas age folders")
    parser.add_argument(
        "--stage", action="append", required=True, help="NAME=PATH of a saved refiner"
    )
    parser.add_argument("--schedule", nargs="+", required=True, help="stage names, in order")
    parser.add_argument("--max-turn", type=float, default=10.0, help="residual range (deg)")
    parser.add_argument("--seed", type=int, default=999, help="the draw's seed")
    args = parser.parse_args()
    torch.set_num_threads(1)
    stages = {}
    for item in args.stage:
        name, _, path = item.partition("=")
        if not path:
            parser.error(f"--stage: expected NAME=PATH, got {item!r}")
        stages[name] = _load(Path(path))
    unknown = sorted(set(args.schedule) - set(stages))
    if unknown:
        parser.error(f"--schedule: no --stage named {', '.join(unknown)}")
    model = SliceRefinerConfig(head="coords")
    brains = training.prepare_brains(_volumes(args.brain))
    scenes: list[training.PacketScene] = []
    config = training.RefinerTrainingConfig(packets_per_step=24, max_turn_deg=args.max_turn)
    training.draw_packets(brains, model, config, torch.Generator().manual_seed(args.seed), scenes)
    currents = [scene.current for scene in scenes]
    _report("start", scenes, currents)
    for index, name in enumerate(args.schedule):
        net, began = stages[name], time.perf_counter()
        moved = []
        for scene, current in zip(scenes, currents, strict=True):
            with torch.no_grad():
                inputs = training.render_inputs(scene, current, net.config)
                residual = net.to_pose(net(inputs)).double()
            moved.append(se3_compose(current, vector_to_se3(residual)))
        currents = moved
        _report(f"{index + 1}: {name}", scenes, currents, time.perf_counter() - began)


if __name__ == "__main__":
    main()
