"""Floor-plan files: :func:`load` picks the reader from the file (or the ``reader`` named).

Readers, each in its own module and each building a :class:`~frslam_graph.floorplan.model.FloorPlan`:

- ``json``: our format (``FloorPlan.from_dict``, :mod:`frslam_graph.floorplan.model`); a JSON
  object with ``verts`` and no ``rooms`` is a ``houseexpo`` house
  (:mod:`frslam_graph.floorplan.houseexpo`);
- ``r2v``: an R2V vector plan ``.txt`` (:mod:`frslam_graph.floorplan.r2v`);
- ``roomseg``: a room-segmentation image (pixel value = room id) with its map_server YAML
  (:mod:`frslam_graph.floorplan.roomseg`);
- ``image``: a drawn plan image (:mod:`frslam_graph.floorplan.plan_image`).

``FloorPlan.load``, ``FloorPlan.from_image`` and ``FloorPlan.from_room_segmentation`` call
:func:`load` (the package installs it as ``FloorPlan.reader``: the readers build FloorPlans, so
the model does not import them).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from frslam_graph.errors import FloorPlanError
from frslam_graph.floorplan.houseexpo import load_houseexpo
from frslam_graph.floorplan.model import FloorPlan
from frslam_graph.floorplan.plan_image import load_image_plan
from frslam_graph.floorplan.r2v import load_r2v
from frslam_graph.floorplan.roomseg import from_room_segmentation, load_room_segmentation, yaml_beside
from frslam_graph.textfile import read_json

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm")  # plan images load reads
READERS = ("json", "r2v", "roomseg", "image")


def load(path: str | Path, *, reader: str | None = None, **options: Any) -> FloorPlan:
    """Load a plan. Without ``reader`` it is chosen from the file: our ``.json`` (or HouseExpo
    JSON with ``verts``), an R2V vector ``.txt``, a room-segmentation ``.png`` / ``.pgm`` (pixel
    value = room id; with ``yaml=`` the map_server YAML of its map, or one beside it:
    ``<stem>.yaml``, ``X.yaml`` for ``XRoomSeg.png``), or else a drawn plan image (``.png``,
    ``.jpg``, ``.pgm``). ``reader="image"`` / ``"roomseg"`` (``yaml=`` required) use that
    reader whatever the file's name; options go to the reader."""
    if reader == "image":
        return load_image_plan(path, **options)
    if reader == "roomseg":
        yaml = options.pop("yaml")
        return from_room_segmentation(path, yaml, **options)
    if reader is not None and reader not in READERS:
        raise FloorPlanError(
            f"unknown floor-plan reader {reader!r}; expected one of {list(READERS)}", source=str(path)
        )
    path = Path(path)
    if not path.exists():
        raise FloorPlanError("file not found", source=str(path))
    if path.is_dir():
        raise FloorPlanError("expected a floor-plan file, got a directory", source=str(path))
    suffix = path.suffix.lower()
    if reader == "json" or (reader is None and suffix == ".json"):
        data = read_json(path, FloorPlanError, "a JSON floor plan")
        if isinstance(data, Mapping) and "verts" in data and "rooms" not in data:
            return load_houseexpo(data, source=path)
        return FloorPlan.from_dict(data, source=path)
    if reader == "r2v" or (reader is None and suffix == ".txt"):
        return load_r2v(path, **options)
    if suffix in IMAGE_SUFFIXES:
        yaml_path = options.pop("yaml", None)
        if yaml_path is not None or (suffix in (".png", ".pgm") and yaml_beside(path)[0] is not None):
            return load_room_segmentation(path, yaml_path, **options)
        return load_image_plan(path, **options)
    raise FloorPlanError(
        f"unknown floor-plan file type {suffix!r} (expected .json, .txt (R2V) or an image: "
        f"{', '.join(IMAGE_SUFFIXES)})",
        source=str(path),
    )
