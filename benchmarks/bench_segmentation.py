"""CPU speed and size of the brain-mask U-Net on a clinical-size stack (issue 14's ≤ 5 s target).

Times one forward pass of :class:`svr.models.segmentation.BrainUNet` (untrained weights: the speed
does not depend on them) over every slice of a 320 x 320 x 22 stack (the clinical scan's size) and
over the same slices at 128 x 128 (a localisation pass), for a few widths, and reports each
model's float16 size against the 10 MB limit on shipped models. Run from the repository root::

    python benchmarks/bench_segmentation.py --threads 2 \
        --results benchmarks/results/segmentation-speed.md
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import torch

from svr.models.pretrained import MAX_MODEL_BYTES
from svr.models.segmentation import BrainUNet, SegmentationConfig, parameter_bytes

TARGET_S = 5.0


def time_forward(model: BrainUNet, slices: torch.Tensor, repeats: int) -> float:
    """Median wall time (s) of one forward pass over ``slices``, after a warm-up."""
    with torch.inference_mode():
        model(slices[:2])
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            model(slices)
            times.append(time.perf_counter() - start)
    return sorted(times)[len(times) // 2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--widths", type=int, nargs="+", default=[8, 12, 16])
    parser.add_argument("--depth", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--results", type=Path, default=None, help="write a Markdown table here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    full, small = torch.randn(22, 1, 320, 320), torch.randn(22, 1, 128, 128)
    rows = []
    for width in args.widths:
        model = BrainUNet(SegmentationConfig(width, args.depth)).eval()
        size = parameter_bytes(model)
        t_full = time_forward(model, full, args.repeats)
        t_small = time_forward(model, small, args.repeats)
        rows.append(
            f"| {width} | {args.depth} | {size / 1e6:.2f} ({size / MAX_MODEL_BYTES:.2f}× limit) "
            f"| {t_full:.2f} ({t_full / TARGET_S:.2f}× target) | {t_small:.2f} |"
        )
    lines = [
        "# Brain-mask U-Net: CPU speed and size",
        "",
        f"Command: `python benchmarks/bench_segmentation.py --threads {args.threads}"
        f"{' --results ' + str(args.results) if args.results else ''}`",
        "",
        f"torch {torch.__version__}, {args.threads} CPU threads, {platform.processor() or 'cpu'}; "
        f"median of {args.repeats} forward passes (untrained weights, inference mode).",
        "",
        "| width | depth | float16 size (MB) | 22 × 320 × 320 stack (s) | 22 × 128 × 128 (s) |",
        "|---:|---:|---|---|---:|",
        *rows,
        "",
        f"Targets: ≤ {TARGET_S:g} s per 320 × 320 × 22 stack on 2 cores, ≤ "
        f"{MAX_MODEL_BYTES / 1e6:g} MB shipped.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.results is not None:
        args.results.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
