r"""Behaviour unchanged across a refactor: hash every output of a fixed set of runs, then compare.

Runs (CPU, one thread each, fixed seeds), on the bench case sb24-large and the real scan:

* ``recon-given``: ``svr reconstruct`` with the case's masks, ``--registration stack``;
* ``recon-auto``: the same with automatic (network) masks;
* ``recon-cnn-fused``: ``--registration cnn`` (the shipped stack-pose model) with automatic
  masks fused across the stacks;
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
CASE = SHARED / "bench" / "sb24-large"
REAL = SHARED / "stacks" / "real-mialsrtk-sub01"
FAST = ["--output-resolution", "1.5", "--iterations", "2", "--device", "cpu", "--quiet"]


def _svr(args: list[str]) -> float:
    for option in ("--output-volume", "--output-stack-masks"):
        if option in args:
            Path(args[args.index(option) + 1]).parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    began = time.time()
    subprocess.run([sys.executable, "-m", "svr", *args], check=True, env=env)
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


def _hash_text(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


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
    recon = {
        "recon-given": ["--stack-masks", *masks, "--registration", "stack"],
        "recon-auto": ["--registration", "stack"],
        "recon-cnn-fused": ["--registration", "cnn", "--fuse-masks"],
    }
    for name, extra in recon.items():
        folder = out / name
        seconds[name] = math.nan if reuse and folder.is_dir() else _svr(
            [
                "reconstruct", "--input-stacks", *stacks, "--thicknesses", "3", *extra, *FAST,
                "--output-volume", str(folder / "volume.nii.gz"),
                "--output-transforms", str(folder / "transforms.csv"), "--overwrite",
            ]
        )  # fmt: skip
        hashes[name] = {
            "volume": _hash_nifti(folder / "volume.nii.gz"),
            "transforms": _hash_text(folder / "transforms.csv"),
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
