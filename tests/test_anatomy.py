"""Label-edited training brains: ventricles shrunk, cerebellum grown, contrast re-drawn."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from svr.image import Image
from svr.sampling.anatomy import AnatomyVariantConfig, AtlasLabels, anatomy_variant

# A labelled ball on a 1 mm grid: white matter (1) round a spherical ventricle (2, radius 6 mm),
# a cerebellum (3, radius 3 mm) low at the back, extra-axial CSF (4) as an outer shell.
N = 40
LEVELS = {1: 100.0, 2: 300.0, 3: 150.0, 4: 250.0}
NOTHING = dict(
    ventricle_shrink_mm=(0.0, 0.0),
    cerebellum_grow_mm=(0.0, 0.0),
    intensity_jitter=0.0,
    random_contrast_probability=0.0,
    blur_mm=0.0,
)


def _distance(centre) -> np.ndarray:
    grid = np.stack(np.meshgrid(*[np.arange(N)] * 3, indexing="ij"), -1).astype(float)
    return np.linalg.norm(grid - np.asarray(centre, float), axis=-1)


@pytest.fixture(scope="module")
def brain():
    middle = (N - 1) / 2
    labels = np.zeros((N, N, N), np.int64)
    labels[_distance((middle,) * 3) <= 17] = 4
    labels[_distance((middle,) * 3) <= 15] = 1
    labels[_distance((middle,) * 3) <= 6] = 2
    labels[_distance((middle, middle - 9, middle - 9)) <= 3] = 3
    image = np.vectorize(lambda label: LEVELS.get(label, 0.0))(labels)
    texture = np.random.default_rng(0).normal(0.0, 2.0, labels.shape) * (labels > 0)
    affine = torch.eye(4, dtype=torch.float64)
    volume = Image(torch.tensor(image + texture, dtype=torch.float32), affine)
    return volume, torch.from_numpy(labels > 0), torch.from_numpy(labels).float(), texture


def test_a_variant_with_nothing_drawn_is_the_brain(brain) -> None:
    volume, mask, labels, _ = brain
    out = anatomy_variant(volume, mask, labels, AnatomyVariantConfig(**NOTHING), seed=3)
    assert out.data.dtype == torch.float32 and torch.equal(out.affine, volume.affine)
    torch.testing.assert_close(out.data, volume.data * mask, atol=1e-3, rtol=0)


def test_the_ventricles_shrink_by_the_drawn_depth(brain) -> None:
    volume, mask, labels, texture = brain
    config = AnatomyVariantConfig(**{**NOTHING, "ventricle_shrink_mm": (3.0, 3.0)})
    out = anatomy_variant(volume, mask, labels, config, seed=0).data.numpy()
    level = out - texture  # the label levels, texture removed
    ventricle = labels.numpy() == 2
    still = ventricle & (np.abs(level - LEVELS[2]) < 1.0)
    turned = ventricle & (np.abs(level - LEVELS[1]) < 1.0)
    assert (still | turned)[ventricle].all()  # each ventricle voxel is ventricle or white matter
    # A 6 mm ball shrunk by 3 mm keeps the voxels more than 3 mm inside its edge: a 3 mm ball.
    r = _distance(((N - 1) / 2,) * 3)
    assert still[r <= 2.0].all() and not still[(r >= 3.6) & ventricle].any()
    assert abs(int(still.sum()) - 4 / 3 * math.pi * 3.0**3) < 40
    assert (np.abs(level - volume.data.numpy() + texture)[~ventricle] < 1e-2).all()  # the rest


def test_the_cerebellum_grows_into_its_neighbours_only(brain) -> None:
    volume, mask, labels, texture = brain
    config = AnatomyVariantConfig(**{**NOTHING, "cerebellum_grow_mm": (2.0, 2.0)})
    level = anatomy_variant(volume, mask, labels, config, seed=0).data.numpy() - texture
    cerebellum = np.abs(level - LEVELS[3]) < 1.0
    # The oracle: every voxel within 2 mm of a cerebellum voxel's centre, by brute force.
    grid = np.stack(np.meshgrid(*[np.arange(N)] * 3, indexing="ij"), -1).reshape(-1, 3)
    seeds = grid[(labels.numpy() == 3).reshape(-1)]
    near = (np.linalg.norm(grid[:, None] - seeds[None], axis=-1).min(1) <= 2.0).reshape(N, N, N)
    inside = mask.numpy()
    assert np.array_equal(cerebellum, near & inside)  # nothing grows out of the brain
    assert (volume.data.numpy()[~inside] == 0).all() and (level + texture)[~inside].max() == 0
    # Grown into the extra-axial CSF only, the white matter beside it stays white matter.
    only = AnatomyVariantConfig(
        **{**NOTHING, "cerebellum_grow_mm": (2.0, 2.0)}, labels=AtlasLabels(grows_into=(4,))
    )
    level = anatomy_variant(volume, mask, labels, only, seed=0).data.numpy() - texture
    cerebellum = np.abs(level - LEVELS[3]) < 1.0
    assert np.array_equal(cerebellum, near & inside & np.isin(labels.numpy(), (3, 4)))


def test_contrast_is_redrawn_per_label_reproducibly(brain) -> None:
    volume, mask, labels, texture = brain
    config = AnatomyVariantConfig(**{**NOTHING, "random_contrast_probability": 1.0})
    a = anatomy_variant(volume, mask, labels, config, seed=7).data.numpy()
    b = anatomy_variant(volume, mask, labels, config, seed=7).data.numpy()
    c = anatomy_variant(volume, mask, labels, config, seed=8).data.numpy()
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    top = np.percentile(volume.data.numpy()[mask.numpy()], 99)
    for label in LEVELS:
        values = (a - texture)[labels.numpy() == label]
        assert values.max() - values.min() < 1e-2  # one level per label
        assert 0.1 * top - 1e-2 <= values.mean() <= top + 1e-2
    jitter = AnatomyVariantConfig(**{**NOTHING, "intensity_jitter": 0.1})
    d = anatomy_variant(volume, mask, labels, jitter, seed=1).data.numpy() - texture
    for label, value in LEVELS.items():
        assert 0.9 * value - 0.5 <= d[labels.numpy() == label].mean() <= 1.1 * value + 0.5


def test_bad_inputs_are_named(brain) -> None:
    volume, mask, labels, _ = brain
    with pytest.raises(ValueError, match="'labels' must have the volume's shape"):
        anatomy_variant(volume, mask, labels[:-1])
    with pytest.raises(ValueError, match="'mask' must have"):
        anatomy_variant(volume, mask[:, :-1], labels)
    with pytest.raises(ValueError, match="'labels' must be integers >= 0"):
        anatomy_variant(volume, mask, labels + 0.5)
    with pytest.raises(ValueError, match="'seed'"):
        anatomy_variant(volume, mask, labels, seed=-1)
    with pytest.raises(ValueError, match="'ventricle_shrink_mm'"):
        AnatomyVariantConfig(ventricle_shrink_mm=(3.0, 1.0))
    with pytest.raises(ValueError, match="'random_contrast_probability'"):
        AnatomyVariantConfig(random_contrast_probability=1.5)
    with pytest.raises(ValueError, match="'intensity_jitter'"):
        AnatomyVariantConfig(intensity_jitter=1.0)
