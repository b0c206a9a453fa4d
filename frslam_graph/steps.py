"""Work split into steps (anytime scheduling of the backend's deferred work).

A piece of work is a generator: each ``next()`` runs one bounded step; the generator's return
value (``StopIteration.value``) is the result. The caller decides how many steps to run per scan
(:class:`~frslam_graph.backend.deferred.DeferredSteps`, the loop closer's budget); the result
does not depend on it. Each yield gives the estimated cost (ms) of the step that ends there, from
the sizes involved (never a clock), so steps are packed into a per-scan budget deterministically;
a yield of None means "unknown: give it the scan's whole budget". The code between yields outside
these steps is light glue (well under a millisecond).
"""

from __future__ import annotations

from collections.abc import Generator
from typing import TypeVar

T = TypeVar("T")
Steps = Generator[float | None, None, T]


def run_steps(steps: Steps[T]) -> T:
    """Run a step generator to the end (all its steps now); returns its result."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value


__all__ = ["Steps", "run_steps"]
