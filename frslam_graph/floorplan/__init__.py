"""Floor plans: the model (rooms, doors, walls), loaders (ours, R2V, room segmentation, HouseExpo)."""

from frslam_graph.floorplan.model import (
    ROOM_TYPES,
    Door,
    FloorPlan,
    Room,
    make_polygon,
    normalise_room_type,
)

__all__ = ["ROOM_TYPES", "Door", "FloorPlan", "Room", "make_polygon", "normalise_room_type"]
