"""The accepted registration of the floor plan and what was built from it (plan in map metres)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from frslam_graph.localisation.relocalisation import Relocaliser


@dataclass
class AcceptedPlan:
    """An accepted registration (``id`` tags its priors ``reloc:reg<id>``), the plan it puts in
    ``map`` (metres), the relocaliser on that plan and the share of the map its walls explained."""

    id: int
    registration: Any
    plan: Any  # FloorPlan in map metres
    relocaliser: Relocaliser
    map_fit: float

    def trusted(self, plan: Any) -> Any:
        """``plan`` (plan units) without the rooms the judge dropped from this registration (those
        whose walls the map had seen through): the rooms the accepted plan in ``map`` holds."""
        kept = [r.id for r in self.plan.rooms]
        return plan if len(kept) == len(plan.rooms) else plan.subset(kept)


__all__ = ["AcceptedPlan"]
