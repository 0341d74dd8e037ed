"""How many of a stack-pose model's hidden units fire: a stalled run is one where none does.

The stack-pose network's heads share one hidden layer (``StackPoseNet.fc``: 128 units for width
16, a ReLU). A unit that outputs zero for every input gets no gradient and never fires again; when
all do, the network's outputs no longer depend on the block, and training stalls with the pose
loss of the zero residual (about 0.25) and the score loss of the base rate (about 0.65). This
simulates training blocks (``svr.models.stack_pose_batches.simulate_batch``: the training stacks and
their starts, GA 26 of the atlas, real motion) and reports, per model, the share of hidden units
that fire (output > 0) for at least one of them, and how much the outputs vary over the blocks.

Run from the repository root (seconds per model, one core)::

    python benchmarks/bench_hidden_units.py --model stack-pose runs/a runs/b \
        [--results benchmarks/results/stack-pose-hidden-units.md]
"""

from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path

import torch
from bench_common import SHARED, write_results

ATLAS_AGE = SHARED / "data" / "atlas" / "sb-fidon2021" / "GA26_operated"
MOTION = SHARED / "data" / "motion" / "svort_fetal_motion_trajectories.npz"


def measure(model_path: str, volume, trajectories, batches: int) -> dict[str, float]:
    """The share of hidden units that fire, and the outputs' spread, over simulated blocks."""
    from svr.models.stack_pose import load_stack_pose_model
    from svr.models.stack_pose_batches import simulate_batch
    from svr.models.stack_pose_train import StackPoseTrainingConfig

    net = load_stack_pose_model(model_path)
    generator = torch.Generator().manual_seed(5)
    config = StackPoseTrainingConfig()
    blocks = torch.cat(
        [
            simulate_batch([volume], trajectories, net.config, config, generator)[0]
            for _ in range(batches)
        ]
    )
    seen: list[torch.Tensor] = []
    hook = net.fc.register_forward_hook(lambda _module, _inputs, out: seen.append(out))
    with torch.no_grad():
        output = net(blocks)
    hook.remove()
    hidden = seen[0]
    return {
        "blocks": float(len(blocks)),
        "units": float(hidden.shape[1]),
        "firing": float((hidden > 0).any(0).sum()),
        "score_sd": float(output.score.std()),
        "shift_sd_mm": float(output.residual[:, :3, 3].std()),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", nargs="+", default=["stack-pose"], help="stack-pose models")
    parser.add_argument("--batches", type=int, default=4, help="training batches (8 blocks each)")
    parser.add_argument("--results", type=Path, help="also write the table here (markdown)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if not ATLAS_AGE.is_dir():
        print(
            f"{ATLAS_AGE}: no such folder (the atlas; see ../shared/data/README)", file=sys.stderr
        )
        return 1
    from svr.sampling.motion import load_trajectories
    from svr.sampling.volume import downsample_volume, load_canonical_volume

    volume = downsample_volume(
        load_canonical_volume(ATLAS_AGE / "srr.nii.gz", ATLAS_AGE / "mask.nii.gz"), 2
    )
    trajectories = load_trajectories(MOTION)
    lines = [
        "| model | hidden units firing | share | score logit SD | residual shift SD (mm) "
        "| firing vs first model |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    first = None
    for model in args.model:
        m = measure(model, volume, trajectories, args.batches)
        first = m["firing"] if first is None else first
        ratio = f"x{m['firing'] / first:.2f}" if first else "n/a"
        lines.append(
            f"| {model} | {m['firing']:.0f} of {m['units']:.0f} | "
            f"{100 * m['firing'] / m['units']:.1f} % | {m['score_sd']:.2f} | "
            f"{m['shift_sd_mm']:.2f} | {ratio} |"
        )
        print(lines[-1], flush=True)
    if args.results is not None:
        write_results(
            args.results,
            "Hidden units that fire, per stack-pose model",
            "\n".join(lines),
            f" ({datetime.date.today().isoformat()}, {args.batches * 8} simulated training "
            "blocks, one thread, the 2-core VM)",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
