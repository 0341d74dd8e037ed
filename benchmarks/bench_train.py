"""Training images per second and peak memory of each backbone, data against model.

Run from the repository root::

    python benchmarks/bench_train.py [--batch-size 32] [--width 32] [--depth 4] [--size 128]
        [--spacing 1.0] [--warmup 3] [--repeats 5] [--threads 2] [--device cpu|cuda|all]

For the ResNet and Inception backbones (``--width``, ``--depth``) with the SE(3) pose head and
loss, at a batch of ``--batch-size`` 1 x ``--size`` x ``--size`` slices (``--spacing`` mm; default
128 x 128 at 1 mm), the table gives images per second
(batch size over the median wall time of ``--repeats`` steps, after ``--warmup`` untimed ones) and
the peak memory of:

* ``model step``: forward, the ``se3`` loss, backward and an AdamW step
  (``svr.models.train.train_step``, the step ``svr.models.train.train`` takes, without a
  learning-rate schedule), on one fixed batch (thin slices of the phantom); on CUDA also ``model
  step amp``: float16 autocast with a ``GradScaler``;
* ``data thin`` and ``data thick 3 mm + aug``: ``svr.sampling.dataset.SliceStream`` making batches
  of that size (random poses with the empty-slice rule, sampling, labels) from the phantom on the
  device, as thin slices, and as 3 mm thick slices (Gaussian PSF, 5 samples) with the default
  intensity augmentation; one backbone-free row each;
* ``train() e2e``: ``svr.models.train.train`` run for ``--warmup`` + ``--repeats`` steps on the
  thick, augmented stream (no ``DataLoader`` workers: batches made in the training process), each
  step's time read from its ``log.csv`` (``log_every=1``).

Data and model run one after the other in one process, so the end-to-end rate is about
``1 / (1 / model + 1 / data)``; the lines after the table say which of the two limits each backbone.

Each row runs in a fresh (spawned) process with ``--threads`` torch CPU threads. Peak memory is
the rise over the measured section (warm-up and timed steps, or the whole ``train()`` call) above
what the process held before it (the model and the fixed batch, or the volume): on the CPU of the
process's peak resident set (``VmHWM``, reset through ``/proc/self/clear_refs``), so it includes
the AdamW state, the gradients, the activations and the allocator's and thread pool's overheads;
on CUDA of ``torch.cuda.max_memory_allocated``. CUDA steps are bracketed by
``torch.cuda.synchronize``. By default it runs on the CPU, and on CUDA too when available.

The volume is ``svr.sampling.phantom.make_phantom(gestational_age_config(28))``, canonicalised.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import gc
import multiprocessing as mp
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from bench_common import add_device_options, resolve_devices
from bench_sampler import status_kib

from svr.image import Image
from svr.models.backbones import BACKBONE_NAMES, BackboneConfig
from svr.models.network import ModelConfig, build_model, loss_function
from svr.models.train import TrainConfig, train, train_step
from svr.sampling.augment import SliceAugmentConfig
from svr.sampling.dataset import SliceDatasetConfig, SliceStream
from svr.sampling.phantom import gestational_age_config, make_phantom
from svr.sampling.slicer import SliceConfig
from svr.sampling.volume import CanonicalVolume, canonicalize

GESTATIONAL_AGE_WEEKS = 28
THIN = "thin"
THICK = "thick 3 mm + aug"
DATA_CONFIGS = {
    THIN: SliceDatasetConfig(),
    THICK: SliceDatasetConfig(
        slice=SliceConfig(thickness_mm=3.0, psf_samples=5), augment=SliceAugmentConfig()
    ),
}
"""The streams timed, by row name; ``batch_size`` is replaced by ``--batch-size``."""


@dataclass(frozen=True)
class Settings:
    """The command-line settings every row shares."""

    batch_size: int
    width: int
    depth: int
    warmup: int
    repeats: int
    threads: int
    size: int = 128
    spacing_mm: float = 1.0

    def model_config(self, backbone: str) -> ModelConfig:
        """The SE(3) model with ``backbone`` at the chosen width, depth and input geometry."""
        return ModelConfig(
            backbone=BackboneConfig(backbone, self.width, self.depth),
            input_size=(self.size, self.size),
            spacing_mm=self.spacing_mm,
        )

    def data_config(self, name: str) -> SliceDatasetConfig:
        """The stream ``name`` of :data:`DATA_CONFIGS` at the chosen batch size and geometry."""
        config = DATA_CONFIGS[name]
        slices = dataclasses.replace(
            config.slice, size=(self.size, self.size), spacing_mm=self.spacing_mm
        )
        return dataclasses.replace(config, slice=slices, batch_size=self.batch_size)


@dataclass(frozen=True)
class Inputs:
    """The canonical phantom and the fixed training batch, as numpy arrays for a child process."""

    data: np.ndarray
    affine: np.ndarray
    mask: np.ndarray
    centre_mm: np.ndarray
    intensity_scale: float
    slices: np.ndarray
    labels: np.ndarray

    def volume(self) -> CanonicalVolume:
        """The canonical volume, on the CPU."""
        image = Image(torch.from_numpy(self.data), torch.from_numpy(self.affine))
        mask, centre = torch.from_numpy(self.mask), torch.from_numpy(self.centre_mm)
        return CanonicalVolume(image, mask, centre, self.intensity_scale)


@dataclass(frozen=True)
class Case:
    """One row of the table.

    Attributes:
        kind: ``"model"`` (model step), ``"data"`` (stream batches) or ``"train"`` (``train()``).
        device: ``"cpu"`` or ``"cuda"``.
        backbone: The backbone name, ``"-"`` for data rows.
        data: The stream of a data row, a key of :data:`DATA_CONFIGS`; ``"-"`` for other rows.
        amp: Float16 autocast and loss scaling (model rows on CUDA).
    """

    kind: Literal["model", "data", "train"]
    device: str
    backbone: str = "-"
    data: str = "-"
    amp: bool = False

    @property
    def label(self) -> str:
        """The row's name in the table."""
        if self.kind == "data":
            return f"data {self.data}"
        if self.kind == "train":
            return "train() e2e"
        return "model step amp" if self.amp else "model step"


def step_times(step: Callable[[], object], count: int, device: torch.device) -> list[float]:
    """Wall time (s) of each of ``count`` calls of ``step``, synchronising CUDA around each."""
    sync = torch.cuda.synchronize if device.type == "cuda" else lambda: None
    times = []
    for _ in range(count):
        sync()
        start = time.perf_counter()
        step()
        sync()
        times.append(time.perf_counter() - start)
    return times


def model_section(
    case: Case, settings: Settings, inputs: Inputs, device: torch.device
) -> Callable[[], list[float]]:
    """Build the model, its optimiser and the batch; return the timed training steps."""
    model = build_model(settings.model_config(case.backbone)).to(device).train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)
    scaler = torch.amp.GradScaler("cuda", enabled=case.amp)
    criterion = loss_function("se3")
    slices = torch.from_numpy(inputs.slices).to(device)
    labels = torch.from_numpy(inputs.labels).to(device)

    def step() -> None:
        train_step(model, criterion, optimizer, scaler, slices, labels)

    return lambda: step_times(step, settings.warmup + settings.repeats, device)


def data_section(
    case: Case, settings: Settings, inputs: Inputs, device: torch.device
) -> Callable[[], list[float]]:
    """Build the stream on the device; return the timed batches (a new batch each call)."""
    batches = iter(SliceStream([inputs.volume().to(device)], settings.data_config(case.data)))
    return lambda: step_times(lambda: next(batches), settings.warmup + settings.repeats, device)


def train_section(
    case: Case, settings: Settings, inputs: Inputs, device: torch.device
) -> Callable[[], list[float]]:
    """Load the volume; return a ``train()`` run and its steps' times from ``log.csv``."""
    volume = inputs.volume()

    def run() -> list[float]:
        with tempfile.TemporaryDirectory() as folder:
            config = TrainConfig(
                output_dir=folder,
                model=settings.model_config(case.backbone),
                data=settings.data_config(THICK),
                steps=settings.warmup + settings.repeats,
                log_every=1,
                device=device.type,
            )
            train(config, [volume], progress=False)
            with (Path(folder) / "log.csv").open(newline="") as file:
                rows = list(csv.DictReader(file))
        return [settings.batch_size / float(row["images_per_s"]) for row in rows]

    return run


SECTIONS = {"model": model_section, "data": data_section, "train": train_section}


def probe(case: Case, settings: Settings, inputs: Inputs, conn: Connection) -> None:
    """In a fresh process: send the case's step times (s) and its peak memory rise (bytes)."""
    torch.set_num_threads(settings.threads)
    device = torch.device(case.device)
    section = SECTIONS[case.kind](case, settings, inputs, device)
    gc.collect()
    if device.type == "cuda":
        torch.cuda.synchronize()
        before = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
        times = section()
        peak = torch.cuda.max_memory_allocated() - before
    else:
        Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
        before = status_kib("VmRSS")
        times = section()
        peak = (status_kib("VmHWM") - before) * 1024
    conn.send((times, peak))


def measure(case: Case, settings: Settings, inputs: Inputs) -> tuple[float, float]:
    """Images per second (median of the timed steps) and peak MiB of a case, in a new process."""
    context = mp.get_context("spawn")
    receive, send = context.Pipe(duplex=False)
    process = context.Process(target=probe, args=(case, settings, inputs, send))
    process.start()
    send.close()  # so that recv() raises EOFError, not hangs, if the probe fails
    times, peak = receive.recv()
    process.join()
    return settings.batch_size / statistics.median(times[settings.warmup :]), peak / 2**20


def make_inputs(settings: Settings) -> Inputs:
    """The canonical phantom and batch 0 of its thin-slice stream."""
    volume = canonicalize(*make_phantom(gestational_age_config(GESTATIONAL_AGE_WEEKS)))
    batch = SliceStream([volume], settings.data_config(THIN)).batch(0)
    return Inputs(
        volume.image.data.numpy(),
        volume.image.affine.numpy(),
        volume.mask.numpy(),
        volume.centre_mm.numpy(),
        volume.intensity_scale,
        batch["slices"].numpy(),
        batch["labels"].numpy(),
    )


def device_cases(device: str) -> list[Case]:
    """The rows of one device: the data rows, then each backbone's model and train() rows."""
    cases = [Case("data", device, data=name) for name in DATA_CONFIGS]
    for backbone in BACKBONE_NAMES:
        cases.append(Case("model", device, backbone))
        if device == "cuda":
            cases.append(Case("model", device, backbone, amp=True))
        cases.append(Case("train", device, backbone))
    return cases


def parameter_count(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def print_limits(results: dict[Case, tuple[float, float]]) -> None:
    """Per device and backbone, whether the fp32 model step or the thick stream is slower."""
    for device in dict.fromkeys(case.device for case in results):
        data = results[Case("data", device, data=THICK)][0]
        for backbone in BACKBONE_NAMES:
            model = results[Case("model", device, backbone)][0]
            slower = "model" if model < data else "data"
            print(
                f"{device} {backbone}: model step {model:.0f} images/s, data {THICK} "
                f"{data:.0f} images/s: the {slower} limits training"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch-size", type=int, default=32, help="slices per step")
    parser.add_argument("--width", type=int, default=32, help="backbone width")
    parser.add_argument("--depth", type=int, default=4, help="backbone depth")
    parser.add_argument("--size", type=int, default=128, help="slice height and width, pixels")
    parser.add_argument("--spacing", type=float, default=1.0, help="in-plane spacing, mm")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps first")
    parser.add_argument("--repeats", type=int, default=5, help="timed steps per row")
    add_device_options(parser)
    args = parser.parse_args()
    devices = resolve_devices(parser, args)
    settings = Settings(
        args.batch_size,
        args.width,
        args.depth,
        args.warmup,
        args.repeats,
        args.threads,
        size=args.size,
        spacing_mm=args.spacing,
    )

    inputs = make_inputs(settings)
    print(
        f"torch {torch.__version__}, {args.threads} CPU threads; phantom GA "
        f"{GESTATIONAL_AGE_WEEKS} weeks {inputs.data.shape}; batches of {args.batch_size} "
        f"slices 1x{args.size}x{args.size} at {args.spacing:g} mm; median of {args.repeats} "
        f"steps after {args.warmup} warm-up"
    )
    counts = ", ".join(
        f"{name} {parameter_count(build_model(settings.model_config(name))):,}"
        for name in BACKBONE_NAMES
    )
    print(f"parameters (width {args.width}, depth {args.depth}, se3 head): {counts}")
    print("peak MiB: cpu, rise of VmHWM; cuda, rise of max_memory_allocated (fresh process)")
    print(
        f"\n{'case':<24}{'backbone':<11}{'device':<8}{'batch':>6}{'images/s':>10}{'peak MiB':>10}"
    )
    results: dict[Case, tuple[float, float]] = {}
    for case in (case for device in devices for case in device_cases(device)):
        rate, peak = results[case] = measure(case, settings, inputs)
        print(
            f"{case.label:<24}{case.backbone:<11}{case.device:<8}{args.batch_size:>6}"
            f"{rate:>10.1f}{peak:>10.1f}",
            flush=True,
        )
    print()
    print_limits(results)


if __name__ == "__main__":
    main()
