"""Random smooth deformations: the rigid part is removed, slices read x + d(x) (scipy oracle)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation
from test_slicer import random_poses, smooth_volume

from svr.image import Image
from svr.sampling.dataset import SliceDatasetConfig, SliceStream
from svr.sampling.deform import control_point_positions, random_displacement, remove_rigid_part
from svr.sampling.slicer import SliceConfig, sample_slices, slice_points
from svr.sampling.volume import CanonicalVolume


def _rigid_fit(d: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Least-squares (t, w) of d ~ t + w x x, solved with numpy (independent of the code)."""
    rows, rhs = [], []
    for xi, di in zip(x, d, strict=True):
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1.0
            # (w x x)_k = (x x e_k) . w
            rows.append(np.concatenate([e, np.cross(xi, e)]))
            rhs.append(di[k])
    return np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]


def test_rigid_field_is_removed_entirely(rng):
    x = rng.normal(scale=30.0, size=(64, 3))
    t, w = rng.normal(size=3), 0.05 * rng.normal(size=3)
    d = t + np.cross(w, x)
    out = remove_rigid_part(torch.from_numpy(d), torch.from_numpy(x))
    assert float(out.abs().max()) < 1e-10


def test_residual_has_no_rigid_part(rng):
    x = rng.normal(scale=30.0, size=(125, 3))
    d = rng.normal(scale=3.0, size=(125, 3))
    out = remove_rigid_part(torch.from_numpy(d), torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(_rigid_fit(out, x), 0.0, atol=1e-10)
    # and what was removed is exactly the numpy fit of the input
    t_w = _rigid_fit(d, x)
    np.testing.assert_allclose(d - out, t_w[:3] + np.cross(t_w[3:], x), atol=1e-10)


def test_control_points_span_the_voxel_grid(rng):
    vol = smooth_volume(rng, shape=(11, 13, 9), spacing=0.8)
    pos = control_point_positions(vol, 3)
    affine = vol.affine.numpy()
    corner = affine[:3, :3] @ np.array([10.0, 12.0, 8.0]) + affine[:3, 3]
    np.testing.assert_allclose(pos[0, 0, 0].numpy(), affine[:3, 3])
    np.testing.assert_allclose(pos[-1, -1, -1].numpy(), corner)
    np.testing.assert_allclose(pos[1, 0, 0].numpy(), affine[:3, :3] @ [5.0, 0, 0] + affine[:3, 3])


def test_slices_read_the_volume_at_x_plus_d(rng):
    vol = smooth_volume(rng, shape=(40, 44, 36))
    c = 4
    field = torch.from_numpy(rng.normal(scale=2.0, size=(3, c, c, c)))
    poses = random_poses(rng, 5, trans=2.0)
    config = SliceConfig(size=(24, 20), spacing_mm=1.1)
    got = sample_slices(vol, poses, config, displacement_mm=field).numpy()
    # oracle: trilinear displacement at each point (scipy, in control-grid index units), then
    # trilinear volume at x + d (scipy, in voxel index units)
    pts = slice_points(poses, config.size, config.spacing_mm).numpy().reshape(-1, 3)
    inv = np.linalg.inv(vol.affine.numpy())
    idx = pts @ inv[:3, :3].T + inv[:3, 3]
    ctrl = idx * (c - 1) / (np.array(vol.shape) - 1)
    d = np.stack([map_coordinates(f, ctrl.T, order=1, mode="nearest") for f in field.numpy()], 1)
    moved = (pts + d) @ inv[:3, :3].T + inv[:3, 3]
    want = map_coordinates(vol.data.numpy().astype(np.float64), moved.T, order=1, cval=0.0)
    inside = np.all((ctrl >= 0) & (ctrl <= c - 1), axis=1)
    assert inside.mean() > 0.5
    np.testing.assert_allclose(got.reshape(-1)[inside], want[inside], atol=2e-5)


def test_a_constant_field_is_a_translation(rng):
    vol = smooth_volume(rng)
    shift = np.array([1.5, -2.0, 0.7])
    field = torch.from_numpy(np.broadcast_to(shift[:, None, None, None], (3, 2, 2, 2)).copy())
    poses = random_poses(rng, 4, trans=2.0)
    config = SliceConfig(size=(16, 16), spacing_mm=1.0, thickness_mm=2.0)
    moved = poses.clone()
    moved[:, 3:] += torch.from_numpy(shift)
    torch.testing.assert_close(
        sample_slices(vol, poses, config, displacement_mm=field),
        sample_slices(vol, moved, config),
        atol=1e-5,
        rtol=0,
    )


def test_random_displacement_is_reproducible_smooth_and_rigid_free(rng):
    vol = smooth_volume(rng, shape=(30, 34, 28), spacing=0.8)
    a = random_displacement(vol, 3.0, torch.Generator().manual_seed(5))
    b = random_displacement(vol, 3.0, torch.Generator().manual_seed(5))
    assert a.shape == (3, 5, 5, 5) and a.dtype == torch.float64
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    pos = control_point_positions(vol, 5).reshape(-1, 3).numpy()
    np.testing.assert_allclose(_rigid_fit(a.reshape(3, -1).T.numpy(), pos), 0.0, atol=1e-10)
    assert 2.0 < float(a.std()) < 4.0
    assert float(random_displacement(vol, 0.0, torch.Generator()).abs().max()) == 0.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"std_mm": -1.0}, "'std_mm'"), ({"std_mm": 1.0, "control_points": 1}, "'control_points'")],
)
def test_random_displacement_errors(rng, kwargs, match):
    with pytest.raises(ValueError, match=match):
        random_displacement(smooth_volume(rng), generator=torch.Generator(), **kwargs)


def test_sample_slices_rejects_a_bad_field(rng):
    with pytest.raises(ValueError, match="'displacement_mm'"):
        sample_slices(
            smooth_volume(rng), random_poses(rng, 1), SliceConfig(), torch.zeros(2, 3, 3, 3)
        )


def _brain(rng) -> CanonicalVolume:
    vol = smooth_volume(rng, shape=(48, 48, 48))
    x = torch.linspace(-1, 1, 48)
    r2 = x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2
    data = (vol.data - vol.data.min()) * (r2 < 0.6)
    return CanonicalVolume(
        Image(data, vol.affine), r2 < 0.6, torch.zeros(3, dtype=torch.float64), 1.0
    )


def test_stream_deforms_the_anatomy_not_the_labels(rng):
    brain = _brain(rng)
    base = SliceDatasetConfig(
        slice=SliceConfig(size=(24, 24), spacing_mm=2.0), rotation="uniform", tz_range_mm=8.0
    )
    plain = SliceStream([brain], base).batch(3)
    deformed = SliceStream([brain], SliceDatasetConfig(**{**base.__dict__, "deform_mm": 3.0}))
    one, again = deformed.batch(3), deformed.batch(3)
    torch.testing.assert_close(one["poses"], plain["poses"], rtol=0, atol=0)
    torch.testing.assert_close(one["labels"], plain["labels"], rtol=0, atol=0)
    torch.testing.assert_close(one["slices"], again["slices"], rtol=0, atol=0)
    change = (one["slices"] - plain["slices"]).abs().mean() / plain["slices"].abs().mean()
    assert 0.02 < float(change) < 1.0


@pytest.mark.parametrize(
    ("field", "value"),
    [("deform_mm", -1.0), ("deform_mm", float("nan")), ("deform_control_points", 1)],
)
def test_config_rejects_bad_deformation(field, value):
    with pytest.raises(ValueError, match=f"'{field}'"):
        SliceDatasetConfig(**{field: value})


def test_scipy_rotation_oracle_sanity():
    # the numpy rigid fit used above recovers a known small rotation
    rng = np.random.default_rng(0)
    x = rng.normal(scale=20.0, size=(30, 3))
    w = np.array([0.01, -0.02, 0.015])
    d = Rotation.from_rotvec(w).apply(x) - x
    np.testing.assert_allclose(_rigid_fit(d, x)[3:], w, atol=5e-4)
