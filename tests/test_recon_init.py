"""Learned pose initialisation: robust pose averaging and the CNN slice-pose bookkeeping."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from recon_settings import recon_config
from synthetic import ellipsoid_brain

import svr.reconstruction.initialisation.slice_model as cnn_init
from svr.geometry import (
    quat_to_matrix,
    se3_compose,
    se3_inverse,
    so3_exp,
    so3_log,
    vector_to_se3,
)
from svr.geometry.averaging import robust_mean_pose
from svr.geometry.mirror import SAGITTAL, mirror_twin_matrix
from svr.image import Image, stack_slice_poses
from svr.models.backbones import BackboneConfig
from svr.models.network import ModelConfig, build_model
from svr.models.predict import PlanePredictions
from svr.reconstruction.initialisation.slice_model import (
    consensus_start,
    learned_consensus,
    slice_predictions,
)
from svr.reconstruction.registration import stack_registration
from svr.reconstruction.slices import SliceSet, Stack, array_poses, extract_slices, plane_poses
from svr.sampling.slicer import SliceConfig, sample_slices

F64 = torch.float64
SPACING = 2.0  # in-plane mm of the synthetic stacks
TINY = ModelConfig(backbone=BackboneConfig(width=8, depth=2), input_size=(32, 32), spacing_mm=2.0)
# scanner <- canonical: where the canonical brain sits in the scanner.
G = torch.eye(4, dtype=F64)
G[:3, :3] = so3_exp(torch.tensor([0.5, -0.3, 1.1], dtype=F64))
G[:3, 3] = torch.tensor([10.0, -25.0, 40.0], dtype=F64)


def random_rotations(n: int, generator: torch.Generator) -> torch.Tensor:
    """(n, 3, 3) uniformly random rotations."""
    return quat_to_matrix(torch.randn(n, 4, generator=generator, dtype=F64))


def rigid(rotations: torch.Tensor, translations: torch.Tensor) -> torch.Tensor:
    """(n, 4, 4) transforms from (n, 3, 3) rotations and (n, 3) translations."""
    out = torch.eye(4, dtype=F64).repeat(len(rotations), 1, 1)
    out[:, :3, :3], out[:, :3, 3] = rotations, translations
    return out


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angles (degrees) between the rotations of (..., 4, 4) or (..., 3, 3) transforms."""
    return torch.rad2deg(so3_log(a[..., :3, :3].transpose(-1, -2) @ b[..., :3, :3]).norm(dim=-1))


def noisy_with_outliers(
    generator: torch.Generator, clustered: bool, n_in: int = 70, n_out: int = 30
) -> tuple[torch.Tensor, torch.Tensor]:
    """Inliers near a true pose (0.5 deg, 0.5 mm noise) and gross outliers; returns (T, truth).

    Outliers are random rotations: uniform, or scattered (15 deg) about one wrong orientation
    120 deg away (a consistent mislabelling), with translations 40 mm away.
    """
    truth = rigid(random_rotations(1, generator), 20 * torch.randn(1, 3, generator=generator))[0]
    noise = math.radians(0.5) * torch.randn(n_in, 3, generator=generator, dtype=F64)
    inliers = rigid(
        truth[:3, :3] @ so3_exp(noise),
        truth[:3, 3] + 0.5 * torch.randn(n_in, 3, generator=generator, dtype=F64),
    )
    if clustered:
        axis = torch.nn.functional.normalize(torch.randn(3, generator=generator, dtype=F64), dim=0)
        scatter = math.radians(15) * torch.randn(n_out, 3, generator=generator, dtype=F64)
        wrong = truth[:3, :3] @ so3_exp(math.radians(120) * axis) @ so3_exp(scatter)
    else:
        wrong = random_rotations(n_out, generator)
    shifts = 40.0 + 10 * torch.randn(n_out, 3, generator=generator, dtype=F64)
    return torch.cat([inliers, rigid(wrong, truth[:3, 3] + shifts)]), truth


def chordal_mean_rotation(rotations: torch.Tensor) -> torch.Tensor:
    """The plain (non-robust) chordal mean of (M, 3, 3) rotations, by SVD (test reference)."""
    u, _, vh = torch.linalg.svd(rotations.sum(dim=0))
    return u @ torch.diag(torch.tensor([1.0, 1.0, float(torch.det(u @ vh))], dtype=F64)) @ vh


# --- robust_mean_pose ---------------------------------------------------------------------------


def test_robust_mean_of_identical_transforms_is_exact():
    g = torch.Generator().manual_seed(1)
    T = rigid(random_rotations(1, g), torch.tensor([[3.0, -7.0, 120.0]], dtype=F64))
    mean = robust_mean_pose(T.expand(9, 4, 4))
    assert mean.dtype == F64 and mean.shape == (4, 4)
    torch.testing.assert_close(mean, T[0], atol=1e-12, rtol=0)
    torch.testing.assert_close(robust_mean_pose(T), T[0], atol=1e-12, rtol=0)  # M = 1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_robust_mean_resists_30_percent_clustered_outliers(seed):
    T, truth = noisy_with_outliers(torch.Generator().manual_seed(seed), clustered=True)
    assert float(angle_deg(chordal_mean_rotation(T[:, :3, :3]), truth)) > 10.0  # plain mean fails
    mean = robust_mean_pose(T)
    assert float(angle_deg(mean, truth)) < 1.5
    assert float((mean[:3, 3] - truth[:3, 3]).norm()) < 1.0


@pytest.mark.parametrize("seed", [0, 1])
def test_robust_mean_resists_30_percent_uniform_outliers(seed):
    T, truth = noisy_with_outliers(torch.Generator().manual_seed(seed), clustered=False)
    mean = robust_mean_pose(T)
    assert float(angle_deg(mean, truth)) < 0.5
    assert float(angle_deg(mean, truth)) < float(
        angle_deg(chordal_mean_rotation(T[:, :3, :3]), truth)
    )
    assert float((mean[:3, 3] - truth[:3, 3]).norm()) < 1.0


def test_robust_mean_is_left_equivariant():
    T, _ = noisy_with_outliers(torch.Generator().manual_seed(5), clustered=True)
    moved = se3_compose(G, T)
    torch.testing.assert_close(
        robust_mean_pose(moved), se3_compose(G, robust_mean_pose(T)), atol=1e-9, rtol=0
    )


def test_robust_mean_weights():
    T, truth = noisy_with_outliers(torch.Generator().manual_seed(6), clustered=True, n_out=90)
    weights = torch.cat([torch.ones(70, dtype=F64), torch.zeros(90, dtype=F64)])
    torch.testing.assert_close(robust_mean_pose(T, weights), robust_mean_pose(T[:70]))
    # Outliers are the majority; doubling the inliers' weight wins it back.
    assert float(angle_deg(robust_mean_pose(T), truth)) > 10.0
    assert float(angle_deg(robust_mean_pose(T, 1.0 + weights), truth)) < 1.5


def test_robust_mean_argument_errors():
    T = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    with pytest.raises(TypeError, match="'transforms'"):
        robust_mean_pose(torch.eye(4, dtype=torch.int64)[None])
    with pytest.raises(ValueError, match=r"'transforms' must have shape \(\.\.\., M, 4, 4\)"):
        robust_mean_pose(T[:, :3])
    with pytest.raises(ValueError, match="'transforms' must have shape"):
        robust_mean_pose(T[:0])
    with pytest.raises(ValueError, match="'transforms' holds non-finite"):
        robust_mean_pose(torch.full_like(T, math.nan))
    with pytest.raises(ValueError, match=r"'weights' must have shape \(3,\)"):
        robust_mean_pose(T, torch.ones(2))
    for bad in (torch.tensor([1.0, -1.0, 1.0]), torch.zeros(3)):
        with pytest.raises(ValueError, match="'weights' must be finite, non-negative"):
            robust_mean_pose(T, bad)
    with pytest.raises(ValueError, match="'max_iterations'"):
        robust_mean_pose(T, max_iterations=0)
    with pytest.raises(ValueError, match="'tolerance'"):
        robust_mean_pose(T, tolerance=0.0)


# --- slice_predictions ----------------------------------------------------------------------------


def oblique_stack(
    volume: Image,
    mask: Image,
    name: str,
    rotvec: tuple[float, float, float],
    size: tuple[int, int],
    planes: int,
    thickness: float,
    first_k: int,
    motion: torch.Tensor | None = None,
) -> tuple[Stack, torch.Tensor]:
    """A stack cut from a canonical volume as the scanner would see it through ``G``.

    The stack's affine is oblique in the scanner frame; its k-plane ``k`` has scanner pose
    ``S_k`` (built here from the affine, not by the library) and canonical pose ``G^-1 o S_k``
    (``G^-1 o S_k o M_k`` with a (K, 4, 4) ``motion``), where the (thin) slice is sampled. The
    stack stands for planes ``first_k ...`` of its file.

    Returns:
        The stack and the (K, 4, 4) true canonical poses of its k-planes (origin at the plane
        centre).
    """
    i_n, j_n = size
    R = so3_exp(torch.tensor(rotvec, dtype=F64))
    affine = torch.eye(4, dtype=F64)
    affine[:3, :3] = R * torch.tensor([SPACING, SPACING, thickness], dtype=F64)
    centre = torch.tensor([(i_n - 1) / 2, (j_n - 1) / 2, (planes - 1) / 2], dtype=F64)
    affine[:3, 3] = G[:3, 3] + torch.tensor([3.0, -2.0, 1.5], dtype=F64) - affine[:3, :3] @ centre
    k = torch.arange(planes, dtype=F64)
    plane_centres = torch.stack(
        [torch.full_like(k, (i_n - 1) / 2), torch.full_like(k, (j_n - 1) / 2), k], 1
    )
    scanner = rigid(R.expand(planes, 3, 3), plane_centres @ affine[:3, :3].T + affine[:3, 3])
    canonical = se3_compose(se3_inverse(G), scanner)
    if motion is not None:
        canonical = se3_compose(canonical, motion)
    config = SliceConfig(size=size, spacing_mm=SPACING)
    inside = sample_slices(mask, canonical, replace(config, mode="nearest")).permute(1, 2, 0) > 0.5
    data = sample_slices(volume, canonical, config).permute(1, 2, 0) * inside
    stack = Stack(
        name=name,
        image=Image(data.contiguous(), affine),
        mask=Image(inside.contiguous(), affine.clone()),
        thickness_mm=thickness,
        k_indices=torch.arange(first_k, first_k + planes),
        full_shape=size,
    )
    return stack, canonical


def make_scene(
    motion_deg: float = 0.0, motion_mm: float = 0.0
) -> tuple[Image, list[Stack], dict[str, torch.Tensor], SliceSet]:
    """A textured ellipsoid brain in canonical space, three oblique stacks of different sizes.

    Each slice moved by its own random rotation of ``motion_deg`` and shift of ``motion_mm``.
    """
    n, sp = 40, 2.5
    volume, mask = ellipsoid_brain(
        n, sp, (30.0, 24.0, 20.0), seed=3, origin_mm=(-(n - 1) / 2 * sp,) * 3
    )
    specs = [
        ("axial.nii.gz", (0.2, -0.1, 0.3), (40, 36), 14, 4.0, 0),
        ("coronal.nii.gz", (1.4, 0.2, -0.2), (33, 38), 12, 4.5, 3),
        ("sagittal.nii.gz", (0.3, 1.5, 0.4), (36, 31), 13, 4.0, 1),
    ]
    generator = torch.Generator().manual_seed(5)
    stacks, truth = [], {}
    for name, rotvec, size, planes, thickness, first_k in specs:
        axes = torch.nn.functional.normalize(torch.randn(planes, 3, generator=generator), dim=1)
        shifts = torch.nn.functional.normalize(torch.randn(planes, 3, generator=generator), dim=1)
        motion = rigid(so3_exp(math.radians(motion_deg) * axes.to(F64)), motion_mm * shifts.to(F64))
        stack, canonical = oblique_stack(
            volume, mask, name, rotvec, size, planes, thickness, first_k, motion
        )
        stacks.append(stack)
        truth[name] = canonical
    return volume, stacks, truth, extract_slices(stacks)


@pytest.fixture(scope="module")
def scene() -> tuple[Image, list[Stack], dict[str, torch.Tensor], SliceSet]:
    """Three oblique stacks of a motionless brain."""
    return make_scene()


@pytest.fixture(scope="module")
def moving_scene() -> tuple[Image, list[Stack], dict[str, torch.Tensor], SliceSet]:
    """The same stacks with every slice moved by 8 degrees and 3 mm (random directions)."""
    return make_scene(motion_deg=8.0, motion_mm=3.0)


def oracle(truth: dict[str, torch.Tensor], corrupt: float = 0.0, drop_last: bool = False):
    """A stand-in for :func:`svr.models.predict.predict_plane_poses` that knows the true poses.

    It keeps its contract: the cropped stack's k-planes with a nonempty mask, their scanner poses
    and canonical poses about the plane centre. A fraction ``corrupt`` of the rows get random
    poses instead.
    """
    generator = torch.Generator().manual_seed(11)

    def predict(model, stack, mask=None, batch_size=64, name="stack") -> PlanePredictions:
        kept = torch.nonzero(mask.data.flatten(0, 1).any(dim=0)).flatten()
        if drop_last:
            kept = kept[:-1]
        poses = truth[name][kept].clone()
        bad = torch.randperm(len(kept), generator=generator)[: round(corrupt * len(kept))]
        poses[bad] = rigid(
            random_rotations(len(bad), generator),
            40 * torch.randn(len(bad), 3, generator=generator, dtype=F64),
        )
        return PlanePredictions(kept, stack_slice_poses(stack)[kept], poses)

    return predict


def test_oracle_predictions_give_the_true_transform_and_poses(scene, monkeypatch):
    volume, stacks, truth, slices = scene
    monkeypatch.setattr(cnn_init, "predict_plane_poses", oracle(truth))
    init = slice_predictions(build_model(TINY).eval(), stacks, slices)
    n = len(slices)
    assert init.predicted_poses.shape == init.consensus_poses.shape == (n, 4, 4)
    assert init.stack_transforms.shape == (3, 4, 4) and init.global_transform.shape == (4, 4)
    assert init.rotation_deviation_deg.shape == init.translation_deviation_mm.shape == (n,)
    to_canonical = se3_inverse(G)
    for transform in (*init.stack_transforms, init.global_transform):
        torch.testing.assert_close(transform, to_canonical, atol=1e-9, rtol=0)
    expected = se3_compose(to_canonical, slices.scanner_poses)
    torch.testing.assert_close(init.predicted_poses, expected, atol=1e-9, rtol=0)
    torch.testing.assert_close(init.consensus_poses, expected, atol=1e-9, rtol=0)
    assert float(init.rotation_deviation_deg.max()) < 1e-6
    assert float(init.translation_deviation_mm.max()) < 1e-6
    # The k mapping: each slice's k-plane pose is the truth of the file's plane k.
    for sid, stack in enumerate(stacks):
        rows = slices.stack_slices(sid)
        cropped_k = slices.slice_indices[rows] - stack.k_indices[0]
        torch.testing.assert_close(
            plane_poses(slices, init.predicted_poses)[rows],
            truth[stack.name][cropped_k],
            atol=1e-9,
            rtol=0,
        )
    # The origin: the padded slices are the volume sampled at the predicted canonical poses.
    config = SliceConfig(size=slices.size, spacing_mm=SPACING)
    resliced = sample_slices(volume, init.predicted_poses, config)
    torch.testing.assert_close(
        resliced[slices.masks], slices.images[slices.masks], atol=1e-4, rtol=0
    )


def test_consensus_survives_25_percent_random_predictions(scene, monkeypatch):
    _, stacks, truth, slices = scene
    monkeypatch.setattr(cnn_init, "predict_plane_poses", oracle(truth, corrupt=0.25))
    init = slice_predictions(build_model(TINY).eval(), stacks, slices)
    expected = se3_compose(se3_inverse(G), slices.scanner_poses)
    wrong = (init.predicted_poses - expected).abs().amax(dim=(1, 2)) > 1e-6
    assert 0.2 < float(wrong.double().mean()) < 0.3
    assert float(angle_deg(init.predicted_poses[wrong], expected[wrong]).median()) > 30.0
    assert float(angle_deg(init.consensus_poses, expected).max()) < 1.0
    assert float((init.consensus_poses - expected)[:, :3, 3].norm(dim=-1).max()) < 1.0
    assert float(angle_deg(init.global_transform, se3_inverse(G))) < 1.0
    # The outliers are the slices that deviate from their consensus.
    deviates = (init.rotation_deviation_deg > 1.0) | (init.translation_deviation_mm > 1.0)
    assert torch.equal(deviates, wrong)


def test_cnn_slice_poses_errors(scene, monkeypatch):
    _, stacks, truth, slices = scene
    model = build_model(TINY).eval()
    with pytest.raises(ValueError, match="'stacks' must be the stacks of 'slices', in order"):
        slice_predictions(model, stacks[::-1], slices)
    with pytest.raises(ValueError, match="'batch_size' must be an int >= 1"):
        slice_predictions(model, stacks, slices, batch_size=0)
    moved = stacks[1].image.affine.clone()
    moved[:3, 3] += 2.0 * moved[:3, 2] / moved[:3, 2].norm()  # 2 mm along the normal
    shifted = [stacks[0], replace(stacks[1], image=Image(stacks[1].image.data, moved)), stacks[2]]
    monkeypatch.setattr(cnn_init, "predict_plane_poses", oracle(truth))
    with pytest.raises(ValueError, match=r"'coronal\.nii\.gz': slices of 'slices' do not lie"):
        slice_predictions(model, shifted, slices)
    monkeypatch.setattr(cnn_init, "predict_plane_poses", oracle(truth, drop_last=True))
    with pytest.raises(
        ValueError, match=r"'axial\.nii\.gz': no prediction for the slices k = \[\d+\]"
    ):
        slice_predictions(model, stacks, slices)


def test_cnn_slice_poses_end_to_end_with_a_tiny_network(scene):
    _, stacks, _, slices = scene
    model = build_model(TINY)
    with torch.no_grad():
        for p in model.head.parameters():
            p.normal_(0.0, 0.1)  # input-dependent predictions
    init = slice_predictions(model.eval(), stacks, slices.subset(slices.stack_ids != 1), 16)
    n = int((slices.stack_ids != 1).sum())
    assert init.predicted_poses.shape == init.consensus_poses.shape == (n, 4, 4)
    for field in (init.predicted_poses, init.consensus_poses, init.global_transform):
        assert field.dtype == F64 and bool(field.isfinite().all())
        R = field[..., :3, :3]
        torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3, dtype=F64).expand_as(R))
    assert bool(init.stack_transforms[1].isnan().all())  # no slice of stack 1 left
    kept = slices.subset(slices.stack_ids != 1)
    torch.testing.assert_close(
        init.consensus_poses,
        se3_compose(init.stack_transforms[kept.stack_ids], kept.scanner_poses),
    )
    assert bool(init.rotation_deviation_deg.isfinite().all())
    assert float(init.rotation_deviation_deg.max()) > 0.0  # an untrained net is not rigid


# --- learned_consensus, refined poses and the learned initialisation ----------------------------


def true_array_poses(slices: SliceSet, truth: dict[str, torch.Tensor], stacks) -> torch.Tensor:
    """(N, 4, 4) true canonical poses of the slice set's padded arrays."""
    planes = torch.stack(
        [
            truth[slices.stack_names[int(sid)]][int(k) - int(stacks[int(sid)].k_indices[0])]
            for sid, k in zip(slices.stack_ids, slices.slice_indices, strict=True)
        ]
    )
    return array_poses(slices, planes)


def test_learned_consensus_of_true_poses_gives_the_scanner_to_canonical_transform(scene):
    _, stacks, truth, slices = scene
    exact = true_array_poses(slices, truth, stacks)
    init = learned_consensus(slices, exact.float())  # any float dtype; computed in float64
    to_canonical = se3_inverse(G)  # built by the test, independent of the library
    for transform in (*init.stack_transforms, init.global_transform):
        torch.testing.assert_close(transform, to_canonical, atol=1e-5, rtol=0)
    torch.testing.assert_close(init.predicted_poses, exact, atol=1e-5, rtol=0)
    torch.testing.assert_close(init.consensus_poses, exact, atol=1e-4, rtol=0)
    assert init.predicted_poses.dtype == F64
    assert float(init.rotation_deviation_deg.max()) < 1e-3


def test_refined_poses_keep_agreeing_predictions_and_replace_outliers(moving_scene):
    _, stacks, truth, slices = moving_scene
    predicted = true_array_poses(slices, truth, stacks)
    generator = torch.Generator().manual_seed(2)
    bad = torch.rand(len(slices), generator=generator) < 0.2
    predicted[bad] = rigid(
        random_rotations(int(bad.sum()), generator),
        60 * torch.randn(int(bad.sum()), 3, generator=generator, dtype=F64),
    )
    init = learned_consensus(slices, predicted)
    outlier = init.outliers(30.0, 20.0)
    # 8 degrees of motion against 30: only the random predictions are outliers (here all of
    # them land farther than 30 degrees or 20 mm from the consensus).
    assert torch.equal(outlier, bad)
    refined = init.refined_poses(30.0, 20.0)
    torch.testing.assert_close(refined[~bad], predicted[~bad])
    torch.testing.assert_close(refined[bad], init.consensus_poses[bad])
    # The consensus is rigid per stack: it cannot follow the motion the predictions show.
    exact = true_array_poses(slices, truth, stacks)
    assert float(angle_deg(init.consensus_poses[~bad], exact[~bad]).median()) > 4.0
    assert float(angle_deg(refined[~bad], exact[~bad]).max()) < 1e-6
    # Bounds of 0 keep no prediction that deviates at all.
    torch.testing.assert_close(init.refined_poses(0.0, 0.0), init.consensus_poses)


def test_learned_consensus_and_refined_poses_errors(scene):
    _, _, _, slices = scene
    good = slices.scanner_poses.clone()
    with pytest.raises(ValueError, match=r"'predicted' must be a \(\d+, 4, 4\) tensor"):
        learned_consensus(slices, good[:-1])
    with pytest.raises(ValueError, match=r"'predicted' must be a \(\d+, 4, 4\) tensor"):
        learned_consensus(slices, good.numpy())
    nan = good.clone()
    nan[0, 0, 3] = math.nan
    with pytest.raises(ValueError, match="'predicted' holds non-finite values"):
        learned_consensus(slices, nan)
    with pytest.raises(ValueError, match="'slices' is empty"):
        learned_consensus(slices.subset(slices.stack_ids < 0), good[:0])
    init = learned_consensus(slices, good)
    with pytest.raises(ValueError, match="'max_rotation_deg' must be finite and >= 0"):
        init.refined_poses(-1.0, 20.0)
    with pytest.raises(ValueError, match="'max_translation_mm' must be finite and >= 0"):
        init.refined_poses(30.0, math.inf)


def test_learned_initialisation_keeps_good_predictions_per_slice(moving_scene):
    _, stacks, truth, slices = moving_scene
    # Each stack is scored against the other two (11-13 slices each) on a grid of twice this
    # spacing; at 2.5 mm (a 5 mm grid) one stack's exact poses and its registered ones scored
    # within 0.04 of each other either way round, at 2 mm exact poses win by 0.14-0.19.
    config = recon_config(resolution_mm=2.0, template=0)
    exact = true_array_poses(slices, truth, stacks)
    start, kept, _, *_ = consensus_start(slices, learned_consensus(slices, exact), config)
    assert kept == ("cnn", "cnn", "cnn") and start.frame == "canonical"
    torch.testing.assert_close(start.poses, exact)


def test_learned_initialisation_falls_back_to_stack_registration(moving_scene):
    _, stacks, truth, slices = moving_scene
    config = recon_config(resolution_mm=2.5, template=0)
    exact = true_array_poses(slices, truth, stacks)
    generator = torch.Generator().manual_seed(4)
    # A model that knows the brain's orientation but not the slices: 40 degrees of noise each.
    axes = torch.nn.functional.normalize(torch.randn(len(slices), 3, generator=generator), dim=1)
    noisy = exact.clone()
    noisy[:, :3, :3] = exact[:, :3, :3] @ so3_exp(math.radians(40) * axes.to(F64))
    learned = learned_consensus(slices, noisy)
    start, kept, notes, *_ = consensus_start(slices, learned, config)
    assert kept == ("stack", "stack", "stack")
    registered, _ = stack_registration(
        slices, config.initialisation_grid_mm, config.initialisation.template
    )
    # Registration alone, rigidly moved into canonical space by one transform.
    moved = start.poses @ torch.linalg.inv(registered)
    torch.testing.assert_close(moved, moved[:1].expand_as(moved), atol=1e-6, rtol=0)
    assert all(("cnn unsure" in n) or ("NCC" in n) for n in notes)


# --- mirror twins: stack-level disambiguation and the safe choice -------------------------------


def half_twinned(scene) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact predictions with a random half replaced by their mirror twins: (exact, twin, pred)."""
    _, stacks, truth, slices = scene
    exact = true_array_poses(slices, truth, stacks)
    generator = torch.Generator().manual_seed(21)
    twin = torch.rand(len(slices), generator=generator) < 0.5
    return exact, twin, torch.where(twin[:, None, None], mirror_twin_matrix(exact), exact)


def test_stack_order_undoes_random_twins(scene):
    """Half the exact predictions replaced by their mirror twins: the stacks flip them back."""
    slices = scene[3]
    exact, twin, predicted = half_twinned(scene)
    init = learned_consensus(slices, predicted, planes=(SAGITTAL,))
    to_canonical = se3_inverse(G)
    for transform in (*init.stack_transforms, init.global_transform):
        torch.testing.assert_close(transform, to_canonical, atol=1e-5, rtol=0)
    torch.testing.assert_close(init.predicted_poses, exact, atol=1e-5, rtol=0)
    torch.testing.assert_close(init.raw_predicted_poses, predicted)
    assert torch.equal(init.orbit_member.bool(), twin)
    per_stack = torch.zeros(3, dtype=torch.long).index_add(0, slices.stack_ids, twin.long())
    assert torch.equal(init.flipped(slices.stack_ids), per_stack)
    assert torch.equal(init.stack_support, torch.ones(3, dtype=F64))
    # Every prediction a twin: the stack takes every twin back.
    init = learned_consensus(slices, mirror_twin_matrix(exact), planes=(SAGITTAL,))
    torch.testing.assert_close(init.global_transform, to_canonical, atol=1e-5, rtol=0)
    assert bool(init.orbit_member.bool().all())


def test_without_the_flip_the_twins_break_the_consensus(scene):
    """The same predictions with the twin logic removed (no planes): no stack is right."""
    slices = scene[3]
    _, _, predicted = half_twinned(scene)
    init = learned_consensus(slices, predicted)
    error = angle_deg(init.stack_transforms, se3_inverse(G).expand(3, 4, 4))
    centre = (init.stack_transforms[:, :3, 3] - se3_inverse(G)[:3, 3]).norm(dim=-1)
    assert bool(((error > 1.0) | (centre > 1.0) | (init.stack_support < 0.9)).all())


def test_disambiguation_with_noisy_predictions_and_motion(moving_scene):
    """8 deg / 3 mm motion, 5 deg / 2 mm prediction noise, 40 % twins: the stacks are right."""
    _, stacks, truth, slices = moving_scene
    exact = true_array_poses(slices, truth, stacks)
    generator = torch.Generator().manual_seed(22)
    axes = torch.nn.functional.normalize(torch.randn(len(slices), 3, generator=generator), dim=1)
    noisy = exact.clone()
    noisy[:, :3, :3] = exact[:, :3, :3] @ so3_exp(math.radians(5) * axes.to(F64))
    noisy[:, :3, 3] += 2.0 * torch.randn(len(slices), 3, generator=generator, dtype=F64)
    twin = torch.rand(len(slices), generator=generator) < 0.4
    predicted = torch.where(twin[:, None, None], mirror_twin_matrix(noisy), noisy)
    init = learned_consensus(slices, predicted, planes=(SAGITTAL,))
    assert float(angle_deg(init.stack_transforms, se3_inverse(G).expand(3, 4, 4)).max()) < 5.0
    assert float((init.orbit_member.bool() == twin).double().mean()) > 0.95


def test_learned_initialisation_falls_back_on_a_wrong_model(moving_scene):
    """Random predictions: the model is unsure of every stack, which starts from registration."""
    _, _stacks, _truth, slices = moving_scene
    config = recon_config(resolution_mm=2.5, template=0)
    generator = torch.Generator().manual_seed(23)
    wrong = rigid(
        random_rotations(len(slices), generator),
        40 * torch.randn(len(slices), 3, generator=generator, dtype=F64),
    )
    learned = learned_consensus(slices, wrong, planes=(SAGITTAL,))
    assert float(learned.stack_support.max()) < config.initialisation.slice_min_support
    _start, kept, notes, *_ = consensus_start(slices, learned, config)
    assert kept == ("stack",) * 3
    assert all(n.startswith("cnn unsure") for n in notes)


def test_learned_initialisation_rejects_confident_but_inconsistent_stacks(moving_scene):
    """Each stack rigidly wrong by its own 25 deg: full support, but the stacks disagree."""
    _, stacks, truth, slices = moving_scene
    config = recon_config(resolution_mm=2.5, template=0)
    exact = true_array_poses(slices, truth, stacks)
    errors = so3_exp(
        torch.tensor([[0.44, 0.0, 0.0], [0.0, -0.44, 0.0], [0.0, 0.0, 0.44]], dtype=F64)
    )
    wrong = exact.clone()
    wrong[:, :3, :3] = errors[slices.stack_ids] @ exact[:, :3, :3]
    learned = learned_consensus(slices, wrong, planes=(SAGITTAL,))
    assert bool((learned.stack_support == 1).all())
    start, kept, _notes, *_ = consensus_start(slices, learned, config)
    # At most one stack keeps its own frame: the others would tear the brain apart.
    assert kept.count("cnn") <= 1
    registered, _ = stack_registration(
        slices, config.initialisation_grid_mm, config.initialisation.template
    )
    stack_rows = torch.tensor([k == "stack" for k in kept])[slices.stack_ids]
    moved = start.poses[stack_rows] @ torch.linalg.inv(registered[stack_rows])
    torch.testing.assert_close(moved, moved[:1].expand_as(moved), atol=1e-6, rtol=0)


def test_robust_mean_pose_is_batched():
    gen = torch.Generator().manual_seed(11)
    T = vector_to_se3(
        torch.randn(2, 3, 7, 6, generator=gen, dtype=F64)
        * torch.tensor([0.4] * 3 + [5.0] * 3, dtype=F64)
    )
    weights = torch.rand(2, 3, 7, generator=gen, dtype=F64) + 0.1
    batched = robust_mean_pose(T, weights)
    assert batched.shape == (2, 3, 4, 4)
    for a in range(2):
        for b in range(3):
            torch.testing.assert_close(
                batched[a, b], robust_mean_pose(T[a, b], weights[a, b]), atol=1e-10, rtol=0
            )
    with pytest.raises(ValueError, match=r"'weights' must have shape \(2, 3, 7\)"):
        robust_mean_pose(T, weights[0])
    zero = weights.clone()
    zero[1, 2] = 0.0
    with pytest.raises(ValueError, match="not all zero"):
        robust_mean_pose(T, zero)
