"""The benchmarks' independent mid-sagittal oracle (midplane_oracle, bench_real_midplane).

Oracle: a phantom mirror-symmetric about its x = 0 plane by construction, turned by a known
rotation (scipy ``Rotation``): the measured normal must be the turned x axis, in the array's
axes when the array is turned, in the world when only the affine is.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
from scipy.ndimage import affine_transform, gaussian_filter
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from midplane_oracle import midplane_of_array, midplane_of_file


def symmetric_phantom(size: int = 40) -> np.ndarray:
    """(size,)*3 blobs placed in mirror pairs about the central x plane, unlike along y and z."""
    grid = np.stack(np.meshgrid(*(np.arange(size) - (size - 1) / 2,) * 3, indexing="ij"), -1)
    data = np.zeros((size,) * 3, dtype=np.float32)
    for centre, radius, value in (
        ((6, 4, 2), 5, 1.0),
        ((9, -7, -4), 4, 0.6),
        ((4, 2, 10), 3, 0.8),
        ((0, -2, -9), 4, 0.5),
    ):
        for sign in (1, -1):
            at = np.array([sign * centre[0], centre[1], centre[2]])
            data[np.linalg.norm(grid - at, axis=-1) < radius] = value
    return gaussian_filter(data, 1.0)


def turned(data: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    centre = (np.array(data.shape) - 1) / 2
    index = rotation.T  # isotropic voxels: out(p) = in(R^T (p - c) + c)
    return affine_transform(data, index, offset=centre - index @ centre, order=1)


def test_the_oracle_finds_a_known_turned_midplane():
    phantom = symmetric_phantom()
    rotation = Rotation.from_euler("xyz", [8.0, 12.0, -9.0], degrees=True).as_matrix()
    estimate = midplane_of_array(turned(phantom, rotation), np.array([1.5, 1.5, 1.5]))
    expected = rotation @ np.array([1.0, 0.0, 0.0])
    error = math.degrees(math.acos(min(1.0, abs(float(estimate.normal @ expected)))))
    assert error < 1.0
    assert 10.0 < estimate.tilt_deg < 20.0
    assert estimate.correlation > 0.9


def test_the_output_frame_is_the_files_world_not_its_voxel_grid(tmp_path):
    phantom = symmetric_phantom()  # symmetric about its grid's first axis
    turn = Rotation.from_euler("xyz", [0.0, 9.0, 5.0], degrees=True).as_matrix()
    affine = np.eye(4)
    affine[:3, :3] = turn * 1.5  # voxels -> canonical mm: the grid turned by ``turn``
    path = tmp_path / "volume.nii.gz"
    nib.save(nib.Nifti1Image(phantom, affine), path)
    estimate, normal = midplane_of_file(path)
    assert estimate.tilt_deg < 1.0  # level on its own grid
    np.testing.assert_allclose(normal, turn[:, 0], atol=0.02)  # the grid's axis, in the world
    world_tilt = math.degrees(math.acos(abs(float(normal[0]))))
    expected = math.degrees(math.acos(float(turn[0, 0])))
    assert abs(world_tilt - expected) < 1.0
