"""Quality floors on a shared bench case, scored by the shared yardstick (slow; ``-m slow``).

The case is reconstructed in-process (``load_stacks`` with the case's masks and thicknesses,
``reconstruct`` with the default settings, stack registration) and the volume is scored by
``../shared/tools/score_recon.py`` run as a child process: rigid alignment to the ground truth,
a linear intensity fit, then PSNR and SSIM inside the ground-truth brain mask (JSON on its last
line of output). The floors are absolute, not relative to a previous run.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from recon_settings import recon_config

from svr.reconstruction.outputs import write_volume
from svr.reconstruction.pipeline import reconstruct
from svr.reconstruction.stacks import load_stacks

PSNR_FLOOR_DB = 24.0
SSIM_FLOOR = 0.90


@pytest.mark.slow
def test_sb28_moderate_meets_the_quality_floors(shared_data: Path, tmp_path: Path) -> None:
    case = shared_data / "bench" / "sb28-moderate"
    scorer = shared_data.parent / "tools" / "score_recon.py"
    if not case.is_dir() or not scorer.is_file():
        pytest.skip(f"bench case {case} or scorer {scorer} not found")
    thickness = json.loads((case / "case.json").read_text())["thickness"]
    stack_paths = sorted((case / "stacks").glob("*.nii.gz"))
    mask_paths = [case / "masks" / p.name.replace(".nii.gz", "_mask.nii.gz") for p in stack_paths]
    assert len(stack_paths) == len(thickness) > 0
    stacks = load_stacks(stack_paths, mask_paths, thickness)

    device = "cuda" if torch.cuda.is_available() else "cpu"
    result = reconstruct(stacks, recon_config(), device=device, progress=False)
    volume = write_volume(result.volume, tmp_path / "recon.nii.gz")

    run = subprocess.run(
        [sys.executable, str(scorer), str(volume), str(case)],
        capture_output=True,
        text=True,
        check=False,
        timeout=1800,
    )
    assert run.returncode == 0, f"score_recon.py failed:\n{run.stderr[-3000:]}"
    scores = json.loads(run.stdout.strip().splitlines()[-1])
    print(f"sb28-moderate ({device}): {scores}")  # shown with -s
    assert scores["psnr"] >= PSNR_FLOOR_DB, scores
    assert scores["ssim"] >= SSIM_FLOOR, scores
