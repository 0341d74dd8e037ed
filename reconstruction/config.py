"""How a reconstruction runs: one dataclass per stage, grouped in :class:`ReconstructionConfig`.

Every field that a command-line option sets declares that option here (:func:`svr.options.option`):
the parser of ``svr reconstruct``, ``svr register`` and ``svr bids``, the message for a bad value
and the provenance record are made from these declarations. Defaults that depend on how the
slices start are not looked up by name anywhere: :meth:`ReconstructionConfig.preset` chooses
them once, where the command resolves its options, and every field holds its value explicitly.
Each configuration checks itself on construction (:class:`~svr.errors.ConfigFieldError` names the
field and what it accepts).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal, get_args

from svr.errors import ConfigFieldError
from svr.models.pretrained import SLICE_REFINER_STAGES
from svr.options import option
from svr.validation import (
    check_bool,
    check_choice,
    check_fraction,
    check_int,
    check_int_tuple,
    check_number,
    check_number_tuple,
    check_range,
)

__all__ = [
    "INITIALISATIONS",
    "LEARNED_STARTS",
    "SCHEDULES",
    "GridConfig",
    "InitialisationConfig",
    "OutlierConfig",
    "ReconstructionConfig",
    "ScheduleConfig",
    "SuperResolutionConfig",
]

INITIALISATIONS = ("scanner", "stack", "learned", "learned-slices", "atlas")
"""How the slices' poses start (:mod:`svr.reconstruction.initialisation`, one module each):
``"scanner"`` the scanner's poses; ``"stack"`` rigid stack registration to a template stack;
``"learned"`` every stack and packet placed in canonical space by the stack-pose network;
``"learned-slices"`` every slice predicted by a slice-pose network, made rigid per stack;
``"atlas"`` every stack placed by agreement with an atlas, no network."""

LEARNED_STARTS: tuple[str, ...] = ("learned", "learned-slices", "atlas")
"""The starts in canonical space, near the slices' final poses (their own schedule preset)."""

Schedule = Literal["adaptive", "fixed"]
SCHEDULES: tuple[str, ...] = get_args(Schedule)


@dataclass(frozen=True)
class GridConfig:
    """The output volume's grid.

    Attributes:
        resolution_mm: Isotropic voxel size of the output volume (mm).
    """

    resolution_mm: float = option(
        0.8, "--output-resolution", "isotropic voxel size of the output volume", metavar="MM"
    )

    def __post_init__(self) -> None:
        check_number("GridConfig", "resolution_mm", self.resolution_mm, gt=0)


@dataclass(frozen=True)
class InitialisationConfig:
    """How the slices' poses start, before slice-to-volume registration.

    Attributes:
        kind: One of :data:`INITIALISATIONS`.
        template: Index of the template stack of stack registration, or ``None`` for the stack
            with the most brain voxels.
        grid_mm: Voxel size (mm) of the volumes that stack registration registers to and that
            score each stack's candidate starts; ``None``: twice the output resolution.
        restart_deg: ``"learned"``: the turn (degrees) of six restarts of the network about each
            stack's chosen transform, averaged (0: none).
        slice_refinement: ``"learned"`` with an atlas: every slice moved by the shipped slice
            refiner against the atlas, kept where the other stacks agree better
            (:mod:`~svr.reconstruction.initialisation.slice_refinement`).
        slice_refiner_steps: Steps of each shipped refiner stage, in
            :data:`~svr.models.pretrained.SLICE_REFINER_STAGES`' order (``wide``, ``fine``), >= 0.
        slice_trajectory: With ``slice_refinement``: where the head was calm, the slices' poses
            are then put on their packets' motion trajectories
            (:mod:`~svr.reconstruction.initialisation.slice_refinement`).
        slice_max_deviation_deg: ``"learned-slices"``: a slice whose predicted rotation is
            farther than this (degrees) from its stack's consensus takes the consensus pose.
        slice_max_deviation_mm: ``"learned-slices"``: likewise for its slice centre (mm). Both
            bounds also define a slice's support for its stack's consensus.
        slice_min_support: ``"learned-slices"``: a stack whose fraction of supporting slices is
            below this keeps stack registration, in [0, 1].
    """

    kind: str = "stack"
    template: int | None = option(
        None,
        "--template",
        "template stack (0-based index) of stack registration",
        metavar="INDEX",
        default_text="the stack with the most brain voxels",
    )
    grid_mm: float | None = option(
        None,
        "--initialisation-resolution",
        "voxel size of the volumes that stack registration registers to and that score each "
        "stack's candidate starts",
        metavar="MM",
        default_text="twice --output-resolution",
    )
    restart_deg: float = option(
        0.0,
        "--restart-deg",
        "--registration cnn: the turn of six restarts of the stack-pose network about each "
        "stack's chosen pose, averaged (0: none)",
        metavar="DEG",
    )
    slice_refinement: bool = option(
        True,
        "--no-slice-refinement",
        "--registration cnn with an atlas: leave each slice at its packet's pose instead of "
        "moving it by the shipped slice refiner against the atlas (kept only where the other "
        "stacks agree)",
    )
    slice_refiner_steps: tuple[int, ...] = option(
        (4, 3),
        "--slice-refiner-steps",
        "--registration cnn with an atlas: steps of the slice refiner's wide stage, then its "
        "fine stage (more: slower, each step about 3 ms per slice on one core)",
        metavar="N",
    )
    slice_trajectory: bool = option(
        False,
        "--slice-trajectory",
        "--registration cnn with an atlas: where the head was calm (the stiffest motion "
        "trajectory predicts a left-out slice best), put each packet's refined slices on its "
        "trajectory",
    )
    slice_max_deviation_deg: float = 30.0
    slice_max_deviation_mm: float = 20.0
    slice_min_support: float = 0.5

    def __post_init__(self) -> None:
        owner = "InitialisationConfig"
        check_choice(owner, "kind", self.kind, INITIALISATIONS)
        check_int(owner, "template", self.template, minimum=0, allow_none=True)
        check_number(owner, "grid_mm", self.grid_mm, gt=0, allow_none=True)
        check_number(owner, "restart_deg", self.restart_deg, ge=0)
        check_bool(owner, "slice_refinement", self.slice_refinement)
        check_bool(owner, "slice_trajectory", self.slice_trajectory)
        steps = check_int_tuple(
            owner,
            "slice_refiner_steps",
            self.slice_refiner_steps,
            length=len(SLICE_REFINER_STAGES),
            minimum=0,
            allow_list=True,
        )
        object.__setattr__(self, "slice_refiner_steps", steps)
        for name in ("slice_max_deviation_deg", "slice_max_deviation_mm"):
            check_number(owner, name, getattr(self, name), gt=0)
        check_fraction(owner, "slice_min_support", self.slice_min_support)


@dataclass(frozen=True)
class ScheduleConfig:
    """How many rounds of (slice-to-volume registration, super-resolution) run, and how.

    Attributes:
        kind: ``"adaptive"``: registration rounds continue while the slices still move
            (:mod:`svr.reconstruction.convergence`), slices that have stopped moving sit out a
            round at a time, slices that still fit badly get a wider search, and the volume is
            reconstructed anew at the final poses. ``"fixed"``: exactly ``rounds`` rounds with the
            per-round settings (the schedule of release 0.1.0, reproduced bit for bit).
        rounds: ``"fixed"``: the number of rounds, registration skipped in the first.
            ``"adaptive"``: the most rounds, the first (super-resolution only) and the final one
            included.
        svr_levels: Resolution levels of slice-to-volume registration (coarse to fine).
        svr_iterations: Levenberg-Marquardt steps per level.
        group_sizes: Hierarchical registration: in round ``r`` (from 1) slices are registered in
            groups of ``group_sizes[r - 1]`` temporal neighbours, then one by one.
        min_slice_pixels: Slices with fewer brain pixels keep their group's pose instead of being
            registered one by one, and are never excluded by NCC.
        converged_deg: ``"adaptive"``: a slice whose rotation changed by more than this (degrees)
            in a round is still moving.
        converged_mm: ``"adaptive"``: likewise for the displacement of its centre (mm).
        converged_fraction: ``"adaptive"``: the slices have converged once at most this
            fraction of the registrable slices is still moving, in [0, 1).
        polish: ``"adaptive"``: the rounds go on after convergence until the slices also settle
            at the thresholds times this factor, in (0, 1] (or the cap ``rounds``); 1 stops at
            convergence. Whether the slices converged is still judged at the thresholds
            themselves, in the last registration round.
        recapture: ``"adaptive"``: from the second one-by-one round on, slices whose NCC is far
            below the others' get a wider search, at most twice each.
    """

    kind: Schedule = option(
        "adaptive",
        "--schedule",
        "adaptive: registration rounds continue while the slices still move (--converged-deg, "
        "--converged-mm), up to --iterations, then the volume is reconstructed anew at the final "
        "poses; fixed: exactly --iterations rounds (the schedule of release 0.1.0, reproduced bit "
        "for bit)",
    )
    rounds: int = option(
        16,
        "--iterations",
        "rounds of (slice-to-volume registration, super-resolution), no registration in the "
        "first: the most rounds of the adaptive schedule, the number of rounds of the fixed one",
        metavar="N",
        default_text="16; 24 with --registration cnn or atlas; 5 with --schedule fixed",
    )
    svr_levels: int = 3
    svr_iterations: int = option(
        6,
        "--svr-iterations",
        "optimiser steps per resolution level of slice-to-volume registration",
        metavar="N",
    )
    group_sizes: tuple[int, ...] = (4, 2)
    min_slice_pixels: int = 200
    converged_deg: float = option(
        0.3,
        "--converged-deg",
        "adaptive schedule: a slice whose rotation changes by more than this in a round is still "
        "moving; the rounds stop once at most 10%% of the slices are",
        metavar="DEG",
        default_text="0.3; 0.15 with --registration cnn or atlas, whose slices start near their "
        "place",
    )
    converged_mm: float = option(
        0.15,
        "--converged-mm",
        "adaptive schedule: likewise for the displacement of a slice's centre",
        metavar="MM",
        default_text="0.15; 0.075 with --registration cnn or atlas",
    )
    converged_fraction: float = 0.1
    polish: float = option(
        1.0,
        "--polish",
        "adaptive schedule: once converged, the rounds go on until the slices also settle at the "
        "thresholds times this factor, up to --iterations (1: stop at convergence); whether they "
        "converged is still judged at the thresholds themselves",
        metavar="F",
        default_text="1; 0.5 with --registration cnn or atlas",
    )
    recapture: bool = True

    def __post_init__(self) -> None:
        owner = "ScheduleConfig"
        check_choice(owner, "kind", self.kind, SCHEDULES)
        check_int(owner, "rounds", self.rounds, minimum=1)
        for name, minimum in (("svr_levels", 1), ("svr_iterations", 1), ("min_slice_pixels", 0)):
            check_int(owner, name, getattr(self, name), minimum=minimum)
        check_int_tuple(owner, "group_sizes", self.group_sizes, minimum=1)
        for name in ("converged_deg", "converged_mm"):
            check_number(owner, name, getattr(self, name), ge=0)
        check_fraction(owner, "converged_fraction", self.converged_fraction, include_one=False)
        check_number(owner, "polish", self.polish, gt=0, le=1)
        check_bool(owner, "recapture", self.recapture)


LEARNED_START_SCHEDULE = ScheduleConfig(
    rounds=24, converged_deg=0.15, converged_mm=0.075, polish=0.5
)
"""The adaptive schedule for starts near the final poses (:data:`LEARNED_STARTS`): the slices
reach "at most 10 % still moving" at the default thresholds early, before the slow last alignment
that is still worth having, so the thresholds are halved, the rounds polish on to half of those
and the cap is raised."""

FIXED_SCHEDULE = ScheduleConfig(kind="fixed", rounds=5)
"""The fixed schedule of release 0.1.0: five rounds."""


@dataclass(frozen=True)
class SuperResolutionConfig:
    """Edge-preserving conjugate-gradient super-resolution, per round.

    Attributes:
        iterations: Conjugate-gradient iterations per round (the last value repeats). The
            adaptive schedule uses the last value for its final round and the others, the last of
            them repeating, for the rounds before it.
        regularization: Weight of the edge-preserving regulariser per round, read as
            ``iterations``: strong while poses are rough, weaker at the end for detail.
        edge_delta: Intensity difference (normalised units) above which an edge is preserved.
        background_mm: Adaptive schedule: ``(inner, outer)`` distances from each slice's mask
            (mm, in the slice plane) between which pixels are observed as background; ``(0, 0)``
            for none.
    """

    iterations: tuple[int, ...] = option(
        (7, 7, 7, 7, 21),
        "--sr-iterations",
        "super-resolution (conjugate-gradient) iterations per round; the last value repeats",
        metavar="N",
    )
    regularization: tuple[float, ...] = option(
        (0.15, 0.15, 0.15, 0.1, 0.05),
        "--sr-regularization",
        "weight of super-resolution's edge-preserving regulariser per round, relative to the "
        "data; the last value repeats and makes the final volume (lower: sharper, noisier)",
        metavar="W",
    )
    edge_delta: float = 0.15
    background_mm: tuple[float, float] = (2.0, 5.0)

    def __post_init__(self) -> None:
        owner = "SuperResolutionConfig"
        check_int_tuple(owner, "iterations", self.iterations, minimum=1, allow_empty=False)
        check_number_tuple(owner, "regularization", self.regularization, ge=0, allow_empty=False)
        check_number(owner, "edge_delta", self.edge_delta, gt=0)
        check_range(owner, "background_mm", self.background_mm, ge=0)


@dataclass(frozen=True)
class OutlierConfig:
    """Which slices and pixels count, and how much.

    Attributes:
        robust: EM voxel- and slice-level outlier weights (Kuklisova-Murgasova).
        ncc_threshold: Slices whose NCC with their simulation is below this are excluded.
    """

    robust: bool = option(True, "--no-robust", "no EM outlier weights (voxel and slice level)")
    ncc_threshold: float = option(
        0.5,
        "--ncc-threshold",
        "slices whose NCC with their simulation is below this are excluded",
        metavar="NCC",
    )

    def __post_init__(self) -> None:
        check_bool("OutlierConfig", "robust", self.robust)
        check_number("OutlierConfig", "ncc_threshold", self.ncc_threshold, ge=-1, le=1)


@dataclass(frozen=True)
class ReconstructionConfig:
    """How a reconstruction runs (defaults follow NeSVoR's ``svr`` where the meaning is the same).

    Attributes:
        grid: The output grid.
        initialisation: How the slices' poses start.
        schedule: The rounds of registration and super-resolution.
        superres: Super-resolution.
        outliers: Outlier weights and exclusion.
        packets: Interleaved packets per stack (acquisition order ``k = 0, 2, 4, ..., 1, 3, ...``
            for 2; 1 for sequential): slices of one packet are registered in groups, and the
            ``"learned"`` start places each packet on its own.
        seed: Seed of the reconstruction's random draws, were a step to make any: every step is
            deterministic, and the pipeline neither reads nor changes torch's global generator.
    """

    grid: GridConfig = field(default_factory=GridConfig)
    initialisation: InitialisationConfig = field(default_factory=InitialisationConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    superres: SuperResolutionConfig = field(default_factory=SuperResolutionConfig)
    outliers: OutlierConfig = field(default_factory=OutlierConfig)
    packets: int = option(
        2,
        "--packets",
        "interleaved packets per stack: slices k = 0, N, 2N, ... were acquired in one sweep, then "
        "k = 1, N + 1, ..., and so on (1 for sequential acquisition). Slices are registered in "
        "groups of neighbours within a packet, and --registration cnn also places each packet on "
        "its own",
        metavar="N",
    )
    seed: int = 0

    def __post_init__(self) -> None:
        owner = "ReconstructionConfig"
        for name, kind in (
            ("grid", GridConfig),
            ("initialisation", InitialisationConfig),
            ("schedule", ScheduleConfig),
            ("superres", SuperResolutionConfig),
            ("outliers", OutlierConfig),
        ):
            if not isinstance(getattr(self, name), kind):
                raise ConfigFieldError(owner, name, f"a {kind.__name__}", getattr(self, name))
        check_int(owner, "packets", self.packets, minimum=1)
        check_int(owner, "seed", self.seed, minimum=0)

    @classmethod
    def preset(
        cls, initialisation: str = "stack", schedule: str = "adaptive"
    ) -> ReconstructionConfig:
        """The defaults for a start and a schedule: the one place that chooses them by name.

        Starts in canonical space (:data:`LEARNED_STARTS`) take
        :data:`LEARNED_START_SCHEDULE`; the fixed schedule takes :data:`FIXED_SCHEDULE`.

        Args:
            initialisation: One of :data:`INITIALISATIONS`.
            schedule: One of :data:`SCHEDULES`.

        Returns:
            The configuration with those defaults (change fields with :func:`dataclasses.replace`).

        Raises:
            ConfigFieldError: For an unknown start or schedule.
        """
        check_choice("ReconstructionConfig.preset", "schedule", schedule, SCHEDULES)
        rounds = (
            FIXED_SCHEDULE
            if schedule == "fixed"
            else LEARNED_START_SCHEDULE
            if initialisation in LEARNED_STARTS
            else ScheduleConfig()
        )
        return cls(initialisation=InitialisationConfig(kind=initialisation), schedule=rounds)

    @property
    def initialisation_grid_mm(self) -> float:
        """Voxel size (mm) of the initialisation's volumes: as given, else twice the output's."""
        given = self.initialisation.grid_mm
        return 2 * self.grid.resolution_mm if given is None else given

    def settings(self) -> dict[str, object]:
        """Every field, grouped as in the dataclasses (for logs and sidecars)."""
        return dataclasses.asdict(self)
