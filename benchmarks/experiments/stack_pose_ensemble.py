"""Several stack-pose networks read together (an ensemble): per stack.

Each network reads the same block; the readings are averaged (the geodesic mean of the
residual rotations, the mean of the translations and of the scores) at every step of the
stack-pose inference, and ``benchmarks/bench_learned_stack_poses.py`` runs with the average.
``--also`` names the other networks (run folders or checkpoints); every other argument is the
bench's:

    python benchmarks/experiments/stack_pose_ensemble.py --also MODEL2 [MODEL3 ...] \
        --model MODEL --threads 1 --atlas FAMILY --ages 24 28 32 --cases-per-age 6 \
        --phantom-ages --bench --seed SEED --methods learned --results OUT.md

It changes no library code: it wraps the loaded network.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bench_learned_stack_poses as bench

from svr.geometry.averaging import robust_mean_pose
from svr.models.stack_pose import StackPoseNet, StackPoseOutput


class Ensemble(nn.Module):
    """Stack-pose networks whose readings of a block are averaged."""

    def __init__(self, nets: list[StackPoseNet]) -> None:
        super().__init__()
        self.nets = nn.ModuleList(nets)
        self.config = nets[0].config

    def forward(self, blocks: Tensor) -> StackPoseOutput:
        """(B, 3, S, S, S) blocks -> the averaged (B, 4, 4) residuals and (B,) scores."""
        outs = [net(blocks) for net in self.nets]
        residuals = torch.stack([out.residual.double() for out in outs], dim=1)
        score = torch.stack([out.score for out in outs]).mean(dim=0)
        mean = robust_mean_pose(residuals).to(outs[0].residual.dtype)
        return StackPoseOutput(mean, score, None, None)


def main() -> int:
    argv = sys.argv[1:]
    if "--also" not in argv:
        raise SystemExit("stack_pose_ensemble.py: give --also MODEL [MODEL ...]")
    start = argv.index("--also") + 1
    end = next((i for i in range(start, len(argv)) if argv[i].startswith("--")), len(argv))
    others, sys.argv[1:] = argv[start:end], argv[: start - 1] + argv[end:]
    load = bench.load_stack_pose_model

    def ensemble(*args, **kwargs):
        first = load(*args, **kwargs)
        rest = [load(other, *args[1:], **kwargs) for other in others]
        return Ensemble([first, *rest])

    bench.load_stack_pose_model = ensemble
    return bench.main()


if __name__ == "__main__":
    raise SystemExit(main())
