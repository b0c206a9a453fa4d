"""Rasterisation shared by registration, simulation and mapping.

A :class:`RasterFrame` ties pixels to a metric (or plan-unit) frame exactly like
``nav_msgs/OccupancyGrid``: pixel (row r, col c) covers ``x in [x0 + c*res, x0 + (c+1)*res)`` and
``y in [y0 + r*res, y0 + (r+1)*res)``: row 0 is the *lowest* y. Pixel centres are at
``(c + 0.5, r + 0.5)`` in continuous pixel coordinates returned by :meth:`RasterFrame.to_pixel`.

Polygons are filled by a vectorised scanline (winding numbers at pixel centres): a pixel is
inside exactly when its centre is, at any sub-pixel position, so areas are unbiased and masks
change smoothly with the transform (which registration refinement relies on).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
import shapely.geometry.polygon
from shapely.geometry import MultiPolygon, Polygon


@dataclass(frozen=True)
class RasterFrame:
    """Pixel grid over a frame: ``resolution`` units per pixel, ``origin`` = lower-left corner of
    pixel (0, 0), ``shape`` = (H, W); row 0 = lowest y."""

    resolution: float
    origin: tuple[float, float]
    shape: tuple[int, int]

    def __post_init__(self) -> None:
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"resolution must be positive, got {self.resolution}")
        h, w = self.shape
        if h <= 0 or w <= 0:
            raise ValueError(f"shape must be positive, got {self.shape}")

    @classmethod
    def around(
        cls, bounds: Sequence[float], resolution: float, margin: float = 0.0, max_pixels: int = 50_000_000
    ) -> RasterFrame:
        """A frame covering ``bounds`` = (minx, miny, maxx, maxy) plus ``margin`` on every side."""
        minx, miny, maxx, maxy = (float(b) for b in bounds)
        minx, miny, maxx, maxy = minx - margin, miny - margin, maxx + margin, maxy + margin
        w = max(1, int(np.ceil((maxx - minx) / resolution)))
        h = max(1, int(np.ceil((maxy - miny) / resolution)))
        if w * h > max_pixels:
            raise ValueError(
                f"raster of {h}x{w} pixels is too large (limit {max_pixels}); use a coarser resolution"
            )
        return cls(float(resolution), (minx, miny), (h, w))

    @property
    def height(self) -> int:
        return self.shape[0]

    @property
    def width(self) -> int:
        return self.shape[1]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(minx, miny, maxx, maxy) covered by the frame."""
        x0, y0 = self.origin
        return (x0, y0, x0 + self.width * self.resolution, y0 + self.height * self.resolution)

    def to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) frame coordinates -> (N, 2) continuous pixel coordinates (col, row)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return (xy - np.asarray(self.origin)) / self.resolution

    def to_world(self, colrow: np.ndarray) -> np.ndarray:
        """(N, 2) continuous pixel coordinates (col, row) -> frame coordinates."""
        colrow = np.asarray(colrow, dtype=np.float64).reshape(-1, 2)
        return colrow * self.resolution + np.asarray(self.origin)

    def pixel_matrix(self) -> np.ndarray:
        """3×3 affine mapping frame coordinates to continuous pixel coordinates."""
        r = self.resolution
        x0, y0 = self.origin
        return np.array([[1 / r, 0, -x0 / r], [0, 1 / r, -y0 / r], [0, 0, 1.0]])

    def scaled(self, factor: float) -> RasterFrame:
        """The same extent with ``factor`` times coarser pixels."""
        h = max(1, int(round(self.height / factor)))
        w = max(1, int(round(self.width / factor)))
        return RasterFrame(self.resolution * factor, self.origin, (h, w))


def _oriented_rings(geom, m: np.ndarray) -> list[np.ndarray]:
    """Rings of a (Multi)Polygon / (N, 2) array in continuous pixel coordinates, exterior
    counter-clockwise and holes clockwise, so that winding numbers add up correctly."""
    if isinstance(geom, np.ndarray):
        geom = Polygon(np.asarray(geom, dtype=np.float64).reshape(-1, 2))
    if geom is None or geom.is_empty:
        return []
    if isinstance(geom, MultiPolygon):
        return [r for g in geom.geoms for r in _oriented_rings(g, m)]
    if not isinstance(geom, Polygon):
        return []
    geom = shapely.geometry.polygon.orient(geom, sign=1.0)
    a, t = m[:2, :2], m[:2, 2]
    rings = [np.asarray(geom.exterior.coords)[:, :2]] + [np.asarray(h.coords)[:, :2] for h in geom.interiors]
    out = [r @ a.T + t for r in rings]
    if np.linalg.det(a) < 0:  # a reflection reverses orientation: restore exterior CCW
        out = [r[::-1] for r in out]
    return out


def _winding(rings: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """Winding number at every pixel centre (exact pixel-centre rule, vectorised scanline).

    Each edge crossing the horizontal line through row r's centres (y = r + 0.5, half-open in y)
    adds ±1 (by its direction) at the first column whose centre lies right of the crossing; a
    cumulative sum along the row gives the winding number at each centre.
    """
    h, w = shape
    if not rings:
        return np.zeros(shape, np.int32)
    p0 = np.concatenate([r[:-1] for r in rings])
    p1 = np.concatenate([r[1:] for r in rings])
    ylo, yhi = np.minimum(p0[:, 1], p1[:, 1]), np.maximum(p0[:, 1], p1[:, 1])
    r_start = np.clip(np.ceil(ylo - 0.5), 0, h).astype(np.int64)
    r_end = np.clip(np.ceil(yhi - 0.5), 0, h).astype(np.int64)
    counts = r_end - r_start
    keep = counts > 0
    if not keep.any():
        return np.zeros(shape, np.int32)
    p0, p1, r_start, counts = p0[keep], p1[keep], r_start[keep], counts[keep]
    edge = np.repeat(np.arange(len(counts)), counts)
    offsets = np.arange(len(edge)) - np.repeat(np.cumsum(counts) - counts, counts)
    rows = r_start[edge] + offsets
    yc = rows + 0.5
    x0, y0 = p0[edge, 0], p0[edge, 1]
    dx, dy = p1[edge, 0] - x0, p1[edge, 1] - y0
    x = x0 + (yc - y0) * dx / dy
    cols = np.clip(np.ceil(x - 0.5), 0, w).astype(np.int64)
    direction = np.where(dy > 0, 1, -1)
    delta = np.bincount(rows * (w + 1) + cols, weights=direction, minlength=h * (w + 1))
    return np.cumsum(delta.reshape(h, w + 1)[:, :w], axis=1).astype(np.int32)


def rasterise_polygons(
    polygons: Iterable[Polygon | MultiPolygon | np.ndarray],
    frame: RasterFrame,
    transform: np.ndarray | None = None,
    values: Sequence[int] | None = None,
) -> np.ndarray:
    """Fill polygons into an image of ``frame.shape``: a pixel is inside when its centre is.

    ``transform`` (3×3) maps polygon coordinates into the frame first. Without ``values`` the
    result is a uint8 mask (1 inside any polygon, holes cleared); with ``values`` an int32 label
    image where later polygons overwrite earlier ones.
    """
    m = frame.pixel_matrix()
    if transform is not None:
        m = m @ np.asarray(transform, dtype=np.float64)
    polygons = list(polygons)
    if values is None:
        rings = [r for p in polygons for r in _oriented_rings(p, m)]
        return (_winding(rings, frame.shape) != 0).astype(np.uint8)
    img = np.zeros(frame.shape, np.int32)
    for poly, value in zip(polygons, values, strict=True):
        inside = _winding(_oriented_rings(poly, m), frame.shape) != 0
        img[inside] = int(value)
    return img


def rasterise_plan(
    plan,  # FloorPlan (not imported: keeps this module free of the model)
    frame: RasterFrame,
    rooms: Iterable[str] | None = None,
    transform: np.ndarray | None = None,
    labels: bool = False,
) -> np.ndarray:
    """Rasterise a plan's rooms (all, or the ids in ``rooms``) into ``frame``.

    ``transform`` maps plan coordinates into the frame (e.g. a registration's ``matrix``).
    Returns a uint8 mask, or with ``labels=True`` an int32 image holding the 1-based index of
    each room in ``plan.rooms`` (0 outside).
    """
    keep = None if rooms is None else set(rooms)
    sel = [(i, r) for i, r in enumerate(plan.rooms) if keep is None or r.id in keep]
    polys = [r.polygon for _, r in sel]
    if labels:
        return rasterise_polygons(polys, frame, transform, values=[i + 1 for i, _ in sel])
    return rasterise_polygons(polys, frame, transform)
