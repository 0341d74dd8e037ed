"""How the slices' poses start: one module per start, the shared per-stack choice beside them.

:func:`initialise` runs the start that ``config.initialisation.kind`` names
(:data:`svr.reconstruction.config.INITIALISATIONS`) and nothing else decides it:

========================  =================================================================
``"scanner"``             :mod:`~svr.reconstruction.initialisation.scanner`: the scanner's poses
``"stack"``               :mod:`~svr.reconstruction.initialisation.stack`: stack registration
``"learned"``             :mod:`~svr.reconstruction.initialisation.learned`: stacks and packets
                          placed by the stack-pose network
``"learned-slices"``      :mod:`~svr.reconstruction.initialisation.slice_model`: every slice
                          predicted by a slice-pose network, made rigid per stack
``"atlas"``               :mod:`~svr.reconstruction.initialisation.atlas`: stacks placed by
                          agreement with an atlas, no network
========================  =================================================================

The starts in canonical space share :mod:`~svr.reconstruction.initialisation.choice` (candidates
refined by stack registration, kept per stack only where they agree with the other stacks) and
estimate a stack's pose with :mod:`~svr.reconstruction.initialisation.stack_pose`.
"""

from __future__ import annotations

from collections.abc import Sequence

from svr.models.network import SlicePoseNet
from svr.models.stack_pose import StackPoseNet
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation.atlas import atlas_start
from svr.reconstruction.initialisation.choice import Start
from svr.reconstruction.initialisation.learned import learned_start
from svr.reconstruction.initialisation.scanner import scanner_start
from svr.reconstruction.initialisation.slice_model import slice_model_start
from svr.reconstruction.initialisation.stack import stack_start
from svr.reconstruction.slices import SliceSet, Stack
from svr.sampling.volume import CanonicalVolume

__all__ = ["Start", "initialise"]


def initialise(
    slices: SliceSet,
    stacks: Sequence[Stack],
    config: ReconstructionConfig,
    model: StackPoseNet | SlicePoseNet | None = None,
    atlases: Sequence[CanonicalVolume] = (),
) -> Start:
    """The slices' starting poses by the start ``config.initialisation.kind`` names.

    Args:
        slices: All slices, at their scanner poses.
        stacks: The stacks they were cut from (same order as ``slices.stack_names``).
        config: Settings.
        model: The network of a learned start: a stack-pose network for ``"learned"``, a
            slice-pose network (with ``model.config``) for ``"learned-slices"``; ``None`` else.
        atlases: Brains of about the fetus's age in canonical space, the preferred first (needed
            by ``"atlas"``; ``"learned"`` refines every slice against the first).

    Returns:
        The slices at their starting poses, and what each stack kept.

    Raises:
        ValueError: If the start needs a model of another kind, or atlases, than given.
    """
    kind = config.initialisation.kind
    if kind == "scanner":
        return scanner_start(slices)
    if kind == "stack":
        return stack_start(slices, config)
    if kind == "learned":
        if not isinstance(model, StackPoseNet):
            raise ValueError(_wrong_model(kind, "a stack-pose network (StackPoseNet)", model))
        return learned_start(slices, stacks, model, config, atlases[0] if atlases else None)
    if kind == "learned-slices":
        if not isinstance(model, SlicePoseNet):
            raise ValueError(_wrong_model(kind, "a slice-pose network (SlicePoseNet)", model))
        return slice_model_start(slices, stacks, model, config)
    if not atlases:
        raise ValueError("initialise(): the 'atlas' start needs 'atlases' (at least one)")
    return atlas_start(slices, stacks, atlases, config)


def _wrong_model(kind: str, expected: str, model: object) -> str:
    got = type(model).__name__
    return f"initialise(): the {kind!r} start needs {expected} as 'model', got {got}"
