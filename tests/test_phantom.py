"""The procedural fetal-brain phantom: grid, intensities, anatomy, folding, determinism, config."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from svr.image import Image, world_to_voxel
from svr.sampling.phantom import (
    GA_WEEKS,
    T2_INTENSITY,
    PhantomConfig,
    PhantomLabel,
    gestational_age_config,
    make_phantom,
    make_phantom_labels,
    phantom_affine,
    required_field_of_view_mm,
)

SMALL = {"shape": (64, 64, 64), "spacing_mm": 1.6}


@pytest.fixture(scope="module")
def default_images() -> tuple[Image, Image, Image]:
    volume, mask = make_phantom()
    return volume, mask, make_phantom_labels()


@pytest.fixture(scope="module")
def default_phantom(default_images) -> tuple[np.ndarray, np.ndarray, np.ndarray, torch.Tensor]:
    volume, mask, labels = default_images
    return volume.data.numpy(), mask.data.numpy(), labels.data.numpy(), volume.affine


def _world_points(affine: torch.Tensor, index: np.ndarray) -> np.ndarray:
    a = affine.numpy()
    return index @ a[:3, :3].T + a[:3, 3]


def test_grid_dtypes_and_affine(default_images):
    volume, mask, labels = default_images
    assert volume.shape == mask.shape == labels.shape == (128, 128, 128)
    assert volume.data.dtype == mask.data.dtype == labels.data.dtype == torch.float32
    assert volume.affine.dtype == torch.float64
    assert torch.equal(volume.affine, mask.affine) and torch.equal(volume.affine, labels.affine)
    expected = torch.diag(torch.tensor([0.8, 0.8, 0.8, 1.0], dtype=torch.float64))
    expected[:3, 3] = -0.8 * 63.5
    torch.testing.assert_close(volume.affine, expected, rtol=0, atol=1e-12)
    origin = world_to_voxel(volume.affine, torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(origin, torch.full((3,), 63.5, dtype=torch.float64))


def test_world_origin_is_the_central_voxel_of_an_odd_grid():
    config = PhantomConfig(shape=(65, 71, 67), spacing_mm=1.6)
    affine = phantom_affine(config)
    origin = world_to_voxel(affine, torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(origin, torch.tensor([32.0, 35.0, 33.0], dtype=torch.float64))
    assert torch.equal(make_phantom_labels(config).affine, affine)


def test_intensities_and_mask(default_phantom):
    volume, mask, labels, _ = default_phantom
    assert np.isfinite(volume).all()
    assert volume.min() >= 0.0 and volume.max() <= 1.0
    assert volume.max() > 0.95  # CSF stays bright after the blur
    assert set(np.unique(mask)) == {0.0, 1.0}
    np.testing.assert_array_equal(mask > 0, labels > 0)
    # Background: zero beyond the blur's reach (two voxels) of the mask.
    far = ~ndimage.binary_dilation(mask > 0, np.ones((3, 3, 3), dtype=bool), iterations=2)
    assert far.sum() > 0 and volume[far].max() == 0.0


def _check_mask_size_and_centroid(mask: Image, length: float) -> None:
    points = _world_points(mask.affine, np.argwhere(mask.data.numpy() > 0))
    extent = points.max(0) - points.min(0) + float(mask.spacing[1])
    assert 0.85 * length < extent[1] < 1.15 * length
    assert extent[0] < extent[1] and extent[2] < extent[1]  # longest front to back
    np.testing.assert_allclose(points.mean(0), 0.0, atol=0.5)  # mm: canonical frame


def test_mask_size_and_centroid(default_images):
    _check_mask_size_and_centroid(default_images[1], 80.0)
    _, mask = make_phantom(PhantomConfig(brain_length_mm=60.0, shape=(96, 96, 96)))
    _check_mask_size_and_centroid(mask, 60.0)


def test_every_label_present_and_in_place(default_phantom):
    _, _, labels, affine = default_phantom
    assert set(np.unique(labels).astype(int)) == {int(label) for label in PhantomLabel}
    np.testing.assert_array_equal(labels, np.round(labels))

    def centroid(label: PhantomLabel) -> np.ndarray:
        return _world_points(affine, np.argwhere(labels == label)).mean(0)

    cerebellum, brainstem = centroid(PhantomLabel.CEREBELLUM), centroid(PhantomLabel.BRAINSTEM)
    assert cerebellum[1] < -15 and cerebellum[2] < -10  # posterior-inferior
    assert brainstem[2] < -10 and brainstem[1] > cerebellum[1]  # inferior, in front of it
    ventricles = _world_points(affine, np.argwhere(labels == PhantomLabel.LATERAL_VENTRICLES))
    left, right = (ventricles[:, 0] < 0).sum(), (ventricles[:, 0] > 0).sum()
    assert abs(left - right) < 0.05 * len(ventricles)  # one on each side
    third = _world_points(affine, np.argwhere(labels == PhantomLabel.THIRD_VENTRICLE))
    assert np.abs(third[:, 0]).max() < 2.0  # midline
    # The cortex is the cerebrum's outer layer: tissue next to CSF is cortex.
    cerebral = np.isin(labels, [PhantomLabel.CORTEX, PhantomLabel.WHITE_MATTER])
    touches_csf = cerebral & ndimage.binary_dilation(labels == PhantomLabel.CSF)
    assert (labels[touches_csf] == PhantomLabel.CORTEX).mean() > 0.95


def test_t2_contrast_ordering(default_phantom):
    volume, _, labels, _ = default_phantom

    def mean(label: PhantomLabel, erode: bool = False) -> float:
        region = labels == label
        if erode:
            region = ndimage.binary_erosion(region)
        return float(volume[region].mean())

    ventricles = mean(PhantomLabel.LATERAL_VENTRICLES)
    white, cortex = mean(PhantomLabel.WHITE_MATTER), mean(PhantomLabel.CORTEX)
    assert ventricles > white + 0.15 > cortex + 0.15
    assert mean(PhantomLabel.CSF, erode=True) > 0.95
    for label in (PhantomLabel.WHITE_MATTER, PhantomLabel.LATERAL_VENTRICLES):
        assert mean(label, erode=True) == pytest.approx(T2_INTENSITY[label], abs=0.02)
    assert cortex < mean(PhantomLabel.DEEP_GREY, erode=True) < white


def test_deterministic_and_seeded():
    config = PhantomConfig(**SMALL, folding=0.8, seed=3)
    volume_a, mask_a = make_phantom(config)
    volume_b, mask_b = make_phantom(PhantomConfig(**SMALL, folding=0.8, seed=3))
    assert torch.equal(volume_a.data, volume_b.data) and torch.equal(mask_a.data, mask_b.data)
    labels = make_phantom_labels(config).data
    other = make_phantom_labels(PhantomConfig(**SMALL, folding=0.8, seed=4)).data
    changed = labels != other
    assert changed.float().mean() > 0.005  # a different folding pattern ...
    assert torch.equal(labels > 0, other > 0)  # ... inside the same mask
    assert set(labels[changed].long().unique().tolist()) <= {
        int(PhantomLabel.CSF),
        int(PhantomLabel.CORTEX),
        int(PhantomLabel.WHITE_MATTER),
        int(PhantomLabel.DEEP_GREY),
    }


def test_seed_is_irrelevant_without_folding():
    smooth = make_phantom_labels(PhantomConfig(**SMALL, folding=0.0, seed=1)).data
    assert torch.equal(smooth, make_phantom_labels(PhantomConfig(**SMALL, folding=0.0)).data)


def _cerebral_surface_ratio(folding: float) -> float:
    """Faces between cerebral tissue and CSF per cerebral-tissue voxel."""
    labels = make_phantom_labels(PhantomConfig(folding=folding)).data.numpy()
    tissue = np.isin(labels, [PhantomLabel.CORTEX, PhantomLabel.WHITE_MATTER])
    csf = labels == PhantomLabel.CSF
    faces = sum(int((np.diff(tissue, axis=a) & np.diff(csf, axis=a)).sum()) for a in range(3))
    return faces / tissue.sum()


def test_folding_roughens_the_cortex():
    ratios = [_cerebral_surface_ratio(f) for f in (0.0, 0.5, 1.0)]
    assert ratios[0] < ratios[1] < ratios[2]
    assert ratios[2] > 1.5 * ratios[0]


def test_same_anatomy_at_another_resolution():
    length = 80.0
    coarse = make_phantom_labels(PhantomConfig((65, 65, 65), 1.6, length)).data.numpy()
    fine = make_phantom_labels(PhantomConfig((129, 129, 129), 0.8, length)).data.numpy()
    fine = fine[::2, ::2, ::2]  # the coarse voxel centres
    assert ((coarse > 0) == (fine > 0)).mean() > 0.999
    inside = coarse > 0
    assert (coarse[inside] == fine[inside]).mean() > 0.95


def test_gestational_age_config_monotonic_and_fits():
    weeks = np.linspace(GA_WEEKS[0], GA_WEEKS[-1], 37)
    configs = [gestational_age_config(float(w)) for w in weeks]
    lengths = [c.brain_length_mm for c in configs]
    foldings = [c.folding for c in configs]
    assert np.all(np.diff(lengths) > 0) and np.all(np.diff(foldings) >= 0)
    assert foldings[0] == 0.0 and foldings[-1] == 1.0
    assert gestational_age_config(22).brain_length_mm == pytest.approx(60.0, abs=3)
    assert gestational_age_config(34).brain_length_mm == pytest.approx(100.0, abs=5)
    for config in configs:  # the smallest cube of 128 + 16 n voxels that holds the brain
        n = config.shape[0]
        need = max(required_field_of_view_mm(config.brain_length_mm, config.spacing_mm))
        assert config.shape == (n, n, n) and n % 16 == 0
        assert n == 128 or (n - 16 - 1) * config.spacing_mm < need
    assert gestational_age_config(24).shape == (128, 128, 128)
    over = gestational_age_config(30, seed=7, spacing_mm=1.2)
    assert (over.seed, over.spacing_mm, over.shape) == (7, 1.2, (128, 128, 128))


def test_gestational_age_phantom_is_valid():
    volume, mask = make_phantom(gestational_age_config(21, shape=(64, 64, 64), spacing_mm=1.2))
    assert volume.shape == (64, 64, 64) and mask.data.sum() > 0


@pytest.mark.parametrize("weeks", [19.9, 38.5, math.nan, "30"])
def test_gestational_age_out_of_range(weeks):
    with pytest.raises(ValueError, match="'weeks'"):
        gestational_age_config(weeks)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("shape", (0, 128, 128)),
        ("shape", (128, 128)),
        ("shape", (128.5, 128, 128)),
        ("spacing_mm", 0.0),
        ("spacing_mm", -0.8),
        ("spacing_mm", math.inf),
        ("brain_length_mm", 0.0),
        ("brain_length_mm", math.nan),
        ("folding", -0.1),
        ("folding", 1.01),
        ("folding", math.nan),
        ("seed", -1),
        ("seed", 1.5),
    ],
)
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"'{field}'"):
        PhantomConfig(**{field: value})


@pytest.mark.parametrize(
    "overrides",
    [{"brain_length_mm": 100.0}, {"shape": (128, 96, 128)}, {"spacing_mm": 0.5}],
)
def test_brain_must_fit_in_the_field_of_view(overrides):
    with pytest.raises(ValueError, match=r"'brain_length_mm'.*'shape'.*'spacing_mm'"):
        PhantomConfig(**overrides)
    with pytest.raises(ValueError, match="does not fit"):
        gestational_age_config(34, shape=(128, 128, 128))
