"""``register(plan, grid, method=...)``: one entry point for every registration method.

``method="mfr"`` (default) is our MFR (coarse dihedral/subset search + sub-pixel refinement,
:mod:`frslam_graph.registration.mfr`); ``method="paper"`` is the paper-faithful MFR
(:mod:`frslam_graph.registration.paper`). Both return a :class:`Registration` mapping plan
coordinates to map metres. Modules are imported lazily so one method's import cost or failure
does not affect the other.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from frslam_graph.errors import ConfigError
from frslam_graph.registration.result import Registration

if TYPE_CHECKING:
    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.occupancy import OccupancyGrid

# method name -> (module, function)
METHODS: dict[str, tuple[str, str]] = {
    "mfr": ("frslam_graph.registration.mfr", "register_mfr"),
    "paper": ("frslam_graph.registration.paper", "register_paper"),
}


def register(plan: FloorPlan, grid: OccupancyGrid, *, method: str = "mfr", **options: Any) -> Registration:
    """Register ``plan`` to ``grid``; ``options`` go to the method (see its docstring).

    Raises :class:`~frslam_graph.errors.ConfigError` for an unknown method name; a failed match is
    a ``Registration`` with ``ok == False`` and a ``reason``; a match its method doubts (the paper
    mode's low IoU or near-tie) is ``ok`` with a ``doubt`` (``verdict == "doubtful"``).
    """
    if method not in METHODS:
        raise ConfigError(
            f"unknown registration method {method!r}; expected one of {sorted(METHODS)}", where="method"
        )
    module_name, func_name = METHODS[method]
    func = getattr(importlib.import_module(module_name), func_name)
    return func(plan, grid, **options)
