"""A one-page quality report of a reconstruction (matplotlib, Agg, no display needed).

The page shows, top to bottom:

* orthogonal views of the initial volume (scattered-data approximation at the initial poses),
  the final volume and, when given, a reference volume resampled onto the result's grid by world
  position: the planes normal to the grid's axes (the frame's x, y and z) through the centroid
  of the result's mask, each volume on its own grey scale (0 to its in-mask 99.5th percentile).
  A volume in the canonical frame is first resampled onto a grid aligned with that frame's axes
  (:func:`axis_aligned`), because bringing it into the atlas frame relabels its affine without
  resampling: its views are then the atlas's sagittal (x), coronal (y) and axial (z) planes;
* every slice's NCC with its simulation from the final volume against its number (the row of
  the transforms table), coloured by stack, excluded slices marked with a red cross;
* the wall time of each phase and the initialisation kept for each stack;
* when the rounds were recorded, the convergence of the rounds: per round, the median pose change
  of the registered slices (degrees and mm), the mean slice NCC and the number of slices
  excluded, titled with whether the slices converged.
"""

from __future__ import annotations

import io
import os
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import cast

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.gridspec import SubplotSpec
from torch import Tensor

from svr.files import atomic_write_bytes, check_output_path
from svr.image import Image, resample_to_grid
from svr.reconstruction.atlas_frame import atlas_turn_line
from svr.reconstruction.convergence import verdict
from svr.reconstruction.midplane import mirror_plane_line
from svr.reconstruction.result import ReconstructionResult
from svr.reconstruction.slices import moved_from_stack

__all__ = ["FIGURE_SUFFIXES", "axis_aligned", "masks_figure", "qa_figure"]

FIGURE_SUFFIXES = (".png", ".pdf")
_AXES = ("x", "y", "z")


def axis_aligned(image: Image, mask: Tensor, mode: str = "bilinear") -> Image:
    """An image resampled onto a grid aligned with the world axes around a mask.

    The grid has the image's finest spacing.

    Args:
        image: (I, J, K) volume, its affine any rotation (voxel -> world mm).
        mask: (I, J, K) bool mask on its grid; the grid covers its voxels' world bounding box
            (the whole image where it is empty), with one voxel of margin.
        mode: ``"bilinear"`` (trilinear) or ``"nearest"`` (label maps).

    Returns:
        The float32 image on the new grid (affine: the spacing on the diagonal, no rotation).
    """
    affine = image.affine.detach().cpu().double()
    inside = mask.detach().cpu()
    idx = torch.nonzero(inside) if bool(inside.any()) else torch.nonzero(torch.ones_like(inside))
    corners = idx.double()[:, None, :] + torch.tensor(
        [[a, b, c] for a in (-0.5, 0.5) for b in (-0.5, 0.5) for c in (-0.5, 0.5)],
        dtype=torch.float64,
    )
    world = corners.reshape(-1, 3) @ affine[:3, :3].T + affine[:3, 3]
    spacing = float(affine[:3, :3].norm(dim=0).min())
    low = world.min(dim=0).values - spacing
    shape = tuple(int(n) for n in torch.ceil((world.max(dim=0).values + spacing - low) / spacing))
    grid = torch.eye(4, dtype=torch.float64)
    grid[:3, :3] *= spacing
    grid[:3, 3] = low + spacing / 2
    like = Image(torch.zeros(shape, dtype=torch.float32), grid.to(image.affine.device))
    return resample_to_grid(image, like, mode)


def orthogonal_planes(volume: np.ndarray, centre: tuple[int, int, int]) -> list[np.ndarray]:
    """The three planes through ``centre`` normal to axes i, j, k, as (rows, columns) arrays.

    Displayed with ``origin="lower"``: rows go up along the later axis, columns along the earlier.
    """
    i, j, k = centre
    return [volume[i, :, :].T, volume[:, j, :].T, volume[:, :, k].T]


_PLANES = ("sagittal", "coronal", "axial")


def _column_title(frame: str, axis: int, mm: float) -> str:
    """A column's title: the plane, in the frame it is in (canonical planes are anatomical)."""
    where = f"{frame} {_AXES[axis]} = {mm:.1f} mm"
    return f"{_PLANES[axis]}\n({where})" if frame == "canonical" else where


NOTE_WIDTH = 44
"""Characters per line of a stack's initialisation note in the figure's text panel."""


def _text(result: ReconstructionResult, notes: Sequence[str] = ()) -> str:
    timings = result.timings_s
    lines = [*notes, "time per phase (s)"]
    lines += [f"  {name}: {seconds:.1f}" for name, seconds in timings.items()]
    lines.append(f"  total: {sum(timings.values()):.1f}")
    lines.append("initialisation per stack; slices moved from it (median / max deg)")
    notes = result.initialisation_notes or ("",) * len(result.initialisation)
    moved = moved_from_stack(result.slices)
    ids = result.slices.stack_ids.cpu()
    for sid, (name, init, note) in enumerate(
        zip(result.slices.stack_names, result.initialisation, notes, strict=True)
    ):
        mine = moved[ids == sid]
        spread = (
            f"; moved {float(mine.median()):.0f} / {float(mine.max()):.0f}" if len(mine) else ""
        )
        lines.append(f"  {Path(name).name}: {init}{spread}")
        # Long notes (the learned starts' scores) wrap under their stack: one long line
        # squeezed the figure's panels.
        lines += textwrap.wrap(note, NOTE_WIDTH, initial_indent="    ", subsequent_indent="    ")
    spacing = float(result.volume.spacing[0])
    excluded = int(result.excluded.sum())
    lines.append(f"slices: {len(result.slices)}, excluded {excluded}")
    lines.append(f"volume: {'x'.join(map(str, result.volume.shape))} at {spacing:.2f} mm")
    lines.append(f"frame: {result.slices.frame}")
    if result.frame_margin is not None or result.atlas_margin is not None:
        margins = [
            f"stack-pose {result.frame_margin:.1f}" if result.frame_margin is not None else "",
            f"atlas {result.atlas_margin:.3f}" if result.atlas_margin is not None else "",
        ]
        lines.append("frame margins: " + ", ".join(m for m in margins if m))
    turn = atlas_turn_line(result)
    lines += [turn] if turn else []
    mirror = mirror_plane_line(result)
    lines += [mirror] if mirror else []
    return "\n".join(lines)


def _convergence_panel(figure: Figure, cell: SubplotSpec, result: ReconstructionResult) -> None:
    rounds = result.rounds
    index = np.array([r.index for r in rounds])
    ax = figure.add_subplot(cell)
    moved = [r for r in rounds if r.registered]
    if moved:
        x = np.array([r.index for r in moved])
        ax.plot(x, [r.rotation_deg for r in moved], "o-", label="median rotation change (deg)")
        ax.plot(x, [r.translation_mm for r in moved], "s-", label="median shift (mm)")
    ax.set_xlabel("round")
    ax.set_ylabel("median change of the registered slices")
    ax.set_xticks(index)
    ax.set_ylim(bottom=0.0)
    right = ax.twinx()
    right.plot(index, [r.ncc for r in rounds], "k.--", label="mean slice NCC")
    for r in rounds:
        if r.excluded:
            right.annotate(f"{r.excluded} excl.", (r.index, r.ncc), fontsize=6, color="red")
    right.set_ylabel("mean slice NCC")
    handles = ax.get_legend_handles_labels()
    extra = right.get_legend_handles_labels()
    ax.legend(handles[0] + extra[0], handles[1] + extra[1], fontsize=7, loc="upper right")
    ending = verdict(result.converged)
    ax.set_title(f"{len(rounds)} rounds" + (f": {ending}" if ending else ""), fontsize=9)


def qa_figure(
    result: ReconstructionResult,
    path: str | os.PathLike[str],
    reference: Image | None = None,
    overwrite: bool = False,
    notes: Sequence[str] = (),
    labels: Image | None = None,
    label_colours: Sequence[str] = (),
) -> Path:
    """Draw the quality page of a reconstruction (see the module docstring), atomically.

    Args:
        result: The reconstruction.
        path: A ``.png`` or ``.pdf`` file name; the suffix chooses the format.
        reference: A volume in the result's frame (e.g. the ground truth of a simulation), shown
            resampled onto the result's grid; ``None`` for none.
        overwrite: Whether an existing file may be replaced.
        notes: Lines printed first in the text panel (e.g. where the brain masks came from).
        labels: Tissue labels on the final volume's grid (``svr segment-volume``), drawn over
            the final volume in a row of their own; ``None`` for none.
        label_colours: The colour (``#rrggbb``) of label 1, 2, ...

    Returns:
        The written path.

    Raises:
        ValueError: If the suffix is not ``.png`` or ``.pdf``.
        OutputExistsError: If the file exists and ``overwrite`` is false.
    """
    p = Path(path)
    if p.suffix not in FIGURE_SUFFIXES:
        raise ValueError(f"{p}: QA figures are written as .png or .pdf")
    check_output_path(p, overwrite)
    volumes = {"initial": result.initial_volume, "final": result.volume}
    if reference is not None:
        volumes["reference"] = resample_to_grid(reference, result.volume)
    mask_image = result.mask
    if result.slices.frame == "canonical":
        brain = result.mask.data > 0.5
        volumes = {name: axis_aligned(image, brain) for name, image in volumes.items()}
        mask_image = axis_aligned(result.mask, brain)
        if labels is not None:
            labels = axis_aligned(labels, brain, mode="nearest")
    label_data = None
    if labels is not None:
        label_data = labels.data.detach().cpu().float().numpy().round().astype(np.int64)
        volumes["tissue labels"] = volumes["final"]
    mask = mask_image.data.detach().cpu() > 0.5
    if bool(mask.any()):
        where = torch.nonzero(mask).double().mean(dim=0)
    else:
        where = (torch.tensor(mask.shape, dtype=torch.float64) - 1) / 2
    centre = cast("tuple[int, int, int]", tuple(round(float(c)) for c in where))
    affine = volumes["final"].affine.detach().cpu().double()
    world = affine[:3, :3] @ torch.tensor(centre, dtype=torch.float64) + affine[:3, 3]

    panels = [1.1] + ([1.1] if result.rounds else [])
    figure = Figure(figsize=(8.27, 2.6 * len(volumes) + 3.0 * len(panels)), layout="constrained")
    FigureCanvasAgg(figure)
    if result.verdict is not None:
        colour = {"ok": "black", "warning": "darkorange", "failed": "red"}[result.verdict.status]
        if result.verdict.frame == "untrusted":
            colour = "red"
        text = textwrap.fill(f"verdict: {result.verdict.line()}", 110)
        figure.suptitle(text, color=colour, fontsize=9, ha="left", x=0.01)
    grid = figure.add_gridspec(
        len(volumes) + len(panels), 3, height_ratios=[1.0] * len(volumes) + panels
    )
    for row, (name, image) in enumerate(volumes.items()):
        data = image.data.detach().cpu().float().numpy()
        inside = data[mask.numpy()] if bool(mask.any()) else data.ravel()
        vmax = float(np.percentile(inside, 99.5)) if inside.size else 1.0
        overlays = (
            orthogonal_planes(label_data, centre)
            if name == "tissue labels" and label_data is not None
            else None
        )
        for col, plane in enumerate(orthogonal_planes(data, centre)):
            ax = figure.add_subplot(grid[row, col])
            ax.imshow(plane, cmap="gray", origin="lower", vmin=0.0, vmax=vmax or 1.0)
            if overlays is not None:
                colours = ListedColormap(["#000000", *label_colours])
                ax.imshow(
                    np.ma.masked_equal(overlays[col], 0),
                    cmap=colours,
                    origin="lower",
                    vmin=0,
                    vmax=len(label_colours),
                    alpha=0.45,
                    interpolation="nearest",
                )
            ax.set_xticks([])
            ax.set_yticks([])
            if col == 0:
                ax.set_ylabel(name)
            if row == 0:
                ax.set_title(_column_title(result.slices.frame, col, float(world[col])), fontsize=9)

    ax = figure.add_subplot(grid[len(volumes), :2])
    ncc = result.slice_ncc.detach().cpu().double().numpy()
    stack_ids = result.slices.stack_ids.detach().cpu().numpy()
    excluded = result.excluded.detach().cpu().numpy().astype(bool)
    number = np.arange(len(ncc))
    for sid, name in enumerate(result.slices.stack_names):
        members = stack_ids == sid
        ax.plot(number[members], ncc[members], "o", markersize=3, label=Path(name).name)
    if excluded.any():
        ax.plot(number[excluded], ncc[excluded], "x", color="red", label="excluded")
    ax.set_xlabel("slice (row of the transforms table)")
    ax.set_ylabel("NCC with simulation")
    ax.set_ylim(float(ncc.min(initial=0.0)) - 0.05, 1.02)
    ax.legend(fontsize=7, loc="best", ncol=2)

    ax = figure.add_subplot(grid[len(volumes), 2])
    ax.axis("off")
    ax.text(0.0, 1.0, _text(result, notes), va="top", ha="left", family="monospace", fontsize=7)
    if result.rounds:
        _convergence_panel(figure, grid[len(volumes) + 1, :], result)

    buffer = io.BytesIO()
    figure.savefig(buffer, format=p.suffix[1:], dpi=100)
    return atomic_write_bytes(p, buffer.getvalue(), overwrite)


def masks_figure(
    stacks: Sequence[tuple[str, Image, Tensor]],
    path: str | os.PathLike[str],
    overwrite: bool = False,
    title: str = "brain masks",
) -> Path:
    """Draw each stack with its brain mask's outline, for a person to check at a glance.

    One row per stack: three slices (k-planes) at a quarter, half and three quarters of the
    mask's extent through the stack, on a grey scale from 0 to the stack's 99.5th percentile,
    the mask's outline in red.

    Args:
        stacks: ``(name, stack, mask)`` per stack; the mask is (I, J, K) on the stack's grid.
        path: A ``.png`` or ``.pdf`` file name; the suffix chooses the format.
        overwrite: Whether an existing file may be replaced.
        title: The page's title.

    Returns:
        The written path.

    Raises:
        ValueError: If the suffix is not ``.png`` or ``.pdf`` or there are no stacks.
        OutputExistsError: If the file exists and ``overwrite`` is false.
    """
    p = Path(path)
    if p.suffix not in FIGURE_SUFFIXES:
        raise ValueError(f"{p}: QA figures are written as .png or .pdf")
    if not stacks:
        raise ValueError("masks_figure(): no stacks to draw")
    check_output_path(p, overwrite)
    figure = Figure(figsize=(8.27, 2.7 * len(stacks) + 0.4), layout="constrained")
    FigureCanvasAgg(figure)
    figure.suptitle(title, fontsize=10)
    axes = figure.subplots(len(stacks), 3, squeeze=False)
    for row, (name, stack, mask) in enumerate(stacks):
        data = stack.data.detach().cpu().float().numpy()
        brain = mask.detach().cpu().numpy() > 0
        planes = np.nonzero(brain.any(axis=(0, 1)))[0]
        first, last = (planes[0], planes[-1]) if planes.size else (0, data.shape[2] - 1)
        vmax = float(np.percentile(data, 99.5)) or 1.0
        volume_ml = float(brain.sum() * stack.spacing.prod()) / 1000.0
        for col, fraction in enumerate((0.25, 0.5, 0.75)):
            k = round(first + fraction * (last - first))
            ax = axes[row, col]
            ax.imshow(data[:, :, k].T, cmap="gray", origin="lower", vmin=0.0, vmax=vmax)
            if brain[:, :, k].any():
                ax.contour(brain[:, :, k].T.astype(float), [0.5], colors="red", linewidths=0.8)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"k = {k}", fontsize=8)
            if col == 0:
                ax.set_ylabel(f"{Path(name).name}\n{volume_ml:.0f} ml", fontsize=8)
    buffer = io.BytesIO()
    figure.savefig(buffer, format=p.suffix[1:], dpi=100)
    return atomic_write_bytes(p, buffer.getvalue(), overwrite)
