"""MFR registration of a floor plan to an occupancy grid (plan coordinates -> map metres).

``register(plan, grid, method="mfr" | "paper")`` returns a :class:`Registration`; a failed or
meaningless match has ``ok == False`` and a ``reason`` (it never raises on a valid plan and grid).
"""

from frslam_graph.registration.api import METHODS, register
from frslam_graph.registration.result import Registration, matrix_from_params, params_from_matrix

__all__ = ["METHODS", "Registration", "matrix_from_params", "params_from_matrix", "register"]
