r"""Behaviour unchanged across a refactor: hash every output of a fixed set of runs, then compare.

Runs (CPU, one thread each, fixed seeds), on the bench case sb24-large and the real scan:

* ``recon-given``: ``svr reconstruct`` with the case's masks, ``--registration stack``;
* ``recon-auto``: the same with automatic (network) masks;
* ``recon-cnn-fused``: ``--registration cnn`` (the shipped stack-pose model) with automatic
  masks fused across the stacks;
* ``recon-none``: ``--registration none`` with the case's masks;
* ``recon-fixed``: ``--registration stack --schedule fixed`` with the case's masks;
* ``recon-cnn-atlas``: ``--registration cnn`` with the case's masks and the GA 23 and 25 atlases
  (the output frame fitted to an atlas);
* ``recon-cnn-slice``: ``--registration cnn --model default`` (the shipped slice-pose model);
* ``recon-cnn-classical``: ``--registration cnn --model none`` with the GA 24 atlas (no network);
* ``register``: ``svr register --registration cnn`` (poses only, one round);
* ``bids``: ``svr bids`` on the real scan laid out as a BIDS dataset, automatic masks;
* ``segment``: ``svr segment-stack`` on sb24-large (each stack alone);
* ``segment-fused-real``: ``svr segment-stack --fuse-masks`` on the real scan's 6 stacks;
* ``otsu``: the Otsu automatic masks of sb24-large, prepared (library).

Each output's voxels (as float32 or bool bytes) and affine are hashed (SHA-256); the transforms
tables are hashed as text. Usage::

    python benchmarks/check_identical.py run --out runs/identity/before
    ... change the code ...
    python benchmarks/check_identical.py run --out runs/identity/after
    python benchmarks/check_identical.py compare runs/identity/before runs/identity/after \
        --results benchmarks/results/straight-path.md
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
ATLAS = SHARED / "atlas" / "sb-fidon2021"
CASE = SHARED / "bench" / "sb24-large"
REAL = SHARED / "stacks" / "real-mialsrtk-sub01"
FAST = ["--output-resolution", "1.5", "--iterations", "2", "--device", "cpu", "--quiet"]


def _svr(args: list[str], cpus: str | None = None) -> float:
    for option in ("--output-volume", "--output-stack-masks"):
        if option in args:
            Path(args[args.index(option) + 1]).parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    began = time.time()
    # svr bids gives each participant the CPUs it may use: one CPU, one thread, as the others.
    pin = ["taskset", "-c", cpus] if cpus is not None else []
    subprocess.run([*pin, sys.executable, "-m", "svr", *args], check=True, env=env)
    return time.time() - began


def _hash_nifti(path: Path) -> dict[str, str]:
    import nibabel as nib
    import numpy as np

    image = nib.load(path)
    data = np.asarray(image.dataobj)
    return {
        "data": hashlib.sha256(np.ascontiguousarray(data).tobytes()).hexdigest(),
        "affine": hashlib.sha256(np.asarray(image.affine, dtype=np.float64).tobytes()).hexdigest(),
        "dtype": str(data.dtype),
    }


def _hash_text(path: Path, drop: str | None = None) -> str:
    text = path.read_text()
    return hashlib.sha256((text if drop is None else text.replace(drop, "")).encode()).hexdigest()


def run(out: Path, reuse: bool = False) -> None:
    """Run every case into ``out`` and write ``out/hashes.json``.

    With ``reuse``, a case whose folder exists is hashed as it is (its time is not re-measured).
    """
    import torch

    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    stacks = [str(CASE / "stacks" / f"stack{n}.nii.gz") for n in range(4)]
    masks = [str(CASE / "masks" / f"stack{n}_mask.nii.gz") for n in range(4)]
    hashes: dict[str, dict] = {}
    seconds: dict[str, float] = {}
    given = ["--stack-masks", *masks]

    def atlas(*ages: int) -> list[str]:
        dirs = [next(ATLAS.glob(f"GA{age}_*")) for age in ages]
        return [
            "--atlas-volume", *(str(d / "srr.nii.gz") for d in dirs),
            "--atlas-mask", *(str(d / "mask.nii.gz") for d in dirs),
        ]  # fmt: skip

    recon = {
        "recon-given": ("reconstruct", [*given, "--registration", "stack"]),
        "recon-auto": ("reconstruct", ["--registration", "stack"]),
        "recon-cnn-fused": ("reconstruct", ["--registration", "cnn", "--fuse-masks"]),
        "recon-none": ("reconstruct", [*given, "--registration", "none"]),
        "recon-fixed": ("reconstruct", [*given, "--registration", "stack", "--schedule", "fixed"]),
        "recon-cnn-atlas": ("reconstruct", [*given, "--registration", "cnn", *atlas(23, 25)]),
        "recon-cnn-slice": ("reconstruct", [*given, "--registration", "cnn", "--model", "default"]),
        "recon-cnn-classical": (
            "reconstruct",
            [*given, "--registration", "cnn", "--model", "none", *atlas(24)],
        ),
        "register": ("register", [*given, "--registration", "cnn"]),
    }
    for name, (command, extra) in recon.items():
        folder = out / name
        folder.mkdir(parents=True, exist_ok=True)
        # svr register keeps its own default of one round.
        fast = FAST if command == "reconstruct" else ["--output-resolution", "1.5", *FAST[4:]]
        seconds[name] = math.nan if reuse and (folder / "transforms.csv").exists() else _svr(
            [
                command, "--input-stacks", *stacks, "--thicknesses", "3", *extra, *fast,
                "--output-volume", str(folder / "volume.nii.gz"),
                "--output-transforms", str(folder / "transforms.csv"), "--overwrite",
            ]
        )  # fmt: skip
        hashes[name] = {
            "volume": _hash_nifti(folder / "volume.nii.gz"),
            "transforms": _hash_text(folder / "transforms.csv"),
        }
    folder = out / "bids"
    if not (reuse and folder.is_dir()):
        seconds["bids"] = _bids(folder)
    else:
        seconds["bids"] = math.nan
    anat = folder / "derivatives" / "sub-01" / "anat"
    hashes["bids"] = {
        "volume": _hash_nifti(anat / "sub-01_rec-svr_T2w.nii.gz"),
        "mask": _hash_nifti(anat / "sub-01_rec-svr_desc-brain_mask.nii.gz"),
        # The table names each stack by its path, which holds the run's folder.
        "transforms": _hash_text(anat / "sub-01_rec-svr_transforms.csv", str(folder.resolve())),
    }
    real = sorted(str(p) for p in REAL.glob("sub-01_run-*_T2w.nii.gz"))
    for name, inputs, extra in (
        ("segment", stacks, []),
        ("segment-fused-real", real, ["--fuse-masks"]),
    ):
        folder = out / name
        outputs = [str(folder / f"mask{n}.nii.gz") for n in range(len(inputs))]
        seconds[name] = math.nan if reuse and folder.is_dir() else _svr(
            [
                "segment-stack", "--input-stacks", *inputs, "--output-stack-masks", *outputs,
                *extra, "--device", "cpu", "--quiet", "--overwrite",
            ]
        )  # fmt: skip
        hashes[name] = {Path(p).name: _hash_nifti(Path(p)) for p in outputs}
    began = time.time()
    hashes["otsu"] = _otsu_hashes(stacks)
    seconds["otsu"] = time.time() - began
    (out / "hashes.json").write_text(json.dumps({"hashes": hashes, "seconds": seconds}, indent=1))
    print(f"wrote {out / 'hashes.json'}")


def _bids(folder: Path) -> float:
    """``svr bids`` on the real scan as a BIDS dataset (automatic masks); returns its seconds."""
    import shutil

    if folder.exists():
        shutil.rmtree(folder)
    anat = folder / "input" / "sub-01" / "anat"
    anat.mkdir(parents=True)
    (folder / "input" / "dataset_description.json").write_text(
        json.dumps({"Name": "real scan", "BIDSVersion": "1.9.0"})
    )
    for run in range(1, 7):
        for suffix in (".nii.gz", ".json"):
            name = f"sub-01_run-{run}_T2w{suffix}"
            shutil.copy(REAL / name, anat / name)
    return _svr(
        [
            "bids", str(folder / "input"), str(folder / "derivatives"), "participant",
            "--registration", "stack", *FAST,
        ],
        cpus="0",
    )  # fmt: skip


def _otsu_hashes(paths: list[str]) -> dict[str, str]:
    """The Otsu automatic masks, prepared, through whichever API the code has."""
    import numpy as np

    from svr.image import load_nifti
    from svr.reconstruction.stacks import StackConfig, prepare_stacks

    images = [load_nifti(p) for p in paths]
    if "auto_mask" in StackConfig.__dataclass_fields__:  # before the masking stage
        prepared = prepare_stacks(images, None, 3.0, StackConfig(auto_mask="otsu"))
    else:
        from svr.masking import MaskingConfig, auto_masks

        masks = auto_masks(images, MaskingConfig(method="otsu"))
        prepared = prepare_stacks(images, masks, 3.0, StackConfig())
    result = {}
    for n, stack in enumerate(prepared):
        for what, array in (("data", stack.image.data), ("mask", stack.mask.data)):
            bytes_ = np.ascontiguousarray(array.numpy()).tobytes()
            result[f"stack{n}-{what}"] = hashlib.sha256(bytes_).hexdigest()
        affine = stack.image.affine.double().numpy().tobytes()
        result[f"stack{n}-affine"] = hashlib.sha256(affine).hexdigest()
    return result


def compare(before: Path, after: Path, results: Path | None) -> int:
    """Compare two runs' hashes; print (and write) the table. Exit status 1 on a difference."""
    a = json.loads((before / "hashes.json").read_text())
    b = json.loads((after / "hashes.json").read_text())
    lines = [
        "| run | outputs hashed | identical | before (s) | after (s) |",
        "|---|---|---|---|---|",
    ]
    same_all = True
    for name, hashes in a["hashes"].items():
        other = b["hashes"].get(name)
        same = other == hashes
        same_all &= same
        count = sum(len(v) if isinstance(v, dict) else 1 for v in hashes.values())
        times = [
            f"{t:.0f}" if math.isfinite(t) else "n/a"
            for t in (a["seconds"][name], b["seconds"][name])
        ]
        lines.append(f"| {name} | {count} | {'yes' if same else 'NO'} | {times[0]} | {times[1]} |")
    text = "\n".join(lines)
    print(text)
    if results is not None:
        results.write_text(text + "\n")
    return 0 if same_all else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--reuse", action="store_true", help="hash the outputs already in --out")
    p = sub.add_parser("compare")
    p.add_argument("before", type=Path)
    p.add_argument("after", type=Path)
    p.add_argument("--results", type=Path)
    args = parser.parse_args()
    if args.command == "run":
        run(args.out, args.reuse)
        return 0
    return compare(args.before, args.after, args.results)


if __name__ == "__main__":
    sys.exit(main())
