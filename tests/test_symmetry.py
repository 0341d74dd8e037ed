"""Mirror symmetry: twins of slice poses, the orbit losses, and measuring a volume's plane."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

from svr.geometry import se3_error, vector_to_se3
from svr.geometry.mirror import (
    SAGITTAL,
    ReflectionPlane,
    mirror_twin,
    mirror_twin_matrix,
    orbit_matrices,
    orbit_poses,
)
from svr.image import Image
from svr.losses import se3_geodesic_loss
from svr.losses.orbit import orbit_min_loss, symmetric_se3_geodesic_loss
from svr.metrics import nearest_orbit_member
from svr.models.network import loss_function
from svr.representation_registry import REPRESENTATIONS
from svr.sampling.mirror_planes import (
    mean_plane,
    measure_reflection_plane,
    resolve_symmetry,
    search_reflection_plane,
)
from svr.sampling.poses import pose_labels, random_slice_poses
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import canonicalize

F64 = torch.float64
S = np.diag([-1.0, 1.0, 1.0])  # the sagittal reflection of the canonical frame
D = np.diag([1.0, 1.0, -1.0])  # the slice-frame flip


def random_poses(n: int, seed: int, tz: float = 30.0) -> torch.Tensor:
    return random_slice_poses(n, torch.Generator().manual_seed(seed), 90.0, tz, "uniform")


def scipy_twin(pose: np.ndarray) -> np.ndarray:
    """Independent oracle: (S R D, S t) through scipy's Rotation."""
    R = Rotation.from_rotvec(pose[:3]).as_matrix()
    return np.concatenate([Rotation.from_matrix(S @ R @ D).as_rotvec(), S @ pose[3:]])


def scipy_se3_loss(pred: np.ndarray, target: np.ndarray, length_mm: float = 30.0) -> float:
    """theta^2 + |dt|^2 / L^2 (the default Z) through scipy."""
    rp, rt = Rotation.from_rotvec(pred[:3]), Rotation.from_rotvec(target[:3])
    angle = (rp.inv() * rt).magnitude()
    return float(angle**2 + np.sum((target[3:] - pred[3:]) ** 2) / length_mm**2)


# --- geometry -----------------------------------------------------------------------------------


def test_sagittal_twin_matches_scipy_oracle():
    poses = random_poses(200, 0)
    twins = mirror_twin(poses)
    for p, q in zip(poses.numpy(), twins.numpy(), strict=True):
        expected = scipy_twin(p)
        # compare as matrices (the rotation vector is ambiguous at pi)
        np.testing.assert_allclose(
            Rotation.from_rotvec(q[:3]).as_matrix(),
            Rotation.from_rotvec(expected[:3]).as_matrix(),
            atol=1e-9,
        )
        np.testing.assert_allclose(q[3:], expected[3:], atol=1e-9)


def test_twin_is_a_proper_involution_for_any_plane():
    plane = ReflectionPlane((0.9, 0.3, -0.2), 4.0)
    m = plane.matrix()
    assert float(torch.det(m[:3, :3])) == pytest.approx(-1.0)
    torch.testing.assert_close(m @ m, torch.eye(4, dtype=F64))
    n = torch.tensor(plane.normal, dtype=F64)
    on_plane = 4.0 * n + torch.linalg.cross(n, torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    torch.testing.assert_close(m[:3, :3] @ on_plane + m[:3, 3], on_plane)  # fixed points
    poses = random_poses(50, 1)
    twins = mirror_twin_matrix(vector_to_se3(poses), plane)
    torch.testing.assert_close(torch.det(twins[:, :3, :3]), torch.ones(50, dtype=F64))
    # M T D maps every in-plane point (u, v, 0) to the mirror image of where T maps it
    uv = torch.tensor([[7.0, -3.0, 0.0, 1.0]], dtype=F64).T
    torch.testing.assert_close(twins @ uv, m @ vector_to_se3(poses) @ uv)
    back = mirror_twin(mirror_twin(poses, plane), plane)
    torch.testing.assert_close(vector_to_se3(back), vector_to_se3(poses))
    assert orbit_matrices(twins, ()).shape == (1, 50, 4, 4)


def test_orbit_poses_order_and_planes():
    poses = random_poses(7, 2)
    orbit = orbit_poses(poses)
    assert orbit.shape == (2, 7, 6)
    torch.testing.assert_close(orbit[0], poses)
    torch.testing.assert_close(orbit[1], mirror_twin(poses))
    assert orbit_poses(poses, ()).shape == (1, 7, 6)
    with pytest.raises(ValueError, match="'planes' must hold ReflectionPlane"):
        orbit_poses(poses, ("sagittal",))


def test_reflection_plane_validation_and_json():
    p = ReflectionPlane((-2.0, 0.0, 0.0), 3.0)  # normalised, sign fixed: the same plane
    assert p.normal == (1.0, 0.0, 0.0) and p.offset_mm == -3.0
    assert ReflectionPlane.from_dict(p.to_dict()) == p
    assert p.angle_to_deg(SAGITTAL) == 0.0
    with pytest.raises(ValueError, match="'normal' must be non-zero"):
        ReflectionPlane((0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="'normal' must be a tuple of 3 finite numbers"):
        ReflectionPlane((1.0, math.nan, 0.0))
    with pytest.raises(ValueError, match="'offset_mm' must be a finite number"):
        ReflectionPlane((1.0, 0.0, 0.0), math.inf)
    with pytest.raises(ValueError, match="expected a dict with keys"):
        ReflectionPlane.from_dict({"normal": [1, 0, 0]})


def symmetric_volume(n: int = 48, spacing: float = 2.0, seed: int = 0) -> tuple[Image, Image]:
    """A smooth random brain, exactly symmetric about x = 0 of its world frame."""
    rng = np.random.default_rng(seed)
    grid = (np.indices((n, n, n)) - (n - 1) / 2) * spacing
    mask = (grid[0] / 35) ** 2 + (grid[1] / 40) ** 2 + (grid[2] / 30) ** 2 < 1
    texture = gaussian_filter(rng.normal(size=(n, n, n)), 2.0)
    texture = texture + texture[::-1]  # mirror along array axis 0 = world x
    data = mask * (1.0 + 3.0 * texture).clip(0)
    affine = torch.diag(torch.tensor([spacing, spacing, spacing, 1.0], dtype=F64))
    affine[:3, 3] = -(n - 1) / 2 * spacing
    return (
        Image(torch.from_numpy(data.copy()).float(), affine),
        Image(torch.from_numpy(mask.astype(np.float32)), affine.clone()),
    )


def test_twin_cuts_the_same_slice_from_a_mirror_symmetric_volume():
    volume, _ = symmetric_volume()
    poses = random_poses(40, 3, tz=20.0)
    config = SliceConfig(size=(40, 40), spacing_mm=2.0, thickness_mm=3.0)
    a = sample_slices(volume, poses.float(), config)
    b = sample_slices(volume, mirror_twin(poses).float(), config)
    assert float(a.abs().max()) > 1.0  # the slices hit the brain
    torch.testing.assert_close(a, b, atol=1e-4, rtol=0)
    # ... while the pose itself is far from its twin: a different slice of a lopsided volume
    lopsided = Image(volume.data * (1 + torch.linspace(0, 1, 48)[:, None, None]), volume.affine)
    c = sample_slices(lopsided, poses.float(), config)
    d = sample_slices(lopsided, mirror_twin(poses).float(), config)
    assert float((c - d).abs().amax()) > 0.1


# --- orbit losses -------------------------------------------------------------------------------


def test_symmetric_se3_loss_is_the_nearer_member_against_scipy():
    target = random_poses(100, 4)
    pred = random_poses(100, 5)
    loss = symmetric_se3_geodesic_loss(pred, target, reduction="none")
    for p, t, got in zip(pred.numpy(), target.numpy(), loss.numpy(), strict=True):
        expected = min(scipy_se3_loss(p, t), scipy_se3_loss(p, scipy_twin(t)))
        assert got == pytest.approx(expected, rel=1e-9, abs=1e-12)
    # no plane: the plain loss
    torch.testing.assert_close(
        symmetric_se3_geodesic_loss(pred, target, planes=(), reduction="none"),
        se3_geodesic_loss(pred, target, reduction="none"),
    )


def test_symmetric_se3_loss_is_invariant_to_twinning_the_target():
    target = random_poses(64, 6)
    pred = random_poses(64, 7)
    torch.testing.assert_close(
        symmetric_se3_geodesic_loss(pred, target, reduction="none"),
        symmetric_se3_geodesic_loss(pred, mirror_twin(target), reduction="none"),
    )
    # a prediction at the twin has zero loss
    assert float(symmetric_se3_geodesic_loss(mirror_twin(target), target).abs()) < 1e-10


def test_symmetric_se3_loss_gradcheck_away_from_the_switching_set():
    target = random_poses(6, 8)
    pred = target + 0.2 * torch.randn(6, 6, generator=torch.Generator().manual_seed(0), dtype=F64)
    pred[:3] = mirror_twin(target[:3]) + 0.2  # three near the twin, three near the target
    pred.requires_grad_(True)
    weights = torch.tensor([1.0, 2.0, 0.5, 0.01, 0.02, 0.005], dtype=F64)
    _, index = orbit_min_loss(
        functools.partial(se3_geodesic_loss, reduction="none"),
        pred.detach(),
        target,
        return_index=True,
    )
    assert index.tolist() == [1, 1, 1, 0, 0, 0]
    assert torch.autograd.gradcheck(
        lambda p: symmetric_se3_geodesic_loss(p, target, weights=weights, reduction="none"),
        (pred,),
    )


@pytest.mark.parametrize("angle", [0.0, math.pi - 1e-7, math.pi])
def test_symmetric_se3_loss_gradients_finite_at_0_and_pi(angle):
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
    target = torch.cat([angle * axis / axis.norm(), torch.tensor([1.0, 2.0, 3.0], dtype=F64)])
    for pred0 in (target.clone(), mirror_twin(target), torch.zeros(6, dtype=F64)):
        pred = pred0.clone().requires_grad_(True)
        loss = symmetric_se3_geodesic_loss(pred[None], target[None])
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(pred.grad).all()


def test_switching_set_takes_the_target_members_gradient():
    """Equidistant from T and twin(T): the subgradient is that of the target itself."""
    # T = (I, (10, 0, 0)); its sagittal twin is a half turn about y at (-10, 0, 0). The point
    # (0, 5, 0) is exactly as far from both translations: a loss on translations ties exactly.
    target = torch.tensor([[0.0, 0.0, 0.0, 10.0, 0.0, 0.0]], dtype=F64)
    twin = mirror_twin(target)

    def translation_loss(p: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return (p[..., 3:] - t[..., 3:]).square().sum(-1)

    pred = torch.tensor([[0.3, -0.2, 0.1, 0.0, 5.0, 0.0]], dtype=F64, requires_grad=True)
    loss, index = orbit_min_loss(translation_loss, pred, target, return_index=True)
    ties = [float(translation_loss(pred.detach(), t)) for t in (target, twin)]
    assert ties == [125.0, 125.0]
    assert int(index) == 0
    loss.backward()
    torch.testing.assert_close(pred.grad[0, 3:], torch.tensor([-20.0, 10.0, 0.0], dtype=F64))
    # The SE(3) loss at a quarter turn about y: the same angle and distance to both members (up to
    # rounding); the gradient is the target's, which differs from the twin's.
    pred = torch.tensor([[0.0, math.pi / 2, 0.0, 0.0, 5.0, 0.0]], dtype=F64)
    plain = [se3_geodesic_loss(pred, t, reduction="none") for t in (target, twin)]
    assert float(plain[0]) == pytest.approx(float(plain[1]), rel=1e-14)
    grads = []
    for member in (target, twin):
        q = pred.clone().requires_grad_(True)
        se3_geodesic_loss(q, member).backward()
        grads.append(q.grad)
    assert not torch.allclose(grads[0], grads[1])
    p = pred.clone().requires_grad_(True)
    symmetric_se3_geodesic_loss(p, target).backward()
    torch.testing.assert_close(p.grad, grads[0])


@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_orbit_losses_for_every_representation(representation):
    """min over the orbit of the plain loss, and blind to which member is the label."""
    poses = random_poses(32, 9)
    outputs = pose_labels(random_poses(32, 10), representation).float()
    labels = pose_labels(poses, representation).float()
    twin_labels = pose_labels(mirror_twin(poses), representation).float()
    symmetric = loss_function(representation, planes=(SAGITTAL,))
    plain = loss_function(representation)
    per = [
        torch.stack([plain(o[None], lab[None]) for o, lab in zip(outputs, ls, strict=True)])
        for ls in (labels, twin_labels)
    ]
    expected = torch.minimum(*per).mean()
    torch.testing.assert_close(symmetric(outputs, labels), expected, atol=2e-5, rtol=2e-5)
    torch.testing.assert_close(symmetric(outputs, twin_labels), expected, atol=2e-5, rtol=2e-5)
    # gradients flow to the outputs only, finite
    out = outputs.clone().requires_grad_(True)
    symmetric(out, labels).backward()
    assert torch.isfinite(out.grad).all() and float(out.grad.abs().sum()) > 0


def test_nearest_orbit_member_reports_the_member():
    target = random_poses(20, 11)
    pred = mirror_twin(target)
    pred[:10] = target[:10]
    member, index = nearest_orbit_member(pred, target)
    torch.testing.assert_close(vector_to_se3(member), vector_to_se3(pred))
    assert index.tolist() == [0] * 10 + [1] * 10
    # by rotation alone, and with no plane (the target itself)
    _, index = nearest_orbit_member(
        pred, target, distance=lambda a, b: se3_error(a, b)[..., :3].norm(dim=-1)
    )
    assert index.tolist() == [0] * 10 + [1] * 10
    member, index = nearest_orbit_member(pred, target, planes=())
    torch.testing.assert_close(member, target)
    assert not bool(index.any())


# --- measuring a volume's plane -----------------------------------------------------------------


def test_measure_reflection_plane_finds_a_shifted_and_tilted_plane():
    volume, mask = symmetric_volume(seed=1)
    canonical = canonicalize(volume, mask)
    fit = measure_reflection_plane(canonical)
    assert fit.correlation > 0.999 and fit.plane.angle_to_deg(SAGITTAL) < 0.5
    assert abs(fit.plane.offset_mm) < 0.5
    # Move the canonical frame: x -> R x + (3, 0, 0) with R 4 degrees about z. The mirror plane
    # is then the image of x = 0: normal R e_x, offset 3 * (R e_x)_x.
    rot = torch.eye(4, dtype=F64)
    rot[:3, :3] = torch.from_numpy(Rotation.from_euler("z", 4, degrees=True).as_matrix())
    rot[:3, 3] = torch.tensor([3.0, 0.0, 0.0], dtype=F64)
    moved = canonicalize(
        Image(volume.data, rot @ volume.affine), Image(mask.data, rot @ mask.affine)
    )
    moved.image.affine[:3, 3] += moved.centre_mm  # keep the frame as moved, not re-centred
    fit = measure_reflection_plane(moved)
    normal = rot[:3, 0].numpy()
    truth = ReflectionPlane(tuple(normal), 3.0 * float(normal[0]))
    assert fit.plane.angle_to_deg(truth) < 0.5
    assert fit.plane.offset_mm == pytest.approx(truth.offset_mm, abs=0.4)
    assert fit.correlation > 0.99 > fit.sagittal_correlation


def test_search_reflection_plane_finds_the_plane_in_any_orientation():
    # The brain turned 70 deg about z and 30 deg about y: its mirror plane is far beyond the
    # local search from x = 0, and the search over every orientation finds it (normal R e_x).
    volume, mask = symmetric_volume(seed=4)
    rot = torch.eye(4, dtype=F64)
    rot[:3, :3] = torch.from_numpy(Rotation.from_euler("zy", [70, 30], degrees=True).as_matrix())
    moved = canonicalize(
        Image(volume.data, rot @ volume.affine), Image(mask.data, rot @ mask.affine)
    )
    truth = ReflectionPlane(tuple(rot[:3, 0].numpy()), 0.0)
    fit = search_reflection_plane(moved)
    assert fit.plane.angle_to_deg(truth) < 1.0
    assert fit.correlation > 0.99 > 0.9 > fit.sagittal_correlation
    # A volume of unmirrored texture has no clear plane anywhere.
    rng = np.random.default_rng(5)
    lopsided = gaussian_filter(rng.normal(size=volume.data.shape), 2.0) * mask.data.numpy()
    noise = canonicalize(
        Image(torch.from_numpy(lopsided).float().clamp(min=0), volume.affine), mask
    )
    assert search_reflection_plane(noise).correlation < 0.4
    with pytest.raises(ValueError, match="'refine'"):
        search_reflection_plane(moved, normals=3, refine=4)


def test_resolve_symmetry_modes():
    volume, mask = symmetric_volume(seed=2)
    canonical = canonicalize(volume, mask)
    assert resolve_symmetry("none", [canonical])[0] == ()
    assert resolve_symmetry("sagittal", [canonical])[0] == (SAGITTAL,)
    planes, report = resolve_symmetry("auto", [canonical], ["phantom"])
    assert len(planes) == 1 and planes[0].angle_to_deg(SAGITTAL) < 0.5
    assert report["volumes"]["phantom"]["correlation"] > 0.99
    lopsided = canonicalize(
        Image(volume.data * (1 + 2 * torch.linspace(0, 1, 48)[:, None, None]), volume.affine),
        mask,
    )
    planes, report = resolve_symmetry("auto", [canonical, lopsided])
    assert planes == () and report["planes"] == []
    with pytest.raises(ValueError, match="'mode' must be one of"):
        resolve_symmetry("mirror", [canonical])
    with pytest.raises(ValueError, match="must pair up"):
        resolve_symmetry("auto", [canonical], ["a", "b"])
    assert mean_plane([SAGITTAL, SAGITTAL]) == SAGITTAL
