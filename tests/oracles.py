"""Independent NumPy/scipy re-implementations used as test oracles (never the library itself)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation


def se3_error_np(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """e = (rotvec(R_pred^T R), R_pred^T (t - t_pred)) for (N, 6) float64 arrays."""
    r_pred = Rotation.from_rotvec(pred[:, :3])
    r_true = Rotation.from_rotvec(target[:, :3])
    e_rot = (r_pred.inv() * r_true).as_rotvec()
    e_trans = r_pred.inv().apply(target[:, 3:] - pred[:, 3:])
    return np.concatenate([e_rot, e_trans], axis=1)


def quadratic_form_np(e: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """e^T Z e per row, Z a (6,) diagonal or (6, 6) matrix."""
    z = np.diag(weights) if weights.ndim == 1 else weights
    return np.einsum("ni,ij,nj->n", e, z, e)


def right_jacobian_np(r: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """J_r(r) by central finite differences of log(R(r)^T R(r + d))."""
    base = Rotation.from_rotvec(r)
    cols = []
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        plus = (base.inv() * Rotation.from_rotvec(r + d)).as_rotvec()
        minus = (base.inv() * Rotation.from_rotvec(r - d)).as_rotvec()
        cols.append((plus - minus) / (2 * h))
    return np.stack(cols, axis=1)


def random_poses(
    rng: np.random.Generator, n: int, max_angle: float = np.pi, trans_mm: float = 20.0
) -> np.ndarray:
    """(n, 6) poses with uniformly random axes, angles in [0, max_angle), translations ~N(0, s)."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, max_angle, size=(n, 1))
    return np.concatenate([axis * angle, rng.normal(scale=trans_mm, size=(n, 3))], axis=1)


def np_gram_schmidt(d6: np.ndarray) -> np.ndarray:
    """Rotation matrices with columns Gram-Schmidt-orthonormalised from (..., 6) column pairs."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = a1 / np.linalg.norm(a1, axis=-1, keepdims=True)
    u2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = u2 / np.linalg.norm(u2, axis=-1, keepdims=True)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=-1)


def truth_poses(entry: dict, frame: str) -> torch.Tensor:
    """(N, 4, 4) poses of one stack's slices from a bench-style ``truth_slices.json`` entry."""
    poses = torch.eye(4, dtype=torch.float64).repeat(len(entry["slices"]), 1, 1)
    for k, s in enumerate(entry["slices"]):
        poses[k, :3, :3] = torch.tensor(s[frame]["R"])
        poses[k, :3, 3] = torch.tensor(s[frame]["t"])
    return poses


def foreground_cc(a: torch.Tensor, b: torch.Tensor) -> float:
    """Pearson correlation over the pixels that are non-zero in either image."""
    keep = (a > 0) | (b > 0)
    return float(np.corrcoef(a[keep].numpy(), b[keep].numpy())[0, 1])
