"""The benchmarks' scanner-frame relabelling of canonical-frame volumes (bench_common).

Oracle: a known rigid ``G`` (scipy ``Rotation``) between the frames; the canonical poses are
built from the stack's k-planes through ``G^-1``, and the copy's affine must be ``G`` times the
volume's, with its array untouched and an excluded slice's wild pose ignored.
"""

from __future__ import annotations

import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from svr.image import load_nifti, stack_slice_poses
from svr.pose_io import matrices_to_table, write_pose_table

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_common import scanner_frame_copy


def rigid(rotvec, shift) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    out[:3, 3] = shift
    return out


def test_scanner_frame_copy_applies_the_frame_the_poses_give(tmp_path, rng):
    stack_affine = rigid([0.3, -0.2, 0.5], [10.0, -4.0, 7.0]) @ np.diag([1.1, 1.1, 3.0, 1.0])
    stack = tmp_path / "stack.nii.gz"
    nib.save(nib.Nifti1Image(rng.random((12, 10, 6)).astype(np.float32), stack_affine), stack)

    planes = stack_slice_poses(load_nifti(stack))
    G = rigid([-1.1, 0.7, 2.0], [30.0, -12.0, 5.0])  # scanner <- canonical
    canonical = torch.from_numpy(np.linalg.inv(G)) @ planes
    wild = torch.from_numpy(rigid([2.0, 0.0, 0.0], [90.0, 0.0, 0.0]))
    canonical[2] = wild  # an excluded slice far off
    table = matrices_to_table([str(stack)] * 6, torch.arange(6), canonical, "canonical")
    transforms = write_pose_table(
        table, tmp_path / "t.csv", extra_columns={"excluded": [k == 2 for k in range(6)]}
    )
    volume_affine = rigid([0.0, 0.4, 0.0], [-5.0, 3.0, 1.0]) @ np.diag([0.8, 0.8, 0.8, 1.0])
    data = rng.random((7, 8, 9)).astype(np.float32)
    volume = tmp_path / "volume.nii.gz"
    nib.save(nib.Nifti1Image(data, volume_affine), volume)
    out = scanner_frame_copy(volume, transforms, tmp_path / "copy.nii.gz")
    copy = nib.load(out)
    np.testing.assert_allclose(copy.affine, G @ volume_affine, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(copy.dataobj), data)


def test_the_benchmarks_read_the_last_verdict_a_log_states():
    from bench_common import verdict_in

    verbose = (
        "2026-12-07 17:16:48,830 INFO svr.x: the registered stacks' frame\n"
        "2026-12-07 17:19:09,806 WARNING svr.reconstruction.pipeline: verdict: failed, canonical "
        "frame uncertain: not converged\n"
        "wrote out.nii.gz: 90 slices\n"
        "verdict: failed, canonical frame uncertain: not converged\n"
    )
    assert verdict_in(verbose) == "failed, canonical frame uncertain: not converged"
    summary = "# svr reconstruct summary\nframe: canonical\nverdict: ok, scanner frame\n"
    assert verdict_in(summary) == "ok, scanner frame"
    assert verdict_in("# svr reconstruct summary\nframe: canonical\n") == ""
