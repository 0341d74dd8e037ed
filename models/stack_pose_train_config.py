"""How the stack-pose network is trained (:func:`svr.models.stack_pose_train.train_stack_pose`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from svr.errors import ConfigFieldError
from svr.sampling.blocks import TrainingStackConfig
from svr.sampling.synthesis import SynthesisConfig
from svr.validation import check_fraction, check_instance, check_int, check_number

__all__ = ["StackPoseTrainingConfig"]


@dataclass(frozen=True)
class StackPoseTrainingConfig:
    """How the stack-pose network is trained.

    Attributes:
        steps: Optimiser steps, >= 1.
        stacks_per_step: Stacks simulated per step, >= 1.
        samples_per_stack: Blocks cut from each stack, >= 1.
        learning_rate: Adam's initial rate (cosine decay to 5 % of it).
        fine_tune_steps: The last steps of ``steps``, a second phase: the rate restarts at
            ``fine_tune_learning_rate`` (cosine decay to 5 % of it again) and the fine-tune
            volumes (``train_stack_pose``'s ``fine_tune_volumes``: the procedural phantoms)
            join the training brains. 0 for one phase; < ``steps``.
        fine_tune_learning_rate: Adam's rate at the start of the second phase.
        fine_tune_seed: An int: the second phase is the run that fine-tuning the first
            phase's weights with this seed would be (Adam's moments reset, the random stream
            reseeded with it, its rate ``fine_tune_learning_rate`` times the cosine as that
            run's own), to the last bit: the shipped model's recipe. ``None``: the second phase
            continues the first's random stream and Adam's moments (one schedule with a warm
            restart). Unused without a second phase.
        max_start_deg: Largest start error within reach (degrees).
        start_shift_mm: Per-axis standard deviation of the start's shift (mm).
        positive_fraction: Share of blocks within reach.
        subset_fraction: Share of blocks made of a packet or k neighbouring slices.
        max_subset: Largest k of the neighbouring-slice blocks.
        score_weight: Weight of the score's cross-entropy beside the pose loss.
        coords_weight: Weight of the coordinate loss (``"coords"`` head).
        checkpoint_every: Steps between checkpoints.
        seed: Seed of every random draw.
        stacks: The ranges the training stacks are drawn from.
        synthesis: How synthetic brains are made (label-map synthesis or the real image
            remapped, :class:`~svr.sampling.synthesis.SynthesisConfig`), or ``None`` for none
            (the draws of the runs before synthesis existed).
        synthesis_fraction: With ``synthesis``, the chance that a stack's brain is a synthetic
            copy (brains without tissue labels, the phantoms, are never synthetic).

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range.
    """

    steps: int = 23000
    stacks_per_step: int = 2
    samples_per_stack: int = 4
    learning_rate: float = 1e-3
    fine_tune_steps: int = 9000
    fine_tune_learning_rate: float = 3e-4
    fine_tune_seed: int | None = 2
    max_start_deg: float = 40.0
    start_shift_mm: float = 5.0
    positive_fraction: float = 0.65
    subset_fraction: float = 0.25
    max_subset: int = 12
    score_weight: float = 0.2
    coords_weight: float = 0.1
    checkpoint_every: int = 250
    seed: int = 0
    stacks: TrainingStackConfig = field(default_factory=TrainingStackConfig)
    synthesis: SynthesisConfig | None = None
    synthesis_fraction: float = 0.5

    def __post_init__(self) -> None:
        owner = "StackPoseTrainingConfig"
        for name in (
            "steps",
            "stacks_per_step",
            "samples_per_stack",
            "checkpoint_every",
            "max_subset",
        ):
            check_int(owner, name, getattr(self, name), minimum=1)
        for name in ("positive_fraction", "subset_fraction"):
            check_fraction(owner, name, getattr(self, name))
        for name in ("learning_rate", "fine_tune_learning_rate", "max_start_deg"):
            check_number(owner, name, getattr(self, name), gt=0)
        check_int(owner, "fine_tune_steps", self.fine_tune_steps, minimum=0)
        if self.fine_tune_steps >= self.steps:
            raise ConfigFieldError(
                owner,
                "fine_tune_steps",
                f"< steps ({self.steps}; 0 for one phase)",
                self.fine_tune_steps,
            )
        for name in ("start_shift_mm", "score_weight", "coords_weight"):
            check_number(owner, name, getattr(self, name), ge=0)
        check_int(owner, "seed", self.seed)
        check_int(owner, "fine_tune_seed", self.fine_tune_seed, allow_none=True)
        check_instance(owner, "stacks", self.stacks, TrainingStackConfig)
        check_instance(owner, "synthesis", self.synthesis, SynthesisConfig, allow_none=True)
        check_fraction(owner, "synthesis_fraction", self.synthesis_fraction)

    @property
    def turn(self) -> int:
        """The first step of the second phase (``steps`` without one)."""
        return self.steps - self.fine_tune_steps

    @property
    def second_phase_is_new_run(self) -> bool:
        """Whether the second phase runs as a separate fine-tuning run (``fine_tune_seed``)."""
        return self.fine_tune_seed is not None and self.fine_tune_steps > 0
