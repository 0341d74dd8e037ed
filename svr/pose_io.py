"""Slice-pose tables (``docs/conventions.md``): one row per slice, as CSV or JSON.

Each row holds the stack (or slice-set) file, the slice index in it, the pose vector
``(r_x, r_y, r_z, t_x, t_y, t_z)`` (rad, mm), the 3x4 matrix ``[R | t]`` row by row, and the frame
the pose maps into (``canonical``, ``scanner`` or ``atlas``), optionally followed by extra
per-slice columns (e.g. a registration quality) that readers ignore. The pose maps slice-plane
coordinates ``(u, v, 0)`` in mm (origin at the slice centre, ``u`` along array axis 0) to that
frame.
"""

from __future__ import annotations

import csv
import io
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import torch
from torch import Tensor

from svr.files import atomic_write_text
from svr.frames import FRAMES, Frame
from svr.geometry import se3_to_vector, vector_to_se3
from svr.validation import check_choice

VECTOR_COLUMNS = ("r_x", "r_y", "r_z", "t_x", "t_y", "t_z")
MATRIX_COLUMNS = tuple(f"m{i}{j}" for i in range(3) for j in range(4))
COLUMNS = ("file", "slice_index", *VECTOR_COLUMNS, *MATRIX_COLUMNS, "frame")


@dataclass(frozen=True)
class PoseTable:
    """Slice poses with where they come from.

    Attributes:
        files: One file name per slice.
        slice_indices: (N,) long slice index within its file.
        poses: (N, 6) float64 pose vectors.
        frame: The target frame (:data:`svr.frames.Frame`).
    """

    files: list[str]
    slice_indices: Tensor
    poses: Tensor
    frame: Frame

    def __post_init__(self) -> None:
        n = self.poses.shape[0]
        if self.poses.dim() != 2 or self.poses.shape[1] != 6:
            raise ValueError(f"PoseTable: 'poses' must be (N, 6), got {tuple(self.poses.shape)}")
        if len(self.files) != n or self.slice_indices.shape != (n,):
            raise ValueError(
                "PoseTable: 'files', 'slice_indices' and 'poses' must have one entry per slice"
            )
        check_choice("PoseTable", "frame", self.frame, FRAMES)


def _rows(
    table: PoseTable, extra_columns: Mapping[str, Sequence[object]]
) -> list[dict[str, object]]:
    matrices = vector_to_se3(table.poses.to(torch.float64))[:, :3].reshape(-1, 12)
    rows = []
    for i, (name, vec, mat) in enumerate(
        zip(table.files, table.poses.tolist(), matrices.tolist(), strict=True)
    ):
        row: dict[str, object] = {"file": name, "slice_index": int(table.slice_indices[i])}
        row.update(zip(VECTOR_COLUMNS, vec, strict=True))
        row.update(zip(MATRIX_COLUMNS, mat, strict=True))
        row["frame"] = table.frame
        row.update((name, values[i]) for name, values in extra_columns.items())
        rows.append(row)
    return rows


def write_pose_table(
    table: PoseTable,
    path: str | os.PathLike[str],
    overwrite: bool = False,
    extra_columns: Mapping[str, Sequence[object]] | None = None,
) -> Path:
    """Write a pose table as CSV (``.csv``) or JSON (``.json``), atomically.

    Args:
        table: The poses.
        path: The file to write; its suffix chooses the format.
        overwrite: Whether an existing file may be replaced.
        extra_columns: More per-slice columns after ``frame``, in order: name -> one value per
            slice (numbers, bools or strings), e.g. a quality score. :func:`read_pose_table`
            ignores them.

    Raises:
        ValueError: For another file suffix, or an extra column that reuses a standard column's
            name or does not hold one value per slice.
        OutputExistsError: If the file exists and ``overwrite`` is false.
    """
    p = Path(path)
    extra = dict(extra_columns or {})
    for name, values in extra.items():
        if name in COLUMNS:
            raise ValueError(f"{p}: extra column {name!r} is a standard pose-table column")
        if len(values) != len(table.files):
            raise ValueError(
                f"{p}: extra column {name!r} has {len(values)} values for {len(table.files)} slices"
            )
    columns = [*COLUMNS, *extra]
    rows = _rows(table, extra)
    if p.suffix == ".json":
        text = json.dumps({"columns": columns, "slices": rows}, indent=1) + "\n"
    elif p.suffix == ".csv":
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        text = buffer.getvalue()
    else:
        raise ValueError(f"{p}: pose tables are written as .csv or .json")
    return atomic_write_text(p, text, overwrite)


def read_pose_table(path: str | os.PathLike[str]) -> PoseTable:
    """Read a pose table written by :func:`write_pose_table` (the 6-vectors are authoritative).

    Raises:
        ValueError: Naming the file, if it is missing, malformed, lacks columns or mixes frames.
    """
    p = Path(path)
    try:
        if p.suffix == ".json":
            rows = json.loads(p.read_text())["slices"]
        elif p.suffix == ".csv":
            with p.open(newline="") as f:
                rows = list(csv.DictReader(f))
        else:
            raise ValueError("expected a .csv or .json file")
        files = [str(r["file"]) for r in rows]
        indices = torch.tensor([int(r["slice_index"]) for r in rows], dtype=torch.long)
        poses = torch.tensor(
            [[float(r[c]) for c in VECTOR_COLUMNS] for r in rows], dtype=torch.float64
        ).reshape(-1, 6)
        frames = {str(r["frame"]) for r in rows}
    except (OSError, KeyError, TypeError, ValueError, json.JSONDecodeError) as err:
        raise ValueError(
            f"{p}: not a readable pose table ({err.__class__.__name__}: {err})"
        ) from err
    if len(frames) > 1:
        raise ValueError(f"{p}: rows mix frames {sorted(frames)}")
    try:
        frame = cast("Frame", frames.pop() if frames else "canonical")  # checked by PoseTable
        return PoseTable(files, indices, poses, frame)
    except ValueError as err:
        raise ValueError(f"{p}: {err}") from err


def matrices_to_table(
    files: list[str], slice_indices: Tensor, matrices: Tensor, frame: Frame
) -> PoseTable:
    """A pose table from (N, 4, 4) or (N, 3, 4) matrices."""
    return PoseTable(files, slice_indices, se3_to_vector(matrices.to(torch.float64)), frame)
