"""The adaptive schedule's final super-resolution: its regularisation and CG iterations, swept.

The final round reconstructs the volume anew at the final poses (``SuperResolutionConfig``'s last
``regularization`` and ``iterations``); nothing after it depends on those two values but the
written volume. So one run of ``svr reconstruct`` can give the final volume at several settings:
with ``SVR_FINAL_SR_SETTINGS="REG:ITERS REG:ITERS ..."`` in the environment and this folder's
``final_sr_hook`` on ``PYTHONPATH``, every ``svr reconstruct`` run (for example the children of
``benchmarks/bench_reconstruct.py``) also saves, beside its ``--output-volume``, the final volume
at each setting and at its own (``STEM-finalsr.npz``, the arrays as written, before any frame's
relabelling, which changes only the affine). ``score`` then writes each as a NIfTI with the
output's affine (after checking that the run's own setting reproduces the written array) and
scores it with the shared yardstick::

    PYTHONPATH=benchmarks/experiments/final_sr_hook SVR_FINAL_SR_SETTINGS="0.03:21 0.05:40" \
        python benchmarks/bench_reconstruct.py --threads 1 --registrations cnn ... --out OUT
    python benchmarks/experiments/final_sr_sweep.py score OUT CASE_FOLDER ...
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

ENV = "SVR_FINAL_SR_SETTINGS"
CV_ENV = "SVR_FINAL_SR_CV"
FOLDS = 5


def _snapshot(state):
    """A copy of the schedule's round state whose tensors the solves below cannot change."""
    import torch

    copied = copy.copy(state)
    for field in dataclasses.fields(state):
        value = getattr(state, field.name)
        if isinstance(value, torch.Tensor):
            setattr(copied, field.name, value.clone())
    return copied


def held_out_ncc(acquisition, state, config, index, regularization, iterations):
    """Mean NCC of left-out slices with their simulation, over ``FOLDS`` folds (slice index mod).

    Each fold's slices (and their background pixels) get zero weight in the final
    super-resolution at the given setting; the volume then simulates them.
    """
    import torch

    from svr.reconstruction.registration import slice_ncc
    from svr.reconstruction.rounds import reject_outliers, super_resolve

    projector = acquisition.projector
    scores = []
    for fold in range(FOLDS):
        st = _snapshot(state)
        outliers = reject_outliers(
            acquisition, st.volume, st.points, config, st.pixel_w, st.slice_w, st.background_points
        )
        held = torch.arange(len(acquisition.slices), device=st.volume.device) % FOLDS == fold
        weights = outliers.weights.clone()
        weights[held[projector.slice_of]] = 0
        background = outliers.background_weights
        if background is not None and acquisition.background is not None:
            background = background.clone()
            background[held[acquisition.background.slice_of]] = 0
        left = outliers._replace(weights=weights, background_weights=background)
        volume = super_resolve(
            acquisition, st.volume, st.points, left, config, index, st.background_points,
            (regularization, iterations),
        )  # fmt: skip
        simulated = projector.forward(volume, st.points)
        ncc = slice_ncc(projector, simulated, acquisition.observed)
        use = held & ~outliers.excluded
        scores.append(float(ncc[use].mean()))
    return scores


def parse_settings(text: str) -> list[tuple[float, int]]:
    """``"0.03:21 0.05:40"`` -> ``[(0.03, 21), (0.05, 40)]``."""
    settings = []
    for item in text.split():
        reg, iters = item.split(":")
        settings.append((float(reg), int(iters)))
    return settings


def key(regularization: float, iterations: int) -> str:
    return f"r{regularization:g}_i{iterations}"


def install(settings: list[tuple[float, int]], output: Path) -> None:
    """Patch the schedule's final round to also save the final volume at ``settings``."""
    from svr.reconstruction import schedule
    from svr.reconstruction.rounds import finalise

    original_round, original_volume = schedule._final_round, schedule._reconstruct_volume
    captured: dict = {}

    def volume(acquisition, state, config, timer, round_index, settings_=None):
        if captured.pop("armed", False):
            captured["state"] = _snapshot(state)
        return original_volume(acquisition, state, config, timer, round_index, settings_)

    def final_round(acquisition, state, config, timer, single, index, settled):
        captured["armed"] = True
        record = original_round(acquisition, state, config, timer, single, index, settled)
        arrays = {"own": finalise(acquisition, state.volume, state.points, state.pixel_w).volume}
        for regularization, iterations in settings:
            alt = _snapshot(captured["state"])
            original_volume(acquisition, alt, config, timer, index, (regularization, iterations))
            arrays[key(regularization, iterations)] = finalise(
                acquisition, alt.volume, alt.points, alt.pixel_w
            ).volume
        reg, iters = schedule._final_settings(config)
        cv = {}
        if os.environ.get(CV_ENV):
            for regularization, iterations in [(reg, iters), *settings]:
                cv[f"cv_{key(regularization, iterations)}"] = np.array(
                    held_out_ncc(
                        acquisition, captured["state"], config, index, regularization, iterations
                    )
                )
        np.savez(
            output,
            own_setting=np.array([reg, iters]),
            **cv,
            **{name: array.detach().float().cpu().numpy() for name, array in arrays.items()},
        )
        return record

    schedule._reconstruct_volume = volume
    schedule._final_round = final_round


def install_from_environment() -> None:
    """Called by ``final_sr_hook/sitecustomize.py`` in every process started with the hook."""
    text = os.environ.get(ENV)
    argv = getattr(sys, "argv", [])
    if not text or "reconstruct" not in argv or "--output-volume" not in argv:
        return
    out = Path(argv[argv.index("--output-volume") + 1])
    stem = out.name.removesuffix(".gz").removesuffix(".nii")
    install(parse_settings(text), out.with_name(f"{stem}-finalsr.npz"))


def score(out: Path, cases: list[Path], only: list[str] | None = None) -> int:
    """Write and score the saved settings (``only`` these and the run's own, if given)."""
    import nibabel as nib
    from bench_common import SHARED, run_scorer

    scorer = SHARED / "tools" / "score_recon.py"
    rows = []
    for case in cases:
        for saved in sorted(out.glob(f"{case.name}-*-finalsr.npz")):
            stem = saved.name.removesuffix("-finalsr.npz")
            written = nib.load(out / f"{stem}.nii.gz")
            data = np.load(saved)
            own = key(float(data["own_setting"][0]), int(data["own_setting"][1]))
            gap = float(np.abs(np.asarray(written.dataobj, dtype=np.float32) - data["own"]).max())
            if gap > 1e-4:
                print(f"{stem}: the saved own-setting volume differs from the written one by {gap}")
                return 1
            for name in data.files:
                if name == "own_setting" or name.startswith("cv_"):
                    continue
                label = own if name == "own" else name
                if only and name != "own" and name not in only:
                    continue
                path = out / f"{stem}-{label}.nii.gz"
                nib.save(nib.Nifti1Image(data[name], written.affine, written.header), path)
                result = run_scorer(scorer, path, case)
                rows.append((stem, label, result["psnr"], result["ssim"], label == own))
                print(f"{stem} {label}: {result['psnr']:.2f} dB, SSIM {result['ssim']:.3f}")
                sys.stdout.flush()
    print("\n| run | setting | PSNR (dB) | SSIM | vs own |\n|---|---|---:|---:|---:|")
    base = {stem: psnr for stem, _, psnr, _, own in rows if own}
    for stem, label, psnr, ssim, own in rows:
        print(f"| {stem} | {label}{' (own)' if own else ''} | {psnr:.2f} | {ssim:.3f} | "
              f"{psnr - base[stem]:+.2f} |")  # fmt: skip
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    scoring = sub.add_parser("score", help="write and score the saved volumes")
    scoring.add_argument("out", type=Path, help="bench_reconstruct.py --out folder")
    scoring.add_argument("cases", type=Path, nargs="+", help="case folders (ground truth)")
    scoring.add_argument("--only", nargs="*", help="settings to score (as r0.03_i40), besides own")
    args = parser.parse_args()
    return score(args.out, args.cases, args.only)


if __name__ == "__main__":
    raise SystemExit(main())
