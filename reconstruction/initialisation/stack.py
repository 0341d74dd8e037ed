"""The ``"stack"`` start: every stack registered rigidly to a template stack (scanner frame)."""

from __future__ import annotations

import logging

from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.initialisation.choice import Start
from svr.reconstruction.registration import stack_registration
from svr.reconstruction.slices import SliceSet

__all__ = ["stack_start"]

log = logging.getLogger(__name__)


def stack_start(slices: SliceSet, config: ReconstructionConfig) -> Start:
    """Every stack registered rigidly to a volume of the template stack.

    Args:
        slices: All slices, at their scanner poses.
        config: Settings (``initialisation.template`` and the initialisation grid).

    Returns:
        The slices at their registered poses, in the template stack's (scanner) frame.
    """
    poses, template = stack_registration(
        slices, config.initialisation_grid_mm, config.initialisation.template
    )
    log.info("stack registration to template stack %d", template)
    return Start(slices.with_poses(poses), ("stack",) * len(slices.stack_names))
