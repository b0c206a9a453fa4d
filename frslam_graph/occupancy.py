"""2D occupancy grid in the ROS map_server / nav_msgs/OccupancyGrid convention.

``data`` is int8 (H, W): -1 unknown, 0 free, 100 occupied (values in between are occupancy
probabilities in percent). Row 0 is the *lowest* y (as in nav_msgs), so the image written to
disk is flipped vertically. ``origin`` = (x, y, yaw) of the lower-left corner of cell (0, 0) in
the ``map`` frame; ``resolution`` in metres per cell.

Files follow map_server: a YAML (``image``, ``resolution``, ``origin``, ``negate``,
``occupied_thresh``, ``free_thresh``, optional ``mode``: trinary | scale | raw) and a PGM/PNG
image. Loading applies map_server's rules (p = (255 - v) / 255, or v / 255 when negated;
p > occupied_thresh -> occupied, p < free_thresh -> free, otherwise unknown). An image without a
YAML is read by the same rules with the resolution and origin given (:meth:`OccupancyGrid.from_image`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from frslam_graph.atomic import write_bytes, write_text
from frslam_graph.errors import FrslamError, MapError
from frslam_graph.image_files import grey_levels, read_image
from frslam_graph.limits import short_repr
from frslam_graph.raster import RasterFrame
from frslam_graph.se2 import rot, to_matrix
from frslam_graph.textfile import read_yaml

UNKNOWN, FREE, OCCUPIED = -1, 0, 100
IMAGE_SUFFIXES = (".png", ".pgm", ".jpg", ".jpeg")  # map images OccupancyGrid.load reads without a YAML


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """Occupancy grid: int8 ``data`` (H, W), ``resolution`` m/cell, ``origin`` (x, y, yaw)."""

    data: np.ndarray
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source: str | None = None

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        if data.ndim != 2 or data.shape[0] == 0 or data.shape[1] == 0:
            raise MapError(f"data must be a non-empty 2D array, got shape {data.shape}", self.source, "data")
        if data.dtype != np.int8:
            if not np.all((data >= -1) & (data <= 100)):
                raise MapError("cell values must be -1 (unknown) or 0..100", self.source, "data")
            data = data.astype(np.int8)
        object.__setattr__(self, "data", data)
        res = self.resolution
        if isinstance(res, bool) or not isinstance(res, int | float) or not math.isfinite(res) or res <= 0:
            raise MapError(
                f"must be a positive number of metres per cell, got {short_repr(res)}",
                self.source,
                "resolution",
            )
        object.__setattr__(self, "resolution", float(res))
        origin = tuple(float(v) for v in self.origin)
        if len(origin) == 2:
            origin = (*origin, 0.0)
        if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
            raise MapError(
                f"must be [x, y, yaw] finite numbers, got {short_repr(self.origin)}", self.source, "origin"
            )
        object.__setattr__(self, "origin", origin)

    # ------------------------------------------------------------------ shape & masks
    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def free_mask(self) -> np.ndarray:
        """Bool (H, W): known free cells (value 0..49)."""
        return (self.data >= 0) & (self.data < 50)

    def occupied_mask(self) -> np.ndarray:
        """Bool (H, W): occupied cells (value >= 50)."""
        return self.data >= 50

    def unknown_mask(self) -> np.ndarray:
        return self.data < 0

    @property
    def frame(self) -> RasterFrame:
        """The grid's pixel frame (ignores yaw; see :meth:`map_from_grid` for the full transform)."""
        return RasterFrame(self.resolution, (self.origin[0], self.origin[1]), self.shape)

    def map_from_grid(self) -> np.ndarray:
        """3×3 transform from the grid's unrotated frame (origin at cell (0,0) corner) to ``map``."""
        return to_matrix(self.origin)

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) map coordinates -> (N, 2) continuous cell coordinates (col, row); centres at +0.5."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        x, y, yaw = self.origin
        d = xy - (x, y)
        if yaw != 0.0:
            d = d @ rot(yaw)  # rotate by -yaw
        return d / self.resolution

    def cell_to_world(self, colrow: np.ndarray) -> np.ndarray:
        """(N, 2) continuous cell coordinates (col, row) -> map coordinates."""
        colrow = np.asarray(colrow, dtype=np.float64).reshape(-1, 2)
        d = colrow * self.resolution
        x, y, yaw = self.origin
        if yaw != 0.0:
            d = d @ rot(yaw).T  # rotate by +yaw
        return d + (x, y)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_masks(
        cls,
        free: np.ndarray,
        occupied: np.ndarray,
        resolution: float,
        origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> OccupancyGrid:
        """Grid from bool masks (row 0 = lowest y); occupied wins over free; the rest unknown."""
        data = np.full(np.shape(free), UNKNOWN, np.int8)
        data[np.asarray(free, bool)] = FREE
        data[np.asarray(occupied, bool)] = OCCUPIED
        return cls(data, resolution, origin)

    def crop_to_known(self, margin_cells: int = 2) -> OccupancyGrid:
        """The smallest sub-grid holding every known cell, plus a margin (origin adjusted)."""
        known = ~self.unknown_mask()
        if not known.any():
            return self
        rows = np.flatnonzero(known.any(axis=1))
        cols = np.flatnonzero(known.any(axis=0))
        r0, r1 = max(0, rows[0] - margin_cells), min(self.height, rows[-1] + 1 + margin_cells)
        c0, c1 = max(0, cols[0] - margin_cells), min(self.width, cols[-1] + 1 + margin_cells)
        corner = self.cell_to_world(np.array([[c0, r0]]))[0]
        return OccupancyGrid(
            self.data[r0:r1, c0:c1].copy(),
            self.resolution,
            (corner[0], corner[1], self.origin[2]),
            self.source,
        )

    # ------------------------------------------------------------------ files
    @classmethod
    def load(
        cls, yaml_path: str | Path, resolution: float | None = None, **image_options: Any
    ) -> OccupancyGrid:
        """Read a map_server YAML and its image; or, for an image (``.png``, ``.pgm``, ``.jpg``)
        given with ``resolution`` (metres per pixel), :meth:`from_image` with ``image_options``."""
        yaml_path = Path(yaml_path)
        src = str(yaml_path)
        if yaml_path.suffix.lower() in IMAGE_SUFFIXES:
            if resolution is None:
                raise MapError(
                    "an image map without a map_server YAML needs its resolution in metres per pixel: "
                    "give it with --resolution",
                    src,
                )
            return cls.from_image(yaml_path, resolution, **image_options)
        if resolution is not None or image_options:
            raise MapError(
                "a map_server YAML states its own resolution, origin and thresholds; "
                "a resolution (and the image options) is only for an image map without a YAML",
                src,
                "resolution" if resolution is not None else None,
            )
        meta = read_yaml(yaml_path, MapError, "a map_server YAML with image, resolution, origin")
        if not isinstance(meta, dict):
            raise MapError("expected a YAML mapping with image, resolution, origin", src)
        for key in ("image", "resolution", "origin"):
            if key not in meta:
                raise MapError("missing required field", src, key)
        resolution = _number(meta["resolution"], src, "resolution", positive=True)
        origin = meta["origin"]
        if not isinstance(origin, list | tuple) or len(origin) not in (2, 3):
            raise MapError(f"expected [x, y, yaw], got {short_repr(origin)}", src, "origin")
        origin = tuple(_number(v, src, f"origin[{i}]") for i, v in enumerate(origin))
        negate = int(_number(meta.get("negate", 0), src, "negate"))
        occ_t = _number(meta.get("occupied_thresh", 0.65), src, "occupied_thresh")
        free_t = _number(meta.get("free_thresh", 0.196), src, "free_thresh")
        mode = str(meta.get("mode", "trinary"))
        check_reading(occ_t, free_t, mode, src)
        image_path = Path(str(meta["image"]))
        if not image_path.is_absolute():
            image_path = yaml_path.parent / image_path
        img = _read_image(image_path, src)
        data = image_to_occupancy(img, negate, occ_t, free_t, mode)
        return cls(np.flipud(data).copy(), resolution, origin, src)

    @classmethod
    def from_image(
        cls,
        path: str | Path,
        resolution: float,
        origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
        negate: bool = False,
        occupied_thresh: float = 0.65,
        free_thresh: float = 0.196,
        mode: str = "trinary",
    ) -> OccupancyGrid:
        """A map image without a YAML, read as ROS map_server reads one: ``resolution`` metres
        per pixel, ``origin`` (x, y, yaw) of the lower-left corner of the image's bottom-left
        pixel; image row 0 (the top) is the highest y, so the grid's row 0 is the image's last
        row. Dark is occupied, light free, in between unknown (``negate`` swaps dark and light;
        thresholds and ``mode`` as in a map_server YAML)."""
        src = str(path)
        check_reading(occupied_thresh, free_thresh, mode, src)
        img = grey_levels(read_image(path, MapError, "an occupancy map image"))
        data = image_to_occupancy(img, int(bool(negate)), occupied_thresh, free_thresh, mode)
        return cls(np.flipud(data).copy(), resolution, origin, src)

    def save(self, yaml_path: str | Path, image_format: str = "pgm") -> Path:
        """Write a trinary map_server map: ``<name>.yaml`` + ``<name>.pgm`` (0 occupied, 254 free,
        205 unknown), as ROS map_saver does, each file atomically. Returns the YAML path."""
        yaml_path = Path(yaml_path)
        if image_format not in ("pgm", "png"):
            raise ValueError(f"image_format must be 'pgm' or 'png', got {image_format!r}")
        yaml_path.parent.mkdir(parents=True, exist_ok=True)
        image_path = yaml_path.with_suffix(f".{image_format}")
        img = np.full(self.shape, 205, np.uint8)
        img[self.free_mask()] = 254
        img[self.occupied_mask()] = 0
        ok, encoded = cv2.imencode(f".{image_format}", np.flipud(img))
        if not ok:
            raise MapError("could not encode the map image", str(image_path))
        write_bytes(image_path, encoded.tobytes())
        meta: dict[str, Any] = {
            "image": image_path.name,
            "resolution": float(self.resolution),
            "origin": [float(v) for v in self.origin],
            "negate": 0,
            "occupied_thresh": 0.65,
            "free_thresh": 0.196,
            "mode": "trinary",
        }
        write_text(yaml_path, yaml.safe_dump(meta, sort_keys=False))
        return yaml_path

    def __repr__(self) -> str:
        counts = f"free={int(self.free_mask().sum())} occ={int(self.occupied_mask().sum())}"
        return f"OccupancyGrid({self.height}x{self.width}, res={self.resolution} m, origin={self.origin}, {counts})"


def _number(value: Any, src: str, field: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise MapError(f"expected a finite number, got {short_repr(value)}", src, field)
    if positive and value <= 0:
        raise MapError(f"expected a positive number, got {short_repr(value)}", src, field)
    return float(value)


def check_reading(
    occ_t: float, free_t: float, mode: str, src: str, error: type[FrslamError] = MapError
) -> None:
    """Raise ``error`` naming ``src`` unless 0 <= free_t <= occ_t <= 1 and ``mode`` is a
    map_server mode (trinary, scale, raw)."""
    for field, value in (("occupied_thresh", occ_t), ("free_thresh", free_t)):
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise error(f"expected a finite number, got {short_repr(value)}", src, field)
    if not (0.0 <= free_t <= occ_t <= 1.0):
        raise error(f"need 0 <= free_thresh ({free_t}) <= occupied_thresh ({occ_t}) <= 1", src, "free_thresh")
    if mode not in ("trinary", "scale", "raw"):
        raise error(f"unknown mode {short_repr(mode)} (expected trinary, scale or raw)", src, "mode")


def _read_image(path: Path, src: str) -> np.ndarray:
    """Grey levels of a YAML's image; errors name the YAML and the image."""
    if not path.is_file():
        raise MapError(f"the YAML's image {str(path)!r} does not exist", src, "image")
    try:
        return grey_levels(read_image(path, MapError, "a map image"))
    except MapError as err:
        raise MapError(f"{str(path)!r}: {err.message}", src, "image") from None


def image_to_occupancy(img: np.ndarray, negate: int, occ_t: float, free_t: float, mode: str) -> np.ndarray:
    """int8 occupancy (-1, 0..100) of grey levels 0..255 by map_server's rules, image rows as given."""
    if mode == "raw":
        out = np.clip(img, 0, 255)
        out = np.where(out > 100, -1, out)
        return out.astype(np.int8)
    p = img / 255.0 if negate else (255.0 - img) / 255.0
    data = np.full(img.shape, UNKNOWN, np.int8)
    if mode == "trinary":
        data[p > occ_t] = OCCUPIED
        data[p < free_t] = FREE
    else:  # scale
        mid = (p >= free_t) & (p <= occ_t)
        data[p > occ_t] = OCCUPIED
        data[p < free_t] = FREE
        scaled = np.round(99.0 * (p - free_t) / max(occ_t - free_t, 1e-9)).astype(np.int16)
        data[mid] = np.clip(scaled[mid], 0, 100).astype(np.int8)
        # map_server scale mode: intermediate values are probabilities; 205-grey stays unknown
        data[img == 205] = UNKNOWN
    return data
