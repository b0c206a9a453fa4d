"""Open boundaries of a floor plan: where two rooms meet without a wall (plan units).

Plans drawn with wall segments (R2V) split an open space (a living-dining-kitchen) into labelled
rooms without a wall between them. Whoever turns the plan into geometry (the simulator's true
house, the relocaliser's distance field) must leave those boundaries open, not invent a wall.
The plan must be in metres (``registration.apply(plan)`` or ``plan.transformed(m, units="m")``):
the tolerances below are metric.
"""

from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import Polygon

_CRACK = 0.01  # m: rooms closer than twice this count as touching


def open_boundaries(
    plan, wall_thickness: float, min_opening: float = 0.5
) -> tuple[list[Polygon], list[tuple[str, str]]]:
    """Openings where two rooms share a boundary that no plan wall (or door) runs along.

    Plans with wall segments (R2V) sometimes split one open space into rooms without a wall
    between them (a living-dining-kitchen); building a wall there would invent one. Stretches
    of shared boundary at least ``min_opening`` metres long and farther than a tolerance (1 %
    of the house diagonal, at least 0.1 m) from every wall and door segment are left open.
    Plans without walls keep every boundary as a wall. Returns (opening polygons, room pairs).
    """
    if plan.walls is None or len(plan.walls) == 0 or len(plan.rooms) < 2:
        return [], []
    lines = [shapely.LineString([w[:2], w[2:]]) for w in plan.walls if np.hypot(*(w[2:] - w[:2])) > 0]
    lines += [shapely.LineString([d.a, d.b]) for d in plan.doors if d.width > 0]
    minx, miny, maxx, maxy = plan.bounds
    tol = max(0.1, 0.01 * math.hypot(maxx - minx, maxy - miny))
    supported = shapely.union_all(lines).buffer(tol)
    polys = [r.polygon for r in plan.rooms]
    # rooms that share a boundary in the drawing may not touch exactly once transformed (a
    # hairline crack between two diagonal edges): close cracks narrower than 2 * _CRACK first,
    # or eroding the union would cut the shared boundary out of the interior
    inner = shapely.union_all([p.buffer(_CRACK, join_style="mitre") for p in polys]).buffer(
        -tol / 2.0 - _CRACK, join_style="mitre"
    )
    tree = shapely.STRtree(polys)
    openings, pairs = [], []
    for i, a in enumerate(plan.rooms):
        for j in tree.query(a.polygon, predicate="dwithin", distance=tol):
            if j <= i:
                continue
            b = plan.rooms[int(j)]
            shared = a.polygon.boundary.intersection(b.polygon.buffer(tol / 2.0))
            if shared.is_empty or shared.length < min_opening:
                continue
            # Only interior boundaries: never open an outer wall where two rooms' edges coincide.
            bare = shared.difference(supported).intersection(inner)
            if bare.is_empty:
                continue
            merged = shapely.line_merge(bare) if bare.geom_type == "MultiLineString" else bare
            pieces = [g for g in shapely.get_parts(merged) if g.length >= min_opening]
            if not pieces:
                continue
            openings += [g.buffer(wall_thickness / 2.0 + 0.05, cap_style="flat") for g in pieces]
            pairs.append((a.id, b.id))
    return openings, pairs


__all__ = ["open_boundaries"]
