"""The real-scan mask comparison's frame mapping (benchmarks/bench_real_mask_errors.py).

Oracle: nibabel's ``apply_affine`` on the voxel indices, then the inverse of a frame built with
scipy's ``Rotation``: a voxel must land where the two maps, applied one after the other, put it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from nibabel.affines import apply_affine
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_real_mask_errors import canonical_points


def test_voxels_land_in_the_reference_canonical_frame() -> None:
    affine = np.diag([1.125, 1.125, 3.3, 1.0])
    affine[:3, :3] = (
        Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix() @ affine[:3, :3]
    )
    affine[:3, 3] = [-150.0, 40.0, 12.5]
    frame = np.eye(4)  # canonical mm -> scanner mm
    frame[:3, :3] = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    frame[:3, 3] = [5.0, -7.0, 30.0]
    mask = np.zeros((9, 8, 5), dtype=bool)
    mask[2, 3, 1] = mask[7, 0, 4] = mask[0, 7, 2] = True
    got = canonical_points(mask, affine, np.linalg.inv(frame))
    world = apply_affine(affine, np.argwhere(mask))
    expected = (world - frame[:3, 3]) @ frame[:3, :3]  # R^T (w - t), row by row
    assert np.allclose(got, expected, atol=1e-9)
    # Back through the frame, the scanner points themselves.
    assert np.allclose(apply_affine(frame, got), world, atol=1e-9)
