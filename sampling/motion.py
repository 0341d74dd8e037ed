"""Fetal head motion over time: real trajectories, a seeded random walk, or none.

A motion is a rigid transform ``D(tau)`` of the brain about its centre at each acquisition time
``tau`` (s), returned as (B, 4, 4) matrices acting on points relative to the brain centre:
``y = R(tau) x + t(tau)``.

Real trajectories: SVoRT's 154 fetal head-motion recordings (``.npz`` without pickles; keys
``rot_NNN_{x,y}`` and ``trans_NNN_{x,y}``: sample times in s, and (n, 3) values, extrinsic xyz
Euler angles in rad and translations in mm). A trajectory is interpolated linearly in time, made
relative to its value at the start time, and scaled by a magnitude factor (angles and
translations alike).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from svr.geometry import euler_to_matrix, vector_to_se3


@dataclass(frozen=True)
class Trajectory:
    """One recorded head motion.

    Attributes:
        times_s: (n,) increasing sample times in seconds.
        euler_rad: (n, 3) extrinsic xyz Euler angles in rad.
        translation_mm: (n, 3) translations in mm.
    """

    times_s: np.ndarray
    euler_rad: np.ndarray
    translation_mm: np.ndarray

    @property
    def duration_s(self) -> float:
        """Length of the recording in seconds."""
        return float(self.times_s[-1] - self.times_s[0])


def load_trajectories(path: str | os.PathLike[str]) -> list[Trajectory]:
    """Load SVoRT-format fetal motion trajectories.

    Args:
        path: The ``.npz`` file.

    Returns:
        The trajectories, in index order.

    Raises:
        ValueError: Naming the file, if it cannot be read, holds pickles, or has no trajectories
            in the expected layout.
    """
    p = Path(path)
    try:
        data = np.load(p, allow_pickle=False)
        names = sorted({k[4:7] for k in data.files if k.startswith("rot_")})
        out = []
        for n in names:
            rot_x, rot_y = data[f"rot_{n}_x"], data[f"rot_{n}_y"]
            tr_x, tr_y = data[f"trans_{n}_x"], data[f"trans_{n}_y"]
            if not np.array_equal(rot_x, tr_x) or rot_y.shape != (len(rot_x), 3) or len(rot_x) < 2:
                raise ValueError(f"trajectory {n} has inconsistent sample times or shapes")
            out.append(
                Trajectory(
                    rot_x.astype(np.float64), rot_y.astype(np.float64), tr_y.astype(np.float64)
                )
            )
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(f"{p}: not a fetal motion trajectory file ({err})") from err
    if not out:
        raise ValueError(f"{p}: no trajectories found (expected keys rot_NNN_x, rot_NNN_y, ...)")
    return out


def _interp(times: np.ndarray, samples_t: np.ndarray, values: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(times, samples_t, values[:, i]) for i in range(3)], axis=1)


def trajectory_motion(
    trajectory: Trajectory, times_s: np.ndarray, start_s: float, scale: float = 1.0
) -> Tensor:
    """Motion matrices of a trajectory at acquisition times, relative to its start.

    Times past the end of the recording wrap around (the recording is replayed).

    Args:
        trajectory: The recording.
        times_s: (B,) acquisition times in s, from the start of the acquisition.
        start_s: Where in the recording the acquisition starts (s).
        scale: Magnitude factor for angles and translations.

    Returns:
        (B, 4, 4) float64 motions about the brain centre, identity at time 0.
    """
    t0, length = trajectory.times_s[0], max(trajectory.duration_s, 1e-9)

    def at(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tt = t0 + np.mod(start_s + t, length)
        return (
            _interp(tt, trajectory.times_s, trajectory.euler_rad),
            _interp(tt, trajectory.times_s, trajectory.translation_mm),
        )

    euler, trans = at(np.asarray(times_s, dtype=np.float64))
    euler0, trans0 = at(np.zeros(1))
    R = euler_to_matrix(torch.from_numpy(scale * (euler - euler0)))
    T = torch.eye(4, dtype=torch.float64).repeat(len(euler), 1, 1)
    T[:, :3, :3] = R
    T[:, :3, 3] = torch.from_numpy(scale * (trans - trans0))
    return T


def random_walk_motion(
    num: int, generator: torch.Generator, rotation_deg: float, translation_mm: float
) -> Tensor:
    """A Gaussian random walk of rigid motions over ``num`` consecutive acquisitions.

    The rotation vector and translation each take ``num - 1`` independent Gaussian steps, sized so
    that their end points have standard deviation ``rotation_deg`` (per axis, in degrees) and
    ``translation_mm`` (per axis).

    Args:
        num: Number of acquisitions.
        generator: Source of randomness.
        rotation_deg: Per-axis std of the final rotation, degrees.
        translation_mm: Per-axis std of the final translation, mm.

    Returns:
        (num, 4, 4) float64 motions, identity first.
    """
    steps = torch.randn(max(num - 1, 0), 6, generator=generator, dtype=torch.float64)
    scale = torch.tensor(
        [math.radians(rotation_deg)] * 3 + [translation_mm] * 3, dtype=torch.float64
    ) / math.sqrt(max(num - 1, 1))
    walk = torch.cat([torch.zeros(1, 6, dtype=torch.float64), (steps * scale).cumsum(0)])
    return vector_to_se3(walk)
