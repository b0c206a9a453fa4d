"""frslam: factor-graph 2D SLAM with floor-plan registration (FR-SLAM).

Public API (README.md, docs/design.md)::

    import frslam_graph as fr
    plan = fr.FloorPlan.load("plan.json")
    grid = fr.OccupancyGrid.load("map.yaml")
    reg = fr.register(plan, grid)
    rec = fr.open_recording("intel.clf.bz2")
    slam = fr.FRSlam(config=None, floor_plan=plan)
    result = fr.process(slam, rec)  # offline: the whole recording, LM batch at the end

Names are imported lazily so that ``import frslam_graph`` stays cheap and the sub-packages
(``frslam_graph.datasets``, ``frslam_graph.factors``) can import the model modules without cycles.
Units: metres, radians; frames: REP-103/105 (map, odom, base_link).
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "FloorPlan": "frslam_graph.floorplan",
    "Room": "frslam_graph.floorplan",
    "Door": "frslam_graph.floorplan",
    "OccupancyGrid": "frslam_graph.occupancy",
    "register": "frslam_graph.registration",
    "Registration": "frslam_graph.registration",
    "open_recording": "frslam_graph.datasets",
    "Scan": "frslam_graph.datasets",
    "FRSlam": "frslam_graph.slam",
    "process": "frslam_graph.offline",
    "SlamResult": "frslam_graph.offline",
    "FRSlamConfig": "frslam_graph.config",
    "FrslamError": "frslam_graph.errors",
    "FloorPlanError": "frslam_graph.errors",
    "MapError": "frslam_graph.errors",
    "RecordingError": "frslam_graph.errors",
    "ConfigError": "frslam_graph.errors",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'frslam_graph' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])


__all__ = sorted(_LAZY)
