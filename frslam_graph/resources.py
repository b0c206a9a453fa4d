"""Paths of the small real data sets bundled with the package (``frslam_graph/data``)."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def bundled(relative: str) -> Path:
    """Path of a bundled file, e.g. ``bundled("prbonn/GMap.yaml")``."""
    path = Path(str(files("frslam_graph") / "data" / relative))
    if not path.exists():
        raise FileNotFoundError(f"bundled data file {relative!r} is missing from {path.parent}")
    return path
