"""Library defaults and choices that the command-line help shows, as literals.

Building the ``svr`` parser imports no library module, so that ``svr --help`` does not wait for
torch: the defaults and choices that come from library configurations are copied here, each
under the name of the configuration field (or library constant) it copies, and
``tests/test_cli_light.py`` checks every one against the library.
"""

from __future__ import annotations

from typing import Any

SE3_ROTATIONS: tuple[str, ...] = ("rotvec", "6d")
"""The rotation outputs of the SE(3) head (:data:`svr.models.heads.SE3_ROTATIONS`)."""

SYMMETRY_MODES: tuple[str, ...] = ("none", "sagittal", "auto")
"""``--symmetry`` choices (:data:`svr.sampling.mirror_planes.SYMMETRY_MODES`)."""

SYMMETRY_THRESHOLD = 0.85
"""Brain correlation above which a volume counts as symmetric
(:data:`svr.sampling.mirror_planes.SYMMETRY_THRESHOLD`)."""

SIMULATION: dict[str, Any] = {
    "num_stacks": 3,
    "orientations": "orthogonal",
    "thickness_mm": 3.0,
    "in_plane_mm": 1.0,
    "interleave": 2,
    "slice_time_s": 1.5,
    "motion_scale": 1.0,
    "stack_turn_deg": (0.0, 0.0),
    "random_walk_rotation_deg": 5.0,
    "random_walk_translation_mm": 2.0,
    "noise": 0.02,
    "bias_field": 0.0,
    "signal_void_probability": 0.0,
}
"""Defaults of :class:`svr.sampling.simulate.SimulationConfig` fields (``svr simulate``)."""

STACK_POSE_MODEL: dict[str, Any] = {"head": "regress", "width": 16}
"""Defaults of :class:`svr.models.stack_pose.StackPoseConfig` fields."""

STACK_POSE_TRAINING: dict[str, Any] = {
    "steps": 23000,
    "learning_rate": 1e-3,
    "fine_tune_steps": 9000,
    "fine_tune_learning_rate": 3e-4,
    "fine_tune_seed": 2,
    "checkpoint_every": 250,
    "synthesis_fraction": 0.5,
}
"""Defaults of :class:`svr.models.stack_pose_train.StackPoseTrainingConfig` fields."""

SYNTHESIS_MODES: tuple[str, ...] = ("labels", "mixed")
"""``--synthesis`` choices besides ``none`` (:data:`svr.sampling.synthesis.SYNTHESIS_MODES`)."""

BRAIN_MASK_TRAINING: dict[str, Any] = {"cases": 100, "steps": 4000, "intensity_curves": 0.0}
"""Defaults of :class:`svr.masking.train.BrainMaskTrainingConfig` fields."""

MASKER_RECIPE: dict[str, Any] = {"segmenter_width": 8, "segmenter_context": 0}
"""Defaults of :class:`svr.masking.recipe.MaskerRecipe` fields (those of ``BrainMaskConfig()``)."""
