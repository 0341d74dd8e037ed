"""Tests of the slice poses in :mod:`svr.sampling.poses`.

Oracles: scipy's ``Rotation.from_euler("xyz", ...)`` / ``as_euler`` for the rotations, the
definition ``t = R (0, 0, Tz)`` for the translations, NumPy grids for the grid values and order,
the analytic Haar distribution of the rotation angle (density ``(1 - cos θ) / π``) and of rotated
directions (uniform on the sphere: each coordinate uniform in ``[-1, 1]``), and the inverse
converters of :mod:`svr.geometry` for the labels.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.spatial.transform import Rotation

import svr.geometry as g
from svr.representation_registry import REPRESENTATIONS
from svr.sampling.poses import (
    EulerGridConfig,
    euler_grid,
    euler_grid_poses,
    euler_to_poses,
    iter_euler_grid_poses,
    pose_labels,
    random_slice_poses,
)

F32, F64 = torch.float32, torch.float64
DEFAULT_M = 11**3 * 41


def N(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().to(F64).numpy()


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def matrices(poses: torch.Tensor) -> np.ndarray:
    return Rotation.from_rotvec(N(poses[..., :3]).reshape(-1, 3)).as_matrix()


def assert_euler_poses(poses: torch.Tensor, angles: np.ndarray, tz: np.ndarray, tol: float) -> None:
    """Rotation == scipy from_euler("xyz", angles) and t == R (0, 0, Tz), for (M, 6) poses."""
    expected = Rotation.from_euler("xyz", angles).as_matrix()
    np.testing.assert_allclose(matrices(poses), expected, rtol=0, atol=tol)
    normal = expected[:, :, 2]
    np.testing.assert_allclose(N(poses[:, 3:]), normal * tz[:, None], rtol=0, atol=40 * tol)


# ----------------------------------------------------------------------------- Euler grid


@pytest.fixture(scope="module")
def default_grid() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    angles, tz = euler_grid()
    return angles, tz, euler_grid_poses()


def test_default_grid_size_values_and_order(default_grid) -> None:
    angles, tz, poses = default_grid
    config = EulerGridConfig()
    assert config.num_angles == 11 and config.num_tz == 41 and config.num_poses == DEFAULT_M
    assert (
        angles.shape == (DEFAULT_M, 3)
        and tz.shape == (DEFAULT_M,)
        and poses.shape == (DEFAULT_M, 6)
    )
    assert angles.dtype == tz.dtype == poses.dtype == F64
    degrees = np.arange(-90, 91, 18, dtype=np.float64)
    offsets = np.arange(-40, 41, 2, dtype=np.float64)
    assert degrees.size == 11 and offsets.size == 41
    for column in range(3):
        np.testing.assert_array_equal(np.unique(np.rad2deg(N(angles[:, column])).round(9)), degrees)
    np.testing.assert_array_equal(np.unique(N(tz)), offsets)
    # Order: row-major over (Rx, Ry, Rz, Tz), Tz fastest.
    rx, ry, rz, t = np.meshgrid(
        np.deg2rad(degrees), np.deg2rad(degrees), np.deg2rad(degrees), offsets, indexing="ij"
    )
    expected = np.stack([rx, ry, rz], axis=-1).reshape(-1, 3)
    np.testing.assert_allclose(N(angles), expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(N(tz), t.reshape(-1))
    assert np.unique(np.concatenate([N(angles), N(tz)[:, None]], 1), axis=0).shape[0] == DEFAULT_M


def test_grid_poses_match_scipy_on_a_subset(default_grid) -> None:
    angles, tz, poses = default_grid
    for i in np.random.default_rng(1).choice(DEFAULT_M, size=200, replace=False):
        a, z = N(angles[i]), float(tz[i])
        R = Rotation.from_euler("xyz", a).as_matrix()
        np.testing.assert_allclose(Rotation.from_rotvec(N(poses[i, :3])).as_matrix(), R, atol=1e-13)
        np.testing.assert_allclose(N(poses[i, 3:]), R @ np.array([0.0, 0.0, z]), atol=1e-12)


def test_grid_poses_match_scipy_on_the_full_grid(default_grid) -> None:
    angles, tz, poses = default_grid
    assert_euler_poses(poses, N(angles), N(tz), tol=1e-13)
    # Rotation angles lie in [0, pi].
    assert float(poses[:, :3].norm(dim=-1).max()) <= math.pi + 1e-12


def test_grid_translation_is_tz_along_the_slice_normal(default_grid) -> None:
    _, tz, poses = default_grid
    R = g.so3_exp(poses[:, :3])
    torch.testing.assert_close(R[:, :, 2] * tz[:, None], poses[:, 3:], rtol=0, atol=1e-12)
    # The slice centre (u, v) = (0, 0) lies |Tz| mm from the origin, on the normal.
    torch.testing.assert_close(poses[:, 3:].norm(dim=-1), tz.abs(), rtol=0, atol=1e-12)
    # A point (u, v, 0) of the plane maps to R (u, v, 0) + t: its offset along the normal is Tz.
    uv0 = torch.tensor([13.0, -7.0, 0.0], dtype=F64)
    mapped = (g.vector_to_se3(poses) @ torch.cat([uv0, uv0.new_ones(1)]))[:, :3]
    torch.testing.assert_close((mapped * R[:, :, 2]).sum(-1), tz, rtol=0, atol=1e-12)


def test_grid_poses_equal_poses_from_euler(default_grid) -> None:
    angles, tz, poses = default_grid
    torch.testing.assert_close(euler_to_poses(angles, tz), poses, rtol=0, atol=1e-14)


@pytest.mark.parametrize("chunk_size", [1000, 4096, 4913, DEFAULT_M, 10**6])
def test_chunked_iteration_equals_the_full_grid(default_grid, chunk_size: int) -> None:
    poses = default_grid[2]
    chunks = list(iter_euler_grid_poses(chunk_size=chunk_size))
    assert all(c.shape == (chunk_size, 6) for c in chunks[:-1])
    assert 0 < chunks[-1].shape[0] <= chunk_size
    assert len(chunks) == math.ceil(DEFAULT_M / chunk_size)
    assert torch.equal(torch.cat(chunks), poses)


def test_chunked_iteration_small_chunks_and_dtype() -> None:
    config = EulerGridConfig(angle_step_deg=45, angle_range_deg=45, tz_step_mm=5, tz_range_mm=5)
    full = euler_grid_poses(config)
    assert full.shape == (27 * 3, 6)
    for chunk_size in (1, 2, 7, 26, 81):
        assert torch.equal(torch.cat(list(iter_euler_grid_poses(config, chunk_size))), full)
    chunks32 = list(iter_euler_grid_poses(config, chunk_size=10, dtype=F32, device="cpu"))
    assert all(c.dtype == F32 for c in chunks32)
    assert torch.equal(torch.cat(chunks32), full.to(F32))
    assert torch.equal(euler_grid_poses(config, dtype=F32, device="cpu"), full.to(F32))


def test_iteration_is_lazy() -> None:
    # A grid of 181**3 * 81 ~ 4.8e8 poses (~23 GB): only the first chunk is computed.
    config = EulerGridConfig(angle_step_deg=1.0, tz_step_mm=1.0)
    assert config.num_poses == 181**3 * 81
    first = next(iter_euler_grid_poses(config, chunk_size=200))
    index = torch.arange(200, dtype=F64)
    rz = torch.div(index, 81, rounding_mode="floor") - 90
    angles = torch.stack([torch.full_like(rz, -90.0), torch.full_like(rz, -90.0), rz], dim=-1)
    expected = euler_to_poses(angles.deg2rad(), index % 81 - 40)
    torch.testing.assert_close(
        g.vector_to_se3(first), g.vector_to_se3(expected), rtol=0, atol=1e-12
    )


@pytest.mark.parametrize(
    ("config", "angles_deg", "offsets_mm"),
    [
        (
            EulerGridConfig(angle_step_deg=30, angle_range_deg=60, tz_step_mm=4, tz_range_mm=8),
            [-60, -30, 0, 30, 60],
            [-8, -4, 0, 4, 8],
        ),
        (
            EulerGridConfig(angle_step_deg=10, angle_range_deg=0, tz_step_mm=2.5, tz_range_mm=5),
            [0],
            [-5, -2.5, 0, 2.5, 5],
        ),
        (
            EulerGridConfig(angle_step_deg=45, angle_range_deg=180, tz_step_mm=1, tz_range_mm=0),
            [-180, -135, -90, -45, 0, 45, 90, 135, 180],
            [0],
        ),
        (
            EulerGridConfig(
                angle_step_deg=0.1, angle_range_deg=0.3, tz_step_mm=0.1, tz_range_mm=0.2
            ),
            [-0.3, -0.2, -0.1, 0, 0.1, 0.2, 0.3],
            [-0.2, -0.1, 0, 0.1, 0.2],
        ),
    ],
)
def test_other_steps_and_ranges(config, angles_deg, offsets_mm) -> None:
    angles, tz = euler_grid(config)
    m = len(angles_deg) ** 3 * len(offsets_mm)
    assert config.num_poses == m and angles.shape == (m, 3) and tz.shape == (m,)
    np.testing.assert_allclose(N(config.angle_values_rad()), np.deg2rad(angles_deg), atol=1e-15)
    np.testing.assert_allclose(N(config.tz_values_mm()), offsets_mm, atol=1e-14)
    np.testing.assert_allclose(np.unique(N(tz)), offsets_mm, atol=1e-14)
    poses = euler_grid_poses(config)
    assert_euler_poses(poses, N(angles), N(tz), tol=1e-13)
    assert torch.equal(torch.cat(list(iter_euler_grid_poses(config, chunk_size=17))), poses)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"angle_step_deg": 0.0}, "angle_step_deg"),
        ({"angle_step_deg": -18.0}, "angle_step_deg"),
        ({"angle_step_deg": float("nan")}, "angle_step_deg"),
        ({"angle_range_deg": -90.0}, "angle_range_deg"),
        ({"angle_range_deg": float("inf")}, "angle_range_deg"),
        ({"angle_range_deg": 100.0}, "angle_range_deg"),
        ({"angle_range_deg": 90.0 + 1e-6}, "angle_range_deg"),
        ({"tz_step_mm": 0.0}, "tz_step_mm"),
        ({"tz_step_mm": float("inf")}, "tz_step_mm"),
        ({"tz_range_mm": -1.0}, "tz_range_mm"),
        ({"tz_range_mm": 41.0}, "tz_range_mm"),
    ],
)
def test_bad_configs_raise_naming_the_field(kwargs, field: str) -> None:
    with pytest.raises(ValueError, match=f"'{field}'"):
        EulerGridConfig(**kwargs)


def test_config_is_frozen_and_tolerates_rounding() -> None:
    config = EulerGridConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.angle_step_deg = 1.0  # type: ignore[misc]
    assert EulerGridConfig(tz_step_mm=0.1, tz_range_mm=40.0).num_tz == 801  # 40 / 0.1 = 400.00..06
    assert EulerGridConfig(angle_range_deg=90.0 + 1e-12).num_angles == 11


def test_argument_errors() -> None:
    for chunk_size in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="chunk_size"):
            iter_euler_grid_poses(chunk_size=chunk_size)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="dtype"):
        iter_euler_grid_poses(dtype=torch.int64)
    with pytest.raises(TypeError, match="dtype"):
        euler_grid_poses(dtype=torch.int32)
    with pytest.raises(TypeError, match="tz_mm"):
        euler_to_poses(torch.zeros(2, 3), torch.zeros(2, dtype=torch.int64))
    with pytest.raises(ValueError, match="angles_rad"):
        euler_to_poses(torch.zeros(2, 2), torch.zeros(2))


def test_poses_from_euler_broadcasts_and_keeps_dtype() -> None:
    angles = torch.tensor([0.3, -0.2, 1.1], dtype=F32)
    tz = torch.tensor([[1.0], [-2.0]], dtype=F32)
    poses = euler_to_poses(angles, tz)
    assert poses.shape == (2, 1, 6) and poses.dtype == F32
    R = Rotation.from_euler("xyz", N(angles)).as_matrix()
    np.testing.assert_allclose(N(poses[1, 0, 3:]), R[:, 2] * -2.0, atol=1e-6)
    np.testing.assert_allclose(matrices(poses[0, 0]), R[None], atol=1e-6)


# ----------------------------------------------------------------------------- random poses


def test_random_euler_poses_ranges_and_uniformity() -> None:
    n, angle_range, tz_range = 4000, 90.0, 40.0
    poses = random_slice_poses(n, gen(3), angle_range, tz_range)
    assert poses.shape == (n, 6) and poses.dtype == F64
    R = matrices(poses)
    angles = np.rad2deg(Rotation.from_matrix(R).as_euler("xyz"))
    tz = np.einsum("ni,ni->n", N(poses[:, 3:]), R[:, :, 2])
    assert np.abs(angles).max() <= angle_range + 1e-9
    assert np.abs(tz).max() <= tz_range + 1e-9
    # The translation is along the normal: t = Tz R[:, 2].
    np.testing.assert_allclose(N(poses[:, 3:]), R[:, :, 2] * tz[:, None], atol=1e-12)
    for column in range(3):
        uniform = stats.uniform(-angle_range, 2 * angle_range).cdf
        assert stats.kstest(angles[:, column], uniform).pvalue > 1e-3
    assert stats.kstest(tz, stats.uniform(-tz_range, 2 * tz_range).cdf).pvalue > 1e-3
    # Independent angles: no strong correlation between them.
    assert np.abs(np.corrcoef(angles.T) - np.eye(3)).max() < 0.1


@pytest.mark.parametrize(("angle_range", "tz_range"), [(30.0, 10.0), (0.0, 0.0), (5.0, 0.0)])
def test_random_euler_poses_other_ranges(angle_range: float, tz_range: float) -> None:
    poses = random_slice_poses(500, gen(4), angle_range_deg=angle_range, tz_range_mm=tz_range)
    R = matrices(poses)
    angles = np.rad2deg(Rotation.from_matrix(R).as_euler("xyz"))
    tz = np.einsum("ni,ni->n", N(poses[:, 3:]), R[:, :, 2])
    assert np.abs(angles).max() <= angle_range + 1e-9
    assert np.abs(tz).max() <= tz_range + 1e-9
    if angle_range > 0:
        assert np.abs(angles).max() > 0.8 * angle_range


@pytest.mark.parametrize("rotation", ["euler", "uniform"])
def test_random_poses_are_deterministic_and_use_only_the_generator(rotation: str) -> None:
    state = torch.random.get_rng_state()
    a = random_slice_poses(300, gen(11), rotation=rotation)
    torch.manual_seed(12345)  # the global RNG must not matter
    state_after_seed = torch.random.get_rng_state()
    b = random_slice_poses(300, gen(11), rotation=rotation)
    assert torch.equal(torch.random.get_rng_state(), state_after_seed)
    assert not torch.equal(state, state_after_seed)
    assert torch.equal(a, b)
    assert not torch.allclose(a, random_slice_poses(300, gen(12), rotation=rotation))
    # One generator continues its stream; dtype does not change the samples.
    g1 = gen(5)
    first, second = (random_slice_poses(10, g1, rotation=rotation) for _ in range(2))
    assert not torch.allclose(first, second)
    assert torch.equal(random_slice_poses(10, gen(5), rotation=rotation, dtype=F32), first.to(F32))
    assert random_slice_poses(0, gen(5), rotation=rotation).shape == (0, 6)


def test_random_uniform_rotations_are_haar_distributed() -> None:
    n, tz_range = 20000, 40.0
    poses = random_slice_poses(n, gen(7), tz_range_mm=tz_range, rotation="uniform")
    assert poses.shape == (n, 6)
    theta = N(poses[:, :3].norm(dim=-1))
    assert theta.max() <= math.pi + 1e-12
    # Rotation angle: density (1 - cos θ)/π, mean π/2 + 2/π, variance π²/3 + 2 - mean².
    mean = math.pi / 2 + 2 / math.pi
    std = math.sqrt(math.pi**2 / 3 + 2 - mean**2)
    assert abs(theta.mean() - mean) < 4 * std / math.sqrt(n)
    assert stats.kstest(theta, lambda x: (x - np.sin(x)) / math.pi).pvalue > 1e-3
    # Rotated directions and rotation axes are uniform on the sphere: each coordinate ~ U[-1, 1].
    R = matrices(poses)
    axes = N(poses[:, :3]) / theta[:, None]
    for vectors in (R[:, :, 0], R[:, :, 2], R[:, 0, :], axes):
        for coordinate in range(3):
            assert stats.kstest(vectors[:, coordinate], stats.uniform(-1, 2).cdf).pvalue > 1e-3
    # Not the Euler sampling: Euler angles span the whole of (-180, 180].
    assert np.abs(Rotation.from_matrix(R).as_euler("xyz", degrees=True)[:, 0]).max() > 170
    tz = np.einsum("ni,ni->n", N(poses[:, 3:]), R[:, :, 2])
    np.testing.assert_allclose(N(poses[:, 3:]), R[:, :, 2] * tz[:, None], atol=1e-12)
    assert stats.kstest(tz, stats.uniform(-tz_range, 2 * tz_range).cdf).pvalue > 1e-3


def test_random_pose_argument_errors() -> None:
    with pytest.raises(TypeError, match="generator"):
        random_slice_poses(3, None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="generator"):
        random_slice_poses(3, 0)  # type: ignore[arg-type]
    for n in (-1, 2.0, True):
        with pytest.raises(ValueError, match="'n'"):
            random_slice_poses(n, gen())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="angle_range_deg"):
        random_slice_poses(3, gen(), angle_range_deg=-1.0)
    with pytest.raises(ValueError, match="tz_range_mm"):
        random_slice_poses(3, gen(), tz_range_mm=float("nan"))
    with pytest.raises(ValueError, match=r"euler.*uniform"):
        random_slice_poses(3, gen(), rotation="haar")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="dtype"):
        random_slice_poses(3, gen(), dtype=torch.int64)


# ----------------------------------------------------------------------------- labels

INVERSES = {
    "se3": lambda label, a: label,
    "quat_translation": lambda label, a: g.quat_translation_to_pose(label),
    "anchor_points": lambda label, a: g.anchor_points_to_pose(label, a),
    "rotation6d_translation": lambda label, a: g.rotation_6d_translation_to_pose(label),
}
WIDTHS = {"se3": 6, "quat_translation": 7, "anchor_points": 9, "rotation6d_translation": 9}


def test_representation_names() -> None:
    assert tuple(REPRESENTATIONS) == (
        "se3",
        "quat_translation",
        "anchor_points",
        "rotation6d_translation",
    )


@pytest.mark.parametrize("representation", REPRESENTATIONS)
@pytest.mark.parametrize("half_size", [60.0, 25.0])
def test_labels_shapes_and_round_trip(default_grid, representation: str, half_size: float) -> None:
    poses = torch.cat(
        [
            default_grid[2][::7],
            random_slice_poses(2000, gen(8), rotation="uniform"),
            random_slice_poses(2000, gen(9), rotation="euler"),
        ]
    ).reshape(-1, 2, 6)
    labels = pose_labels(poses, representation, anchor_half_size_mm=half_size)
    assert labels.shape == (*poses.shape[:-1], WIDTHS[representation]) and labels.dtype == F64
    back = INVERSES[representation](labels, half_size)
    # The same rigid transform ...
    torch.testing.assert_close(g.vector_to_se3(back), g.vector_to_se3(poses), rtol=0, atol=1e-10)
    # ... and the same vector, away from angle π where r and -r are the same rotation.
    regular = poses[..., :3].norm(dim=-1) < math.pi - 1e-6
    torch.testing.assert_close(back[regular], poses[regular], rtol=0, atol=1e-10)


def test_labels_match_the_geometry_converters() -> None:
    poses = random_slice_poses(50, gen(10), rotation="uniform", dtype=F32)
    assert pose_labels(poses, "se3") is poses
    assert torch.equal(pose_labels(poses, "quat_translation"), g.pose_to_quat_translation(poses))
    assert torch.equal(pose_labels(poses, "anchor_points"), g.pose_to_anchor_points(poses))
    assert torch.equal(
        pose_labels(poses, "anchor_points", 30.0), g.pose_to_anchor_points(poses, 30.0)
    )
    assert torch.equal(
        pose_labels(poses, "rotation6d_translation"), g.pose_to_rotation_6d_translation(poses)
    )
    assert all(pose_labels(poses, r).dtype == F32 for r in REPRESENTATIONS)


def test_label_errors() -> None:
    poses = torch.zeros(3, 6, dtype=F64)
    with pytest.raises(ValueError, match="se3, quat_translation, anchor_points, rotation6d"):
        pose_labels(poses, "euler")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=re.escape("(..., 6)")):
        pose_labels(torch.zeros(3, 7, dtype=F64), "se3")
    with pytest.raises(TypeError, match="floating-point"):
        pose_labels(torch.zeros(3, 6, dtype=torch.int64), "quat_translation")
    with pytest.raises(ValueError, match="half_size"):
        pose_labels(poses, "anchor_points", anchor_half_size_mm=0.0)


def _ball_volume(radius_mm: float = 20.0):
    from svr.image import Image
    from svr.sampling.volume import CanonicalVolume

    x = torch.arange(64, dtype=torch.float64) - 31.5
    r = (x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2).sqrt()
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, 3] = -31.5
    brain = r < radius_mm
    image = Image(brain.float(), affine)
    return CanonicalVolume(image, brain, torch.zeros(3, dtype=torch.float64), 1.0)


def test_draw_pose_candidates_kinds():
    from svr.sampling.poses import POSE_DRAWS, draw_pose_candidates

    assert POSE_DRAWS == ("euler", "uniform", "euler-grid")
    for kind in ("euler", "uniform"):
        got = draw_pose_candidates(kind, 5, torch.Generator().manual_seed(1))
        want = random_slice_poses(5, torch.Generator().manual_seed(1), rotation=kind)
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    grid = draw_pose_candidates("euler-grid", 7, torch.Generator().manual_seed(2))
    order = torch.randperm(len(euler_grid_poses()), generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(grid, euler_grid_poses()[order[:7]], rtol=0, atol=0)
    with pytest.raises(ValueError, match="'kind' must be one of euler, uniform, euler-grid"):
        draw_pose_candidates("grid", 3, torch.Generator())


def test_draw_validation_poses_keep_brain_slices_in_order():
    from svr.sampling.poses import draw_pose_candidates, draw_validation_poses
    from svr.sampling.slicer import SliceConfig, brain_fraction

    volume = _ball_volume()
    config = SliceConfig(size=(16, 16), spacing_mm=2.0)
    poses = draw_validation_poses(volume, 12, config, torch.Generator().manual_seed(3), "uniform")
    assert poses.shape == (12, 6) and poses.dtype == torch.float64
    mask = volume.image  # the ball's intensities are its mask
    assert bool((brain_fraction(mask, poses, config) >= 0.1).all())
    # the kept poses are the first passing candidates, in the order drawn
    candidates = draw_pose_candidates("uniform", 24, torch.Generator().manual_seed(3))
    passing = candidates[brain_fraction(mask, candidates, config) >= 0.1]
    n = min(len(passing), 12)
    torch.testing.assert_close(poses[:n], passing[:n], rtol=0, atol=0)


def test_draw_validation_poses_errors():
    from svr.sampling.poses import draw_validation_poses
    from svr.sampling.slicer import SliceConfig

    volume, config = _ball_volume(radius_mm=1.0), SliceConfig(size=(16, 16), spacing_mm=2.0)
    with pytest.raises(ValueError, match=r"only 0 of 5 slices reach a brain fraction of 0\.9"):
        draw_validation_poses(volume, 5, config, torch.Generator(), min_brain_fraction=0.9)
    with pytest.raises(ValueError, match="'num_slices'"):
        draw_validation_poses(volume, 0, config, torch.Generator())
    with pytest.raises(ValueError, match="'min_brain_fraction'"):
        draw_validation_poses(volume, 1, config, torch.Generator(), min_brain_fraction=1.0)
