"""How well a registered plan explains the keyframe scans, each relocalised on its own.

Unlike the fit of the map (drawn at estimates the accepted plan's priors pulled onto it), the
scans are not biased towards the accepted plan: the judge compares placements with it and the
refiner weighs a refined scale with it. Scores are mean soft scores in [0, 1].
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from frslam_graph.localisation.relocalisation import Relocaliser

if TYPE_CHECKING:  # pragma: no cover
    from frslam_graph.backend.context import BackendContext


class ScanEvidence:
    """Up to ``samples`` keyframe scans spread evenly over the run, relocalised on a plan."""

    def __init__(self, samples: int, timings: dict[str, float]) -> None:
        self.samples = samples
        self.timings = timings  # seconds spent, by activity (diagnostics)

    def sample(self, n: int) -> np.ndarray:
        """Indices of up to ``samples`` of ``n`` keyframes spread evenly over the run."""
        return np.unique(np.linspace(0, n - 1, min(n, self.samples)).round().astype(np.intp))

    def fit(self, ctx: BackendContext, relocaliser: Relocaliser, n: int) -> float:
        """Mean soft score of the sampled keyframe scans (of the first ``n``), each relocalised on
        the plan in a window around its estimate; 0 without keyframes."""
        if not n:
            return 0.0
        ks = self.sample(n)
        scans = ctx.keyframe_scans()[0]
        t0 = time.perf_counter()
        soft = [relocaliser.relocalise(scans[k], ctx.keyframe(int(k)).pose_map).soft_score for k in ks]
        self.timings["relocalise"] += time.perf_counter() - t0
        return float(np.mean(soft))


__all__ = ["ScanEvidence"]
