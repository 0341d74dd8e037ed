"""Atlases' warped labels fused into one label map, with how sure the fusion is.

Locally weighted voting (Artaechevarria et al. 2009; Sabuncu et al. 2010): at each voxel every
atlas votes with its warped label probabilities, weighted by how well its warped image matches
the reconstruction around that voxel, ``w_a(x) = (G_s * (I - J_a)^2 (x) + eps)^(-p)``, the local
mean squared difference in a Gaussian window of standard deviation ``s``, after each atlas's
intensities are mapped linearly onto the reconstruction's over the brain. Where the atlases
disagree the fused probability of the winning label is low: that is the uncertainty reported.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import ndimage

__all__ = ["FusedLabels", "fuse_labels", "local_weights"]


class FusedLabels(NamedTuple):
    """The fused labels of one reconstruction.

    Attributes:
        labels: (I, J, K) uint8 labels (0 outside ``mask``).
        probability: (I, J, K) float32 fused probability of the chosen label (1 outside the mask).
        agreement: (I, J, K) float32 fraction of the atlases whose own most likely label is the
            chosen one (1 outside the mask).
    """

    labels: np.ndarray
    probability: np.ndarray
    agreement: np.ndarray


def _matched(reference: np.ndarray, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` mapped by the linear fit ``a image + b`` to ``reference`` over ``mask``."""
    x = image[mask].astype(np.float64)
    y = reference[mask].astype(np.float64)
    variance = float(x.var())
    if variance <= 0:
        return np.full_like(image, float(y.mean()))
    slope = float(((x - x.mean()) * (y - y.mean())).mean() / variance)
    return (slope * (image - x.mean()) + y.mean()).astype(np.float32)


def local_weights(
    volume: np.ndarray,
    warped: list[np.ndarray],
    mask: np.ndarray,
    sigma_voxels: tuple[float, float, float],
    power: float,
) -> np.ndarray:
    """Each atlas's local vote weight (module docstring), normalised to sum 1 at every voxel.

    Args:
        volume: (I, J, K) the reconstruction.
        warped: A (I, J, K) warped atlas image per atlas.
        mask: (I, J, K) bool brain.
        sigma_voxels: The Gaussian window's standard deviation per axis (voxels).
        power: The exponent ``p`` (>= 0; 0 is plain majority voting).

    Returns:
        (A, I, J, K) float32 weights.
    """
    scale = float(np.percentile(volume[mask], 99)) if mask.any() else 1.0
    scale = scale if scale > 0 else 1.0
    lmse = []
    for image in warped:
        difference = (volume - _matched(volume, image, mask)) / scale
        lmse.append(ndimage.gaussian_filter(difference * difference, sigma_voxels))
    weights = (np.stack(lmse) + 1e-3) ** (-power)
    return (weights / weights.sum(0, keepdims=True)).astype(np.float32)


def fuse_labels(
    probabilities: list[np.ndarray],
    weights: np.ndarray,
    mask: np.ndarray,
) -> FusedLabels:
    """Fuse the atlases' warped label probabilities with per-voxel weights.

    Args:
        probabilities: A (L, I, J, K) float32 array per atlas: the warped probability of each
            label value 0..L-1 (background included).
        weights: (A, I, J, K) weights summing to 1 over the atlases.
        mask: (I, J, K) bool: where labels are given (0 elsewhere).

    Returns:
        The labels and how sure they are.

    Raises:
        ValueError: If the numbers of atlases differ.
    """
    if len(probabilities) != weights.shape[0]:
        raise ValueError(
            f"fuse_labels(): {len(probabilities)} atlases' probabilities but {weights.shape[0]} "
            "weights"
        )
    fused = np.zeros_like(probabilities[0])
    for probability, weight in zip(probabilities, weights, strict=True):
        fused += probability * weight[None]
    labels = np.argmax(fused, axis=0).astype(np.uint8)
    chosen = np.take_along_axis(fused, labels[None].astype(np.int64), axis=0)[0]
    votes = np.zeros(labels.shape, np.float32)
    for probability in probabilities:
        votes += np.argmax(probability, axis=0) == labels
    agreement = votes / len(probabilities)
    labels[~mask] = 0
    chosen = np.where(mask, chosen, 1.0).astype(np.float32)
    agreement = np.where(mask, agreement, 1.0).astype(np.float32)
    return FusedLabels(labels, chosen, agreement)
