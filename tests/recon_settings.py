"""Reconstruction settings for tests, written as a list of the fields a test changes."""

from __future__ import annotations

import dataclasses

from svr.reconstruction.config import ReconstructionConfig

# Field name -> its group in ReconstructionConfig (None: a field of ReconstructionConfig itself).
GROUP = {
    "resolution_mm": "grid",
    "kind": "initialisation",
    "template": "initialisation",
    "grid_mm": "initialisation",
    "restart_deg": "initialisation",
    "slice_max_deviation_deg": "initialisation",
    "slice_max_deviation_mm": "initialisation",
    "slice_min_support": "initialisation",
    "rounds": "schedule",
    "svr_levels": "schedule",
    "svr_iterations": "schedule",
    "group_sizes": "schedule",
    "min_slice_pixels": "schedule",
    "converged_deg": "schedule",
    "converged_mm": "schedule",
    "converged_fraction": "schedule",
    "polish": "schedule",
    "recapture": "schedule",
    "iterations": "superres",
    "regularization": "superres",
    "edge_delta": "superres",
    "background_mm": "superres",
    "robust": "outliers",
    "ncc_threshold": "outliers",
    "packets": None,
    "seed": None,
}


def recon_config(
    start: str = "stack", schedule: str = "adaptive", **fields
) -> ReconstructionConfig:
    """The preset of ``start`` and ``schedule`` with ``fields`` (any group's) set.

    Args:
        start: The start's kind (:data:`svr.reconstruction.config.INITIALISATIONS`).
        schedule: ``"adaptive"`` or ``"fixed"``.
        fields: Field names of any group (``rounds=3``, ``ncc_threshold=0.2``, ...).
    """
    config = ReconstructionConfig.preset(start, schedule)
    groups: dict[str | None, dict] = {}
    for name, value in fields.items():
        groups.setdefault(GROUP[name], {})[name] = value
    top = groups.pop(None, {})
    changed = {
        group: dataclasses.replace(getattr(config, group), **values)
        for group, values in groups.items()
    }
    return dataclasses.replace(config, **changed, **top)
