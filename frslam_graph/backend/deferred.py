"""Deferred steps: a hook's work run one step per scan on the following scans (anytime).

A job is a generator (:mod:`frslam_graph.steps`): the work between two yields is one step. One
step runs per scan that is not a keyframe (keyframe scans have the graph update and the hooks),
jobs in the order they were deferred; :meth:`DeferredSteps.run_all` runs all that are pending (a
hook calls it before work that needs them done; ``finish`` and the offline run call it). The
schedule depends only on the sequence of scans, so results are deterministic whatever the timing.

Sharing the scan with loop closure: each ``yield`` may give the estimated cost (ms, a cost model
from the sizes involved, never a clock) of the step that ends there; the loop closer then gets the
rest of the scan's budget (``budget_ms``, ``loop_closure.budget_ms``; only steps that fit). A step
that yields None, or a job's last part when its last yield was None, takes the scan's whole
budget. A job whose last yield was a number ends with light glue: the next job's step runs on the
same scan.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from typing import Any


class DeferredSteps:
    """The queue of deferred jobs and the per-scan budget it shares with loop closure."""

    def __init__(self, budget_ms: float) -> None:
        self.budget_ms = budget_ms  # estimated ms of work per scan (cost model)
        self._jobs: deque[Iterator[Any]] = deque()
        self._head_costed = False  # the first job's last yield gave a cost
        self.steps_run = 0  # steps run so far (a hook that ran some made its scan busy)

    def defer(self, steps: Iterator[Any]) -> None:
        """Run ``steps`` (a generator: call the generator function) on the following scans."""
        if not isinstance(steps, Iterator):
            raise TypeError(
                f"defer() takes the steps as a generator (call the generator function), got "
                f"{type(steps).__name__}"
            )
        self._jobs.append(steps)

    @property
    def pending(self) -> int:
        """Number of deferred jobs not finished yet."""
        return len(self._jobs)

    def run_all(self) -> None:
        """Run every pending step now."""
        while self._jobs:
            self.step()

    def step(self) -> float | None:
        """Run the next step; its estimated cost (ms; inf when unknown), None when no job was
        pending."""
        while self._jobs:
            self.steps_run += 1
            try:
                cost = next(self._jobs[0])
            except StopIteration:
                self._jobs.popleft()
                costed, self._head_costed = self._head_costed, False
                if costed:
                    continue  # only glue after its last costed step: the next job's step runs
                return float("inf")
            self._head_costed = isinstance(cost, int | float) and not isinstance(cost, bool)
            return max(float(cost), 0.0) if self._head_costed else float("inf")
        return None


__all__ = ["DeferredSteps"]
