"""A small learned 3D tissue segmenter trained on synthetic brains made from atlas label maps.

An experiment to compare against multi-atlas segmentation. Every training step draws an atlas
(Fidon 2021 spina bifida or Wu 2021 neurotypical; never the held-out ages 24, 28, 32 nor the CRL
family), synthesises a T2-like brain from its labels (:mod:`svr.sampling.synthesis`, ``"labels"``
or ``"mixed"`` mode) on the atlas downsampled to 1.6 mm and resamples a fixed crop around it under
a random rigid transform, scaling and left-right flip, looking like a slice-to-volume
reconstruction: resolution blur, noise, bias, a brain mask dilated or eroded by 0-1 voxels at 1.6
mm (a dilation's ring gets random non-brain intensities), 0 outside it, intensities divided by the
in-mask 99th percentile. The network is a 4-level 3D U-Net (instance norm), trained with
cross-entropy + soft Dice and Adam; checkpoints: safetensors weights + JSON config (+ optimiser).

Usage: ``tissue_unet.py train --output-dir D --minutes 60``, ``tissue_unet.py predict --volume V
--checkpoint-dir C --output L``, ``tissue_unet.py evaluate --cases-dir E --checkpoint-dir C``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import time
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from safetensors.torch import load_file, save_file
from scipy.ndimage import gaussian_filter
from torch import Tensor, nn
from torch.nn import functional

from svr.image import Image, load_nifti, world_to_grid
from svr.sampling.synthesis import SynthesisConfig, synthesize_volume
from svr.sampling.volume import (
    ATLAS_LABELS,
    CanonicalVolume,
    downsample_volume,
    load_canonical_volume,
)

REPO = Path(__file__).resolve().parents[2]
HELD_OUT_WEEKS = (24, 28, 32)
CLASSES = 9
LABEL_NAMES = ("WM", "vent", "cereb", "eCSF", "cGM", "dGM", "stem", "CC")


@dataclass(frozen=True)
class TrainConfig:
    """What a run trains (saved as ``config.json`` beside the weights)."""

    channels: tuple[int, ...] = (8, 16, 32, 64)
    crop: tuple[int, int, int] = (64, 80, 64)
    spacing_mm: float = 1.6
    lr: float = 2e-3
    seed: int = 0
    mixed_probability: float = 0.5
    deform_probability: float = 0.5
    deform_mm: float = 2.0
    max_rotation_deg: float = 10.0
    max_translation_mm: float = 4.0
    max_scaling: float = 0.1
    crop_jitter_voxels: float = 3.0
    max_mask_change: int = 1


class ConvBlock(nn.Sequential):
    """Two 3x3x3 convolutions, each followed by instance norm and a leaky ReLU."""

    def __init__(self, cin: int, cout: int) -> None:
        layers: list[nn.Module] = []
        for c in (cin, cout):
            layers += [nn.Conv3d(c, cout, 3, padding=1), nn.InstanceNorm3d(cout, affine=True)]
            layers.append(nn.LeakyReLU(0.01, inplace=True))
        super().__init__(*layers)


class UNet3D(nn.Module):
    """A small 3D U-Net: max-pool down, trilinear up, skip concatenations, ``classes`` logits."""

    def __init__(self, channels: tuple[int, ...] = (8, 16, 32, 64), classes: int = CLASSES):
        super().__init__()
        self.down = nn.ModuleList(
            ConvBlock(a, b) for a, b in zip((1, *channels[:-1]), channels, strict=True)
        )
        self.up = nn.ModuleList(
            ConvBlock(channels[i] + channels[i + 1], channels[i]) for i in range(len(channels) - 1)
        )
        self.head = nn.Conv3d(channels[0], classes, 1)

    def forward(self, x: Tensor) -> Tensor:
        """(B, 1, I, J, K) images (sides divisible by 2^(levels-1)) -> (B, C, I, J, K) logits."""
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else functional.max_pool3d(x, 2))
            skips.append(x)
        for i in reversed(range(len(self.up))):
            x = functional.interpolate(x, scale_factor=2.0, mode="trilinear", align_corners=False)
            x = self.up[i](torch.cat([skips[i], x], 1))
        return self.head(x)


def training_atlas_dirs() -> list[tuple[int, Path]]:
    """(weeks, folder) of every training atlas: Fidon 2021 and Wu 2021, held-out ages left out."""
    fidon = Path("/work/shared/data/atlas/sb-fidon2021")
    if not fidon.exists():
        fidon = REPO.parent / "shared/data/atlas/sb-fidon2021"
    out = []
    for root in (fidon, Path("/work/atlases/wu")):
        for folder in sorted(root.glob("GA*")):
            weeks = int(re.match(r"GA(\d\d)", folder.name).group(1))  # type: ignore[union-attr]
            if weeks not in HELD_OUT_WEEKS and (folder / "parcellation.nii.gz").exists():
                out.append((weeks, folder))
    return out


def load_atlases(spacing_factor: int = 2) -> list[tuple[int, CanonicalVolume]]:
    """The training atlases as canonical volumes with labels, downsampled by ``spacing_factor``."""
    out = []
    for weeks, folder in training_atlas_dirs():
        volume = load_canonical_volume(
            folder / "srr.nii.gz", folder / "mask.nii.gz", labels_path=folder / ATLAS_LABELS
        )
        out.append((weeks, downsample_volume(volume, spacing_factor)))
    return out


def _uniform(g: torch.Generator, low: float, high: float, n: int = 1) -> Tensor:
    return low + (high - low) * torch.rand(n, generator=g, dtype=torch.float64)


def rotation_matrix(angles: Tensor) -> Tensor:
    """(3, 3) float64 rotation from three angles (rad) about x, then y, then z."""
    c, s = torch.cos(angles), torch.sin(angles)
    rx = torch.tensor([[1, 0, 0], [0, c[0], -s[0]], [0, s[0], c[0]]], dtype=torch.float64)
    ry = torch.tensor([[c[1], 0, s[1]], [0, 1, 0], [-s[1], 0, c[1]]], dtype=torch.float64)
    rz = torch.tensor([[c[2], -s[2], 0], [s[2], c[2], 0], [0, 0, 1]], dtype=torch.float64)
    return rz @ ry @ rx


def grid_points(shape: tuple[int, int, int], spacing: float, centre: Tensor) -> Tensor:
    """(I, J, K, 3) float64 world points of a world-axis-aligned grid centred on ``centre``."""
    axes = [(torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * spacing for n in shape]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1) + centre


def sample_at(data: Tensor, affine: Tensor, points: Tensor, mode: str = "bilinear") -> Tensor:
    """(C, I, J, K) channels on ``affine``'s grid sampled at (..., 3) world points; 0 outside."""
    to_grid = world_to_grid(Image(data[0], affine))
    coords = (points.reshape(-1, 3) @ to_grid[:, :3].T + to_grid[:, 3]).to(data.dtype)
    out = functional.grid_sample(
        data[None], coords.reshape(1, 1, 1, -1, 3), mode=mode, align_corners=True
    )
    return out.reshape(data.shape[0], *points.shape[:-1])


def percentile_99(values: Tensor) -> Tensor:
    """The 99th percentile of a 1D tensor (nearest rank)."""
    k = max(1, min(len(values), round(0.99 * (len(values) - 1)) + 1))
    return torch.kthvalue(values, k).values.clamp(min=1e-6)


def morph(mask: Tensor, steps: int) -> Tensor:
    """(I, J, K) bool mask dilated (``steps`` > 0) or eroded (< 0) by ``|steps|`` voxels (cube)."""
    x = mask.float()[None, None]
    for _ in range(abs(steps)):
        x = functional.max_pool3d(x if steps > 0 else -x, 3, 1, 1)
        x = x if steps > 0 else -x
    return x[0, 0] > 0.5


def make_example(
    volume: CanonicalVolume, config: TrainConfig, g: torch.Generator
) -> tuple[Tensor, Tensor]:
    """One synthetic training crop: (I, J, K) float32 image and (I, J, K) int64 labels."""
    mode = "mixed" if float(_uniform(g, 0, 1)) < config.mixed_probability else "labels"
    deform = config.deform_mm if float(_uniform(g, 0, 1)) < config.deform_probability else 0.0
    synth = SynthesisConfig(
        mode=mode, blur_mm=(0.0, 1.2), noise=(0.0, 0.05), bias=(0.0, 0.4), deform_mm=deform
    )
    brain = synthesize_volume(volume, synth, g)
    assert brain.labels is not None
    # Output grid in the canonical frame (origin: the mask centroid) plus jitter; the source
    # point of an output point p is R S p + t.
    jitter = _uniform(g, -1, 1, 3) * config.crop_jitter_voxels * config.spacing_mm
    angles = _uniform(g, -1, 1, 3) * math.radians(config.max_rotation_deg)
    scale = 1 + _uniform(g, -1, 1, 3) * config.max_scaling
    shift = _uniform(g, -1, 1, 3) * config.max_translation_mm
    matrix = rotation_matrix(angles) * scale[None, :]
    points = grid_points(config.crop, config.spacing_mm, jitter) @ matrix.T + shift
    affine = brain.image.affine.to(torch.float64)
    soft = torch.stack([brain.image.data.float(), brain.mask.float()])
    image, mask = sample_at(soft, affine, points)
    labels = sample_at(brain.labels.float()[None], affine, points, "nearest")[0].round().long()
    mask = mask > 0.5
    if float(_uniform(g, 0, 1)) < 0.5:  # left-right (world x = crop axis 0)
        image, mask, labels = image.flip(0), mask.flip(0), labels.flip(0)
    most = config.max_mask_change
    change = int(torch.randint(-most, most + 1, (1,), generator=g))
    new_mask = morph(mask, change)
    ring = new_mask & ~mask
    level = float(_uniform(g, 0.0, 0.8))
    field = functional.interpolate(
        torch.randn(1, 1, 4, 5, 4, generator=g), size=config.crop, mode="trilinear"
    )[0, 0]
    image = torch.where(ring, (level * (1 + 0.3 * field)).clamp(min=0), image)
    noise = float(_uniform(g, 0.0, 0.03)) * torch.randn(config.crop, generator=g)
    image = (image + noise).clamp(min=0) * new_mask
    if bool(new_mask.any()):
        image = image / percentile_99(image[new_mask])
    gamma = math.exp(float(_uniform(g, -0.3, 0.3)))
    image = image.clamp(min=0) ** gamma
    labels = torch.where(new_mask, labels, torch.zeros_like(labels))
    return image.float(), labels


def loss_terms(logits: Tensor, labels: Tensor) -> tuple[Tensor, Tensor]:
    """Cross-entropy and soft Dice loss (1 - mean Dice over the classes) of (B, C, ...) logits."""
    ce = functional.cross_entropy(logits, labels)
    prob = logits.softmax(1)
    onehot = functional.one_hot(labels, logits.shape[1]).movedim(-1, 1).to(prob)
    dims = tuple(range(2, logits.dim()))
    inter = (prob * onehot).sum(dims)
    dice = (2 * inter + 1e-5) / (prob.sum(dims) + onehot.sum(dims) + 1e-5)
    return ce, 1 - dice.mean()


def _atomic(path: Path, write: object) -> None:
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)  # type: ignore[operator]
    os.replace(tmp, path)


def save_checkpoint(
    out: Path, model: nn.Module, optim: torch.optim.Optimizer, config: TrainConfig, state: dict
) -> None:
    """Weights (``model.safetensors``), config + progress (``config.json``), optimiser state."""
    out.mkdir(parents=True, exist_ok=True)
    weights = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    _atomic(out / "model.safetensors", lambda p: save_file(weights, str(p)))
    _atomic(out / "optimizer.pt", lambda p: torch.save(optim.state_dict(), p))
    text = json.dumps({"config": asdict(config), **state}, indent=2)
    _atomic(out / "config.json", lambda p: p.write_text(text))


def load_model(checkpoint_dir: Path) -> tuple[UNet3D, TrainConfig, dict]:
    """The network (eval mode), its config and the saved progress state."""
    meta = json.loads((Path(checkpoint_dir) / "config.json").read_text())
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in meta.pop("config").items()}
    config = TrainConfig(**fields)
    model = UNet3D(config.channels)
    model.load_state_dict(load_file(str(Path(checkpoint_dir) / "model.safetensors")))
    return model.eval(), config, meta


def train(output_dir: Path, minutes: float, config: TrainConfig, checkpoint_minutes: float) -> None:
    """Train for ``minutes`` of wall time (resuming from ``output_dir`` if it has a checkpoint)."""
    torch.set_num_threads(1)
    output_dir.mkdir(parents=True, exist_ok=True)
    log = (output_dir / "train.log").open("a")
    state = {"step": 0, "elapsed_s": 0.0, "losses": []}
    model = UNet3D(config.channels)
    optim = torch.optim.Adam(model.parameters(), lr=config.lr)
    if (output_dir / "config.json").exists():
        model, config, state = load_model(output_dir)
        model.train()
        optim = torch.optim.Adam(model.parameters(), lr=config.lr)
        optim.load_state_dict(torch.load(output_dir / "optimizer.pt"))
        print(f"resumed at step {state['step']} ({state['elapsed_s'] / 60:.1f} min)", file=log)
    start_time, start_elapsed = time.time(), float(state["elapsed_s"])
    total = start_elapsed + minutes * 60
    atlases = load_atlases()
    ages = sorted({w for w, _ in atlases})
    print(f"{len(atlases)} atlases, ages {ages}, load {time.time() - start_time:.0f} s", file=log)
    last_save, window = time.time(), []
    model.train()
    while True:
        elapsed = start_elapsed + time.time() - start_time
        if elapsed >= total:
            break
        step = int(state["step"])
        g = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
        weeks = ages[int(torch.randint(len(ages), (1,), generator=g))]
        choices = [v for w, v in atlases if w == weeks]
        volume = choices[int(torch.randint(len(choices), (1,), generator=g))]
        t0 = time.time()
        image, labels = make_example(volume, config, g)
        t1 = time.time()
        # lr: constant, then a linear decay to 5% over the last 40% of the planned time
        frac = elapsed / total
        lr = config.lr * (1.0 if frac < 0.6 else max(0.05, 1 - (frac - 0.6) / 0.4))
        for group in optim.param_groups:
            group["lr"] = lr
        ce, dice = loss_terms(model(image[None, None]), labels[None])
        loss = ce + dice
        optim.zero_grad()
        loss.backward()
        optim.step()
        state["step"] = step + 1
        state["elapsed_s"] = start_elapsed + time.time() - start_time
        window.append((ce.item(), dice.item()))
        if len(window) == 25:
            ce_m, dice_m = (float(np.mean(c)) for c in zip(*window, strict=True))
            state["losses"].append([step + 1, round(ce_m + dice_m, 4)])
            print(
                f"step {step + 1} {state['elapsed_s'] / 60:.1f} min loss {ce_m + dice_m:.4f} "
                f"(ce {ce_m:.4f} dice {dice_m:.4f}) lr {lr:.2e} data {t1 - t0:.2f} s "
                f"net {time.time() - t1:.2f} s",
                file=log,
                flush=True,
            )
            window = []
        if time.time() - last_save > checkpoint_minutes * 60:
            save_checkpoint(output_dir, model, optim, config, state)
            last_save = time.time()
    save_checkpoint(output_dir, model, optim, config, state)
    print(f"done: step {state['step']}, {state['elapsed_s'] / 60:.1f} min", file=log, flush=True)


@lru_cache(maxsize=2)
def _cached_model(checkpoint_dir: str) -> tuple[UNet3D, TrainConfig]:
    model, config, _ = load_model(Path(checkpoint_dir))
    return model, config


def segment(volume_path: Path, checkpoint_dir: Path) -> np.ndarray:
    """Tissue labels (0-8, int16) of a masked T2w volume on its own voxel grid.

    The volume is resampled (anti-aliased, trilinear) to the network's world-axis-aligned grid
    centred on its nonzero voxels' centroid, normalised by the in-mask 99th percentile; the
    softmax (averaged with the left-right flipped input's) goes back to the input grid
    trilinearly, then argmax, 0 outside the input's nonzero voxels.
    """
    model, config = _cached_model(str(checkpoint_dir))
    volume = load_nifti(volume_path)
    data, affine = volume.data.numpy(), volume.affine
    inside = data != 0
    spacing = volume.spacing.numpy()
    sigma = np.sqrt(np.clip(config.spacing_mm**2 - spacing**2, 0, None)) / 2.355 / spacing
    smooth = torch.from_numpy(gaussian_filter(data.astype(np.float32), sigma, truncate=3.0))
    idx = torch.from_numpy(np.argwhere(inside)).to(torch.float64)
    centre = idx.mean(0) @ affine[:3, :3].T + affine[:3, 3]
    points = grid_points(config.crop, config.spacing_mm, centre)
    channels = torch.stack([smooth, torch.from_numpy(inside.astype(np.float32))])
    image, mask = sample_at(channels, affine, points)
    mask = mask > 0.5
    image = torch.where(mask, image, torch.zeros_like(image)).clamp(min=0)
    image = image / percentile_99(image[mask])
    with torch.no_grad():
        x = image[None, None]
        prob = model(x).softmax(1) + model(x.flip(2)).softmax(1).flip(2)
    prob = prob[0] / 2  # (C, I, J, K) on the network grid
    net_affine = torch.eye(4, dtype=torch.float64) * config.spacing_mm
    net_affine[3, 3] = 1.0
    net_affine[:3, 3] = points[0, 0, 0]
    world = idx @ affine[:3, :3].T + affine[:3, 3]
    back = sample_at(prob, net_affine, world)  # (C, N)
    labels = np.zeros(data.shape, dtype=np.int16)
    labels[inside] = back.argmax(0).numpy().astype(np.int16)
    return labels


def predict(volume: Path, checkpoint_dir: Path, output: Path) -> None:
    """Segment ``volume`` and write the labels as a NIfTI on its grid."""
    labels = segment(volume, checkpoint_dir)
    reference = nib.load(str(volume))
    out = nib.Nifti1Image(labels, reference.affine)
    out.set_qform(reference.affine, 1)
    out.set_sform(reference.affine, 1)
    output.parent.mkdir(parents=True, exist_ok=True)
    nib.save(out, str(output))


def case_scores(pred: np.ndarray, truth: np.ndarray) -> tuple[list[float], list[float]]:
    """Dice and volume error (%, signed) of labels 1..8."""
    dice, volume = [], []
    for label in range(1, CLASSES):
        p, t = pred == label, truth == label
        denom = p.sum() + t.sum()
        dice.append(float(2 * (p & t).sum() / denom) if denom else float("nan"))
        volume.append(float(100 * (p.sum() - t.sum()) / t.sum()) if t.sum() else float("nan"))
    return dice, volume


def evaluate(cases_dir: Path, checkpoint_dir: Path, wait_minutes: float = 0.0) -> dict:
    """Segment every case of ``cases_dir`` and print Dice, volume errors and times per case."""
    deadline = time.time() + wait_minutes * 60
    while not sorted(cases_dir.glob("*/truth_labels.nii.gz")) and time.time() < deadline:
        time.sleep(180)
    _cached_model(str(checkpoint_dir))
    rows = {}
    head = " ".join(f"{n:>6}" for n in LABEL_NAMES)
    print(f"{'case':<28} {'kind':<10} {head}   mean  |vol err| med   time")
    for folder in sorted(p.parent for p in cases_dir.glob("*/truth_labels.nii.gz")):
        meta = json.loads((folder / "case.json").read_text())
        t0 = time.time()
        pred = segment(folder / "volume.nii.gz", checkpoint_dir)
        seconds = time.time() - t0
        truth = np.rint(np.asarray(nib.load(str(folder / "truth_labels.nii.gz")).dataobj))
        dice, volume = case_scores(pred, truth.astype(np.int16))
        mean = float(np.nanmean(dice))
        med = float(np.nanmedian(np.abs(volume)))
        rows[folder.name] = {
            "meta": meta,
            "dice": dice,
            "volume_error_pct": volume,
            "mean_dice": mean,
            "seconds": seconds,
        }
        cells = " ".join(f"{d:6.3f}" for d in dice)
        kind = str(meta.get("kind", ""))[:10]
        print(f"{folder.name:<28} {kind:<10} {cells} {mean:6.3f} {med:8.1f}% {seconds:6.1f}s")
        print(f"{'  volume error %':<39} " + " ".join(f"{v:6.1f}" for v in volume), flush=True)
    if rows:
        dice_all = np.array([r["dice"] for r in rows.values()])
        vol_all = np.abs(np.array([r["volume_error_pct"] for r in rows.values()]))
        cells = " ".join(f"{d:6.3f}" for d in np.nanmean(dice_all, 0))
        print(f"{'mean over cases':<39} {cells} {np.nanmean(dice_all):6.3f}")
        print(
            f"{'median |volume error| %':<39} "
            + " ".join(f"{v:6.1f}" for v in np.nanmedian(vol_all, 0))
            + f"   all {np.nanmedian(vol_all):.1f}%"
        )
        for kind in sorted({str(r["meta"].get("kind")) for r in rows.values()}):
            means = [r["mean_dice"] for r in rows.values() if str(r["meta"].get("kind")) == kind]
            print(f"mean Dice, kind {kind}: {np.mean(means):.3f} ({len(means)} cases)")
        print(f"time per case: mean {np.mean([r['seconds'] for r in rows.values()]):.1f} s")
    return rows


def main() -> None:
    """The command line: ``train``, ``predict`` and ``evaluate``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    t, p, e = (sub.add_parser(name) for name in ("train", "predict", "evaluate"))
    for parser_, flags in (
        (t, ["output-dir"]),
        (p, ["volume", "checkpoint-dir", "output"]),
        (e, ["cases-dir", "checkpoint-dir"]),
    ):
        for flag in flags:
            parser_.add_argument(f"--{flag}", type=Path, required=True)
    t.add_argument("--minutes", type=float, default=60.0)
    t.add_argument("--checkpoint-minutes", type=float, default=4.0)
    t.add_argument("--lr", type=float, default=TrainConfig.lr)
    t.add_argument("--seed", type=int, default=0)
    e.add_argument("--wait-minutes", type=float, default=0.0)
    e.add_argument("--output-json", type=Path, default=None)
    for s in (p, e):
        s.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    if args.command == "train":
        train(
            args.output_dir,
            args.minutes,
            TrainConfig(lr=args.lr, seed=args.seed),
            args.checkpoint_minutes,
        )
        return
    torch.set_num_threads(args.threads)
    if args.command == "predict":
        t0 = time.time()
        predict(args.volume, args.checkpoint_dir, args.output)
        print(f"{args.output} ({time.time() - t0:.1f} s)")
    else:
        rows = evaluate(args.cases_dir, args.checkpoint_dir, args.wait_minutes)
        if args.output_json is not None:
            args.output_json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
