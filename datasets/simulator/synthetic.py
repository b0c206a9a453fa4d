"""Small synthetic floor plans (plan units, y up) for tests, demos and benchmarks.

``five_room_plan()``: a 200 × 160 unit flat: living room, kitchen, bedroom, corridor, bathroom,
joined by four doors (two more: the entrance, and a bedroom–corridor door).
"""

from __future__ import annotations

from shapely.geometry import box

from frslam_graph.floorplan import Door, FloorPlan, Room


def five_room_plan(name: str = "synthetic-five-rooms") -> FloorPlan:
    """Five rooms tiling a 200 × 160 rectangle, six doors (one to the outside)."""
    rooms = [
        Room("living", "living_room", box(0, 0, 120, 80)),
        Room("kitchen", "kitchen", box(120, 0, 200, 80)),
        Room("bedroom", "bedroom", box(0, 80, 80, 160)),
        Room("corridor", "corridor", box(80, 80, 120, 160)),
        Room("bathroom", "bathroom", box(120, 80, 200, 160)),
    ]
    doors = [
        Door("d0", (120.0, 30.0), (120.0, 50.0), ("living", "kitchen")),
        Door("d1", (90.0, 80.0), (110.0, 80.0), ("living", "corridor")),
        Door("d2", (120.0, 110.0), (120.0, 130.0), ("corridor", "bathroom")),
        Door("d3", (80.0, 120.0), (80.0, 140.0), ("corridor", "bedroom")),
        Door("d4", (20.0, 80.0), (40.0, 80.0), ("living", "bedroom")),
        Door("entrance", (40.0, 0.0), (60.0, 0.0), ("living",)),
    ]
    return FloorPlan(rooms=rooms, doors=doors, units="px", name=name)
