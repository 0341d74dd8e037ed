"""The slice sampler: geometry against scipy and array planes, PSF, bench-case round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from oracles import foreground_cc, truth_poses
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from svr.geometry import vector_to_se3
from svr.image import Image, load_nifti
from svr.sampling.slicer import (
    SliceConfig,
    brain_fraction,
    pose_matrices,
    psf_offsets,
    sample_slices,
    slice_points,
)


def smooth_volume(rng: np.random.Generator, shape=(40, 44, 36), spacing=1.0) -> Image:
    from scipy.ndimage import gaussian_filter

    data = gaussian_filter(rng.normal(size=shape), 2.0)
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] *= spacing
    affine[:3, 3] = -torch.tensor([(n - 1) / 2 * spacing for n in shape], dtype=torch.float64)
    return Image(torch.from_numpy(data).float(), affine)


def random_poses(rng: np.random.Generator, n: int, trans: float = 4.0) -> torch.Tensor:
    r = Rotation.random(n, random_state=rng).as_rotvec()
    return torch.from_numpy(np.concatenate([r, rng.normal(scale=trans, size=(n, 3))], 1))


def test_slice_points_follow_the_design_convention():
    pose = torch.tensor([[0.3, -0.2, 0.5, 1.0, 2.0, 3.0]], dtype=torch.float64)
    pts = slice_points(pose, (5, 7), 0.5)
    T = vector_to_se3(pose)[0]
    # pixel (a, b) sits at (u, v) = ((a - 2) 0.5, (b - 3) 0.5); u along axis 0, v along axis 1
    for a, b in [(0, 0), (2, 3), (4, 6), (1, 5)]:
        uvw = torch.tensor([(a - 2) * 0.5, (b - 3) * 0.5, 0.0, 1.0], dtype=torch.float64)
        torch.testing.assert_close(pts[0, a, b], (T @ uvw)[:3])


def test_slices_equal_scipy_map_coordinates(rng):
    vol = smooth_volume(rng)
    poses = random_poses(rng, 8)
    config = SliceConfig(size=(32, 30), spacing_mm=0.9)
    got = sample_slices(vol, poses, config).numpy()
    pts = slice_points(poses, config.size, config.spacing_mm).numpy().reshape(-1, 3)
    inv = np.linalg.inv(vol.affine.numpy())
    idx = pts @ inv[:3, :3].T + inv[:3, 3]
    want = map_coordinates(
        vol.data.numpy().astype(np.float64), idx.T, order=1, mode="constant", cval=0.0
    ).reshape(got.shape)
    inside = np.all((idx >= 0) & (idx <= np.array(vol.shape) - 1), axis=1).reshape(got.shape)
    assert inside.mean() > 0.5
    cc = np.corrcoef(got[inside], want[inside])[0, 1]
    assert cc > 0.999
    np.testing.assert_allclose(got[inside], want[inside], atol=1e-5)


def test_axis_aligned_poses_give_the_volume_array_planes(rng):
    vol = smooth_volume(rng, shape=(20, 22, 18), spacing=1.0)
    k = 11
    # identity rotation: u along x (axis i), v along y (axis j); the plane z = z_k cuts axis k
    z = float(vol.affine[2, 3]) + k
    pose = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, z]], dtype=torch.float64)  # grid centre is x=y=0
    got = sample_slices(vol, pose, SliceConfig(size=(20, 22), spacing_mm=1.0))[0]
    torch.testing.assert_close(got, vol.data[:, :, k], atol=1e-5, rtol=0)
    # a rotation of 90 deg about x maps v to z: the slice is the plane j = const
    j = 9
    y = float(vol.affine[1, 3]) + j
    pose = torch.tensor([[np.pi / 2, 0.0, 0.0, 0.0, y, 0.0]], dtype=torch.float64)
    got = sample_slices(vol, pose, SliceConfig(size=(20, 18), spacing_mm=1.0))[0]
    torch.testing.assert_close(got, vol.data[:, j, :], atol=1e-5, rtol=0)


def test_poses_as_vectors_and_matrices_agree(rng):
    vol = smooth_volume(rng)
    poses = random_poses(rng, 4)
    config = SliceConfig(size=(16, 16))
    a = sample_slices(vol, poses, config)
    torch.testing.assert_close(sample_slices(vol, vector_to_se3(poses), config), a)
    torch.testing.assert_close(sample_slices(vol, vector_to_se3(poses)[:, :3], config), a)


def test_psf_quadrature_weights_and_thickness_integration(rng):
    config = SliceConfig(thickness_mm=3.0, psf_samples=5)
    offsets = psf_offsets(config)
    assert len(offsets) == 5 and sum(w for _, w in offsets) == pytest.approx(1.0)
    sigma = 3.0 / 2.3548200450309493
    second_moment = sum(w * o[2] ** 2 for o, w in offsets)
    assert second_moment == pytest.approx(sigma**2)
    assert len(psf_offsets(SliceConfig(thickness_mm=3.0, in_plane_psf=True, psf_samples=3))) == 27
    # Against brute-force integration along the normal with many thin samples.
    vol = smooth_volume(rng)
    poses = random_poses(rng, 3)
    got = sample_slices(vol, poses, SliceConfig(size=(24, 24), thickness_mm=3.0))
    ws = np.linspace(-4 * sigma, 4 * sigma, 161)
    weights = np.exp(-0.5 * (ws / sigma) ** 2)
    weights /= weights.sum()
    T = pose_matrices(poses)
    brute = torch.zeros_like(got)
    for w, wt in zip(ws, weights, strict=True):
        shifted = T.clone()
        shifted[:, :3, 3] += float(w) * T[:, :3, 2]
        brute += float(wt) * sample_slices(vol, shifted, SliceConfig(size=(24, 24)))
    inside = brute.abs() > 0
    np.testing.assert_allclose(got[inside].numpy(), brute[inside].numpy(), atol=2e-3)
    thin = sample_slices(vol, poses, SliceConfig(size=(24, 24)))
    assert got.std() < thin.std()  # thickness smooths


def test_brain_fraction(rng):
    mask = torch.zeros(20, 20, 20)
    mask[5:15, 5:15, 5:15] = 1.0
    img = Image(mask, torch.eye(4, dtype=torch.float64))
    centre = torch.tensor([[0.0, 0.0, 0.0, 9.5, 9.5, 9.5]], dtype=torch.float64)
    outside = torch.tensor([[0.0, 0.0, 0.0, 9.5, 9.5, 30.0]], dtype=torch.float64)
    frac = brain_fraction(img, torch.cat([centre, outside]), SliceConfig(size=(20, 20)))
    assert frac[0].item() == pytest.approx(0.25) and frac[1].item() == 0.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"size": (0, 4)}, "'size'"),
        ({"spacing_mm": 0.0}, "'spacing_mm'"),
        ({"thickness_mm": -1.0}, "'thickness_mm'"),
        ({"psf_samples": 4}, "'psf_samples'"),
        ({"mode": "bicubic"}, "'mode'"),
    ],
)
def test_config_validation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SliceConfig(**kwargs)


def test_bad_pose_shapes():
    vol = Image(torch.zeros(4, 4, 4), torch.eye(4, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"sample_slices\(\): 'poses' must have shape"):
        sample_slices(vol, torch.zeros(2, 5))


def test_bench_stacks_are_reproduced_at_their_true_poses(shared_data):
    """The bench simulator's slices equal our sampler's at the recorded poses (a frames check)."""
    case = shared_data / "bench" / "sb28-moderate"
    gt = load_nifti(case / "gt_volume.nii.gz")
    truth = json.loads((case / "truth_slices.json").read_text())
    for entry in truth["stacks"][:2]:
        stack = load_nifti(case / entry["file"])
        T = truth_poses(entry, "scanner")
        config = SliceConfig(
            size=stack.shape[:2], spacing_mm=float(stack.spacing[0]), thickness_mm=3.0
        )
        assert foreground_cc(sample_slices(gt, T, config), stack.data.permute(2, 0, 1)) > 0.99


def test_float16_volume_on_cpu(rng):
    vol = smooth_volume(rng)
    poses = random_poses(rng, 8)
    config = SliceConfig(size=(24, 24), thickness_mm=2.0)
    full = sample_slices(vol, poses, config)
    half = sample_slices(vol.to(dtype=torch.float16), poses, config)
    assert half.dtype == torch.float16
    scale = float(full.abs().max())
    torch.testing.assert_close(half.float(), full, atol=2e-2 * scale, rtol=0)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_cuda_matches_cpu(rng, dtype):
    vol = smooth_volume(rng)
    poses = random_poses(rng, 16)
    config = SliceConfig(size=(32, 32), thickness_mm=2.0)
    cpu = sample_slices(vol, poses, config)
    gpu = sample_slices(vol.to("cuda", dtype), poses.cuda(), config).float().cpu()
    torch.testing.assert_close(gpu, cpu, atol=5e-3 if dtype == torch.float16 else 1e-5, rtol=0)
