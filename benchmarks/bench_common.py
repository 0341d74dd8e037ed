"""Options shared by the benchmark scripts (run as ``python benchmarks/NAME.py``)."""

from __future__ import annotations

import argparse

import torch


def add_device_options(parser: argparse.ArgumentParser, cuda_note: str = "") -> None:
    """Add ``--threads`` (torch CPU threads, default 2) and ``--device cpu|cuda|all``."""
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument(
        "--device",
        choices=["cpu", "cuda", "all"],
        default=None,
        help=f"default: cpu, plus cuda{cuda_note} when available",
    )


def resolve_devices(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[str]:
    """Set the torch CPU threads and return the devices to measure.

    CUDA asked for but absent is a usage error (``parser.error``).
    """
    if args.device in ("cuda", "all") and not torch.cuda.is_available():
        parser.error("CUDA is not available")
    torch.set_num_threads(args.threads)
    if args.device is None:
        return ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]
    return ["cpu", "cuda"] if args.device == "all" else [args.device]
