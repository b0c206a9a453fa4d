"""The accepted registration of the floor plan and what was built from it (plan in map metres)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from frslam_graph.localisation.relocalisation import Relocaliser, RelocaliserParams


@dataclass
class AcceptedPlan:
    """An accepted registration (``id`` tags its priors ``reloc:reg<id>``), the plan it puts in
    ``map`` (metres), the relocaliser on that plan (which ignores the wall pieces the judge found
    seen through, ``relocaliser.ignored``), the share of the map its walls explained and
    ``drawing_tol`` (m): how far the plan may be drawn off the building (the registration's
    own drawing tolerance; 0 for a plan accepted at the fixed structure tolerance)."""

    id: int
    registration: Any
    plan: Any  # FloorPlan in map metres
    relocaliser: Relocaliser
    map_fit: float
    drawing_tol: float = 0.0

    def __post_init__(self) -> None:
        # the relocaliser's covariances carry the plan's drawing error (RMS: half the tolerance,
        # which is twice the registration fit's RMS), so its priors are weighted by it
        self.relocaliser = self.relocaliser.drawn_off(0.5 * self.drawing_tol)

    def relocaliser_on(self, registration: Any, plan: Any, params: RelocaliserParams) -> Relocaliser:
        """The relocaliser of ``registration`` (a refinement of this one: plan -> map) of
        ``plan`` (plan units) with the rooms it trusts, ignoring the same wall pieces, moved
        with the plan."""
        rel = Relocaliser(registration.apply(self.trusted(plan)), params)
        if self.relocaliser.ignored is None:
            return rel
        pts, radius = self.relocaliser.ignored
        move = np.asarray(registration.matrix, float) @ np.linalg.inv(
            np.asarray(self.registration.matrix, float)
        )
        return rel.ignoring(pts @ move[:2, :2].T + move[:2, 2], radius)

    def trusted(self, plan: Any) -> Any:
        """``plan`` (plan units) without the rooms the judge dropped from this registration (those
        whose walls the map had seen through): the rooms the accepted plan in ``map`` holds."""
        kept = [r.id for r in self.plan.rooms]
        return plan if len(kept) == len(plan.rooms) else plan.subset(kept)


__all__ = ["AcceptedPlan"]


def runner_ups(registration: Any) -> list[dict]:
    """The registration's runner-up placements, best first (MFR's ``details["alternatives"]``:
    each with its ``matrix``, plan -> ``map``); [] when it carries none."""
    return list((getattr(registration, "details", None) or {}).get("alternatives", []))
