"""Floor plans: the model (rooms, doors, walls) and its readers (ours, R2V, room segmentation,
HouseExpo, drawn plan images).

- :mod:`~frslam_graph.floorplan.model`: ``FloorPlan``, ``Room``, ``Door``; our JSON schema.
- :mod:`~frslam_graph.floorplan.io`: ``load`` picks the reader from the file.
- readers: :mod:`~frslam_graph.floorplan.r2v`, :mod:`~frslam_graph.floorplan.houseexpo`,
  :mod:`~frslam_graph.floorplan.roomseg`, :mod:`~frslam_graph.floorplan.plan_image`.
- :mod:`~frslam_graph.floorplan.render`: drawing; :mod:`~frslam_graph.floorplan.openings`: open-plan
  boundaries.

The readers build FloorPlans, so the model does not import them: importing this package installs
:func:`frslam_graph.floorplan.io.load` as ``FloorPlan.reader``, which ``FloorPlan.load``,
``FloorPlan.from_image`` and ``FloorPlan.from_room_segmentation`` call.
"""

from frslam_graph.floorplan import io
from frslam_graph.floorplan.model import (
    ROOM_TYPES,
    Door,
    FloorPlan,
    Room,
    make_polygon,
    normalise_room_type,
)

FloorPlan.reader = staticmethod(io.load)

__all__ = ["ROOM_TYPES", "Door", "FloorPlan", "Room", "make_polygon", "normalise_room_type"]
