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


__all__ = ["AcceptedPlan"]
