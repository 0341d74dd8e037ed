"""Whole-uterus training scenes: the brain and its mask kept exactly, shells and surroundings."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic import ellipsoid_brain

from svr.image import Image, resample_to_grid
from svr.sampling.scenes import (
    SceneConfig,
    _neck_direction,
    _paint_face,
    _split_cord,
    make_scene,
)
from svr.sampling.simulate import SimulationConfig, simulate_case
from svr.sampling.volume import canonicalize

SMALL = SceneConfig(extent_mm=120.0, spacing_mm=2.0, brain_scale=(1.0, 1.0), gamma=(1.0, 1.0))


@pytest.fixture(scope="module")
def brain():
    return canonicalize(*ellipsoid_brain(48, 1.0, (18.0, 22.0, 16.0), seed=0), name="ellipsoid")


def test_scene_keeps_the_brain_and_its_mask(brain):
    scene = make_scene(brain, SMALL, seed=1)
    assert scene.image.shape == scene.mask.shape == (60, 60, 60)
    assert scene.image.data.dtype == torch.float32 and scene.mask.dtype == torch.bool
    # at scale 1 the mask is the brain's mask resampled (nearest) onto the scene grid
    brain_mask = Image(brain.mask.float(), brain.image.affine)
    want = resample_to_grid(brain_mask, scene.image, mode="nearest").data > 0.5
    assert torch.equal(scene.mask, want)
    inside = resample_to_grid(brain.image, scene.image).data[scene.mask]
    torch.testing.assert_close(scene.image.data[scene.mask], inside.clamp_min(0), atol=1e-5, rtol=0)
    assert torch.equal(scene.centre_mm, torch.zeros(3, dtype=torch.float64))


def test_scene_has_surroundings_and_head_shells(brain):
    config = SceneConfig(
        extent_mm=120.0, spacing_mm=2.0, csf_mm=(2.5, 4.0), skull_mm=(3.0, 4.0), texture=0.0
    )
    scene = make_scene(brain, config, seed=2)
    outside = scene.image.data[~scene.mask]
    assert float((outside > 0).float().mean()) > 0.99  # no empty background: a uterus scene
    from scipy import ndimage

    distance = ndimage.distance_transform_edt(~scene.mask.numpy(), sampling=2.0)
    image = scene.image.data.numpy()
    csf = image[(distance > 0) & (distance <= 2.0)]  # the first shell: CSF, 2.5-4 mm thick
    assert csf.min() == csf.max() and 1.0 <= csf.min() <= 2.0
    skull = image[(distance > 4.5) & (distance <= 5.5)]  # inside the skull: [csf, csf + 3..4]
    assert skull.size and float(np.median(skull)) <= 0.3


def test_scenes_are_reproducible_and_differ_by_seed(brain):
    a, b = make_scene(brain, SMALL, seed=5), make_scene(brain, SMALL, seed=5)
    assert torch.equal(a.image.data, b.image.data) and torch.equal(a.mask, b.mask)
    c = make_scene(brain, SMALL, seed=6)
    assert not torch.equal(a.image.data, c.image.data)


def test_scale_changes_the_brain_size(brain):
    small = make_scene(brain, SceneConfig(extent_mm=120.0, brain_scale=(0.8, 0.8)), seed=0)
    large = make_scene(brain, SceneConfig(extent_mm=120.0, brain_scale=(1.2, 1.2)), seed=0)
    ratio = float(large.mask.sum()) / float(small.mask.sum())
    assert ratio == pytest.approx(1.5**3, rel=0.15)


def test_stacks_cut_from_a_scene_show_the_surroundings(brain):
    scene = make_scene(brain, SMALL, seed=3)
    case = simulate_case(
        scene, SimulationConfig(num_stacks=1, margin_mm=30.0, motion="none", seed=0)
    )
    stack = case.stacks[0]
    data, mask = stack.image.data, stack.mask.data > 0.5
    assert 0.0 < float(mask.float().mean()) < 0.5
    assert float((data[~mask] > 0.05).float().mean()) > 0.5  # not a masked brain alone


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("extent_mm", 0.0),
        ("spacing_mm", float("nan")),
        ("brain_scale", (1.2, 0.8)),
        ("maternal_labels", (0, 3)),
        ("texture", -0.1),
        ("distractors", (5, 2)),
        ("distractors", (-1, 2)),
        ("distractor_mm", (0.0, 3.0)),
        ("body_scale", (2.0, 1.0)),
        ("face", 1),
        ("spinal_cord", None),
        ("intracranial_mask", "yes"),
    ],
)
def test_config_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"'{field}'"):
        SceneConfig(**{field: value})


def test_seed_must_be_a_non_negative_int(brain):
    with pytest.raises(ValueError, match="'seed'"):
        make_scene(brain, SMALL, seed=-1)
    assert np.isfinite(make_scene(brain, SMALL, seed=0).image.data.numpy()).all()


def test_air_outside_the_abdomen(brain):
    config = SceneConfig(
        extent_mm=200.0,
        spacing_mm=4.0,
        fluid_margin_mm=(10.0, 10.0),
        abdomen_margin_mm=(15.0, 15.0),
    )
    scene = make_scene(brain, config, seed=4)
    image = scene.image.data
    assert float(image[0, 0, 0]) == 0.0 and float(image[-1, -1, -1]) == 0.0
    assert 0.2 < float((image == 0).float().mean()) < 0.95
    assert bool((image[scene.mask] > 0).any())


def test_organs_change_only_the_surroundings(brain):
    """Organs (distractors) are painted outside the head; the brain and its mask are kept, and
    scenes without organs draw the same random numbers as before organs existed."""
    plain = make_scene(brain, SMALL, seed=3)
    busy = make_scene(brain, SMALL.__class__(**{**SMALL.__dict__, "distractors": (40, 40)}), seed=3)
    assert torch.equal(plain.mask, busy.mask)
    assert torch.equal(plain.image.data[plain.mask], busy.image.data[busy.mask])
    changed = (plain.image.data != busy.image.data) & ~plain.mask
    assert float(changed.float().mean()) > 0.02
    from scipy import ndimage

    distance = ndimage.distance_transform_edt(~plain.mask.numpy(), sampling=2.0)
    assert not changed.numpy()[distance <= 1.5].any()  # the CSF shell next to the brain is kept
    # the sum of this scene as the code before organs made it (commit 6ac7f6d)
    assert float(plain.image.data.double().sum()) == pytest.approx(257755.41016155295, rel=1e-9)


def _added_by(brain, base: dict, extra: dict) -> torch.Tensor:
    """Intensities of the voxels a mask option adds to the same untextured scene (seed 8).

    Checks that the image is unchanged and the new mask is a strict superset of the old one.
    """
    plain = SceneConfig(**{**SMALL.__dict__, "texture": 0.0, **base})
    before = make_scene(brain, plain, seed=8)
    after = make_scene(brain, SceneConfig(**{**plain.__dict__, **extra}), seed=8)
    assert torch.equal(before.image.data, after.image.data)
    assert bool((after.mask | ~before.mask).all())  # a superset
    added = after.mask & ~before.mask
    assert int(added.sum()) > 0
    return after.image.data[added]


def test_intracranial_mask_adds_the_csf_shell_only(brain):
    """The same scene; its mask grows by the CSF shell (inside the skull) and nothing else."""
    values = _added_by(brain, {}, {"intracranial_mask": True})
    assert float(values.min()) == float(values.max()) >= 1.0  # the CSF intensity, one value


def test_skull_in_mask_adds_the_skull_shell_only(brain):
    """The same scene; the intracranial mask grows by the skull shell (one dark value)."""
    values = _added_by(brain, {"intracranial_mask": True}, {"skull_in_mask": True})
    assert float(values.min()) == float(values.max()) <= 0.3  # the skull's intensity, one value
    with pytest.raises(
        ValueError, match="'skull_in_mask' must be False without 'intracranial_mask'"
    ):
        SceneConfig(skull_in_mask=True)


def test_tissue_labels_randomise_only_the_brain(brain):
    """With labels, the brain gets one random intensity per label (blurred); the rest of the
    scene, drawn from the main random stream, is unchanged."""
    labels = (brain.image.data > float(brain.image.data[brain.mask].median())).long() + 1
    labels[~brain.mask] = 0
    plain = make_scene(brain, SMALL, seed=9)
    synthetic = make_scene(brain, SMALL, seed=9, tissue_labels=labels)
    assert torch.equal(plain.mask, synthetic.mask)
    outside = ~plain.mask
    assert torch.equal(plain.image.data[outside], synthetic.image.data[outside])
    inside = synthetic.image.data[plain.mask]
    assert not torch.allclose(inside, plain.image.data[plain.mask])
    assert float(inside.min()) >= 0.0 and float(inside.max()) <= 1.0  # values in [0.1, 1], blurred


def test_faces_change_only_what_is_beyond_the_skull(brain):
    """A face (and the body on a neck) changes the scene beyond the skull only: the brain, the
    head's shells and the mask are the same, and scenes without a face draw the same numbers."""
    config = SceneConfig(**{**SMALL.__dict__, "texture": 0.0, "intracranial_mask": True})
    plain = make_scene(brain, config, seed=3)
    faced = make_scene(brain, SceneConfig(**{**config.__dict__, "face": True}), seed=3)
    assert torch.equal(plain.mask, faced.mask)
    from scipy import ndimage

    distance = ndimage.distance_transform_edt(~plain.mask.numpy(), sampling=2.0)
    changed = (plain.image.data != faced.image.data).numpy()
    assert changed.mean() > 0.01
    assert not changed[distance <= 1.5].any()  # the brain and the CSF next to it are kept


def test_face_has_two_eyes_below_the_front_of_the_brain(brain):
    """Painted on an empty scene with one intensity per part: all of it beyond the skull, the
    face under the front of the brain (canonical RAS), two eyes (the vitreous value) on either
    side of the midline, each with a darker lens."""
    from scipy import ndimage

    from svr.image import voxel_centres

    config = SceneConfig(
        extent_mm=120.0,
        spacing_mm=1.0,
        csf_intensity=(1.5, 1.5),
        tissue_intensity=(0.6, 0.6),
        skull_intensity=(0.1, 0.1),
    )
    grid = make_scene(brain, config, seed=1)
    xyz = voxel_centres(grid.image).numpy()
    mask = grid.mask.numpy()
    distance = ndimage.distance_transform_edt(~mask, sampling=1.0)
    scene = np.zeros(mask.shape)
    _paint_face(scene, xyz, mask, distance, 4.0, config, np.random.default_rng(0))
    painted = scene != 0
    assert painted.sum() > 500 and not painted[distance <= 4.0].any()
    points = xyz[mask]
    front, middle = points[:, 1].max(), points.mean(axis=0)
    assert xyz[painted][:, 2].mean() < points[:, 2].min() + 4.0  # below the brain
    assert xyz[painted][:, 1].mean() > middle[1]  # in front of its centre
    eyes, count = ndimage.label(scene == 1.5)
    assert count == 2
    centres = np.array([xyz[eyes == k].mean(axis=0) for k in (1, 2)])
    assert (centres[:, 0] - middle[0]).prod() < 0  # one each side of the midline
    assert (centres[:, 1] > front - 0.3 * np.ptp(points[:, 1])).all()
    frontal = points[points[:, 1] > front - 0.25 * np.ptp(points[:, 1])]
    assert (centres[:, 2] < frontal[:, 2].min() - 4.0).all()  # under the frontal lobes' skull
    lenses = xyz[scene == 0.1]
    assert lenses.size and lenses[:, 1].mean() > centres[:, 1].mean()  # at the eyes' front


def test_neck_is_below_and_behind_the_brain():
    rng = np.random.default_rng(0)
    directions = np.array([_neck_direction(rng) for _ in range(500)])
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0)
    assert (directions[:, 2] < 0).mean() > 0.95 and directions[:, 1].mean() < -0.2


def test_split_cord_cuts_the_thin_part_below_the_base():
    """A ball with a one-voxel rod hanging below it: the cord is the rod under the lowest plane
    whose cross-section is at least 5 % of the ball's largest (pi 10^2: a radius of 2.24)."""
    i, j, k = np.meshgrid(*(np.arange(40),) * 3, indexing="ij")
    ball = (i - 20) ** 2 + (j - 20) ** 2 + (k - 25) ** 2 <= 100
    rod = (i == 20) & (j == 20) & (k >= 3)
    head, cord = _split_cord(ball | rod)
    areas = ball.sum(axis=(0, 1))
    base = int(np.nonzero(areas >= 0.05 * areas.max())[0][0])
    assert 15 < base < 20  # a plane of the ball's bottom cap
    assert np.array_equal(cord, rod & (k < base)) and np.array_equal(
        head, (ball | rod) & (k >= base)
    )
    empty = np.zeros((4, 4, 4), dtype=bool)
    assert not any(part.any() for part in _split_cord(empty))


def test_spinal_cord_leaves_the_mask_below_the_skull_base():
    """An ellipsoid brain with a brainstem (a 4 mm rod, 14 mm below it) in the same scene with
    the cord: its brain voxels are painted as before, the mask (brain and shells) loses only
    voxels near its bottom, and the rod's lower part is out of it."""
    volume, mask = ellipsoid_brain(64, 1.0, (18.0, 22.0, 16.0), seed=0)
    i, j, k = np.indices(mask.shape) - 31.5
    rod = torch.from_numpy((i**2 + j**2 <= 4) & (k > -30) & (k < 0))
    mask.data[rod] = 1.0
    volume.data[rod] = 1.0
    brain = canonicalize(volume, mask, name="ellipsoid with a brainstem")
    config = SceneConfig(**{**SMALL.__dict__, "texture": 0.0, "intracranial_mask": True})
    plain = make_scene(brain, config, seed=4)
    cut = make_scene(brain, SceneConfig(**{**config.__dict__, "spinal_cord": True}), seed=4)
    lost = plain.mask & ~cut.mask
    assert not bool((cut.mask & ~plain.mask).any()) and int(lost.sum()) > 0
    z = np.argwhere(plain.mask.numpy())[:, 2]
    assert np.argwhere(lost.numpy())[:, 2].max() < np.percentile(z, 25)
    assert np.argwhere(cut.mask.numpy())[:, 2].min() >= z.min() + 5  # >= 10 mm of it gone
    brain_mask = Image(brain.mask.float(), brain.image.affine)
    inside = resample_to_grid(brain_mask, plain.image, mode="nearest").data > 0.5
    assert torch.equal(plain.image.data[inside], cut.image.data[inside])
