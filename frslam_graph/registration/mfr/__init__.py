"""Our MFR registration of a floor plan to a partial occupancy map, one module per step.

1. :mod:`~frslam_graph.registration.mfr.map_side`: the partial map prepared (footprint, free
   space, wall-side cells, exits, wall directions, moments).
2. :mod:`~frslam_graph.registration.mfr.plan_side`: the plan prepared (rooms, boundary samples,
   room graph, distance rasters).
3. :mod:`~frslam_graph.registration.mfr.coarse`: IoU and wall agreement over (room subset,
   dihedral case, map direction) placements.
4. :mod:`~frslam_graph.registration.mfr.fine`: sub-pixel refinement and scoring of the best.

:mod:`~frslam_graph.registration.mfr.register` runs them in order (``register_mfr``, its options
in ``DEFAULTS``); :mod:`~frslam_graph.registration.mfr.geometry` holds what the steps share.
"""

from frslam_graph.registration.mfr.register import DEFAULTS, METHOD, register_mfr

__all__ = ["DEFAULTS", "METHOD", "register_mfr"]
