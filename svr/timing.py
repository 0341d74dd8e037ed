"""Wall time per named phase of a long run, logged as each phase ends."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["PhaseTimer"]

log = logging.getLogger(__name__)


class PhaseTimer:
    """Wall time per named phase; a phase entered again adds to its total.

    With ``steps``, each :meth:`phase` given a ``message`` is also announced as a numbered step
    (``[i/n] message``) when it starts, so a user sees how far a run is.

    Attributes:
        timings: Seconds per phase, in the order the phases first ran.
    """

    def __init__(self, steps: int | None = None, logger: logging.Logger | None = None) -> None:
        """Create a timer.

        Args:
            steps: The number of announced steps of the run, or ``None`` to announce none.
            logger: Where phases are logged (default this module's logger).
        """
        self.timings: dict[str, float] = {}
        self.steps = steps
        self.done = 0
        self.log = logger or log

    @contextmanager
    def phase(self, name: str, message: str | None = None) -> Iterator[None]:
        """Time the block as phase ``name``; announce it as the next step if ``message`` is given.

        Args:
            name: The phase's name (the key of :attr:`timings`).
            message: The step's announcement, with ``steps`` set; ``None`` logs only the time.
        """
        if message is not None and self.steps is not None:
            self.done += 1
            self.log.info("[%d/%d] %s", self.done, self.steps, message)
        start = time.perf_counter()
        yield
        elapsed = time.perf_counter() - start
        self.timings[name] = self.timings.get(name, 0.0) + elapsed
        if message is None:
            self.log.info("%s: %.1f s", name, elapsed)
