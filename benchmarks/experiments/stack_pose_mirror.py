"""The stack-pose network read twice, as the block is and mirrored left-right: per stack.

A fetal brain is nearly symmetric about its mid-sagittal plane (canonical ``x = 0``, the
reflection ``M``, :data:`svr.geometry.mirror.SAGITTAL`). The network's block is sampled on a grid
centred on the candidate frame's canonical origin, so the block flipped along its first axis is
the stack seen in the mirrored frame ``M o E``: a stack of the mirrored brain. If the network
reads the residual ``R'`` there, the same evidence says ``M R' M`` for the block itself. This
experiment averages the two readings (the geodesic midpoint of the rotations, the mean of the
translations and of the two scores) at every step of the stack-pose inference and runs
``benchmarks/bench_learned_stack_poses.py`` with it; every argument is the bench's:

    python benchmarks/experiments/stack_pose_mirror.py --model MODEL --threads 1 \
        --atlas FAMILY --ages 24 28 32 --cases-per-age 6 --phantom-ages --bench --seed SEED \
        --methods learned --results OUT.md

It changes no library code: it wraps the loaded network (twice the blocks through it, in one
batch).
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bench_learned_stack_poses as bench

from svr.geometry.averaging import robust_mean_pose
from svr.geometry.mirror import SAGITTAL
from svr.models.stack_pose import StackPoseNet, StackPoseOutput


class MirrorAveraged(nn.Module):
    """A stack-pose network whose every reading is averaged with the mirrored block's."""

    def __init__(self, net: StackPoseNet) -> None:
        super().__init__()
        self.net = net
        self.config = net.config

    def forward(self, blocks: Tensor) -> StackPoseOutput:
        """(B, 3, S, S, S) blocks -> the averaged (B, 4, 4) residuals and (B,) scores."""
        count = blocks.shape[0]
        out = self.net(torch.cat([blocks, blocks.flip(2)]))
        residual = out.residual.double()
        reflect = SAGITTAL.matrix(device=residual.device)
        pair = torch.stack([residual[:count], reflect @ residual[count:] @ reflect], dim=1)
        score = (out.score[:count] + out.score[count:]) / 2
        return StackPoseOutput(robust_mean_pose(pair).to(out.residual.dtype), score, None, None)


def main() -> int:
    load = bench.load_stack_pose_model
    bench.load_stack_pose_model = lambda *args, **kwargs: MirrorAveraged(load(*args, **kwargs))
    return bench.main()


if __name__ == "__main__":
    raise SystemExit(main())
