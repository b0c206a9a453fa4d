"""Label image -> shapely polygons with exact pixel-edge boundaries, and geodesic region growing
(shared by the raster plan loaders).

Pixel (col c, row r) is the unit square [c, c+1] x [r, r+1] in *image* coordinates (x right,
y = row, down). Each label's pixels are cut into horizontal runs, the runs become boxes and the
boxes of one label are merged (their union is exact, so areas equal pixel counts), then
simplified by Douglas-Peucker with a small tolerance, which removes the staircase of slanted
edges and keeps right-angle corners. Callers map image coordinates to their plan frame.
"""

from __future__ import annotations

import cv2
import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon


def label_runs(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Horizontal runs of equal non-zero labels: (label, row, col_start, col_end_exclusive)."""
    lab = np.asarray(labels)
    h, w = lab.shape
    padded = np.zeros((h, w + 2), dtype=lab.dtype)
    padded[:, 1:-1] = lab
    change = padded[:, 1:] != padded[:, :-1]  # (h, w+1): a run boundary before column j
    rows, cols = np.nonzero(change)
    # consecutive boundaries in the same row delimit runs [cols[i], cols[i+1])
    same_row = rows[:-1] == rows[1:]
    r = rows[:-1][same_row]
    c0 = cols[:-1][same_row]
    c1 = cols[1:][same_row]
    val = lab[r, c0]
    keep = val != 0
    return val[keep], r[keep], c0[keep], c1[keep]


def merge_runs(rows: np.ndarray, c0: np.ndarray, c1: np.ndarray) -> tuple[np.ndarray, ...]:
    """Merge runs with the same columns in consecutive rows into rectangles (r0, r1, c0, c1)."""
    if len(rows) == 0:
        return rows, rows, c0, c1
    order = np.lexsort((rows, c1, c0))
    r, a, b = rows[order], c0[order], c1[order]
    new = np.ones(len(r), dtype=bool)
    new[1:] = (a[1:] != a[:-1]) | (b[1:] != b[:-1]) | (r[1:] != r[:-1] + 1)
    start = np.flatnonzero(new)
    end = np.r_[start[1:], len(r)] - 1
    return r[start], r[end] + 1, a[start], b[start]


def largest_polygon(geom: shapely.Geometry) -> Polygon | None:
    """The largest polygon of a (multi)polygon / collection, or None when there is none."""
    if geom is None or geom.is_empty:
        return None
    if isinstance(geom, Polygon):
        return geom
    parts = [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon | MultiPolygon)]
    polys = []
    for p in parts:
        polys.extend(p.geoms if isinstance(p, MultiPolygon) else [p])
    if not polys:
        return None
    return max(polys, key=lambda p: p.area)


def labels_to_polygons(
    labels: np.ndarray, ids: np.ndarray | None = None, simplify: float = 0.0
) -> dict[int, shapely.Geometry]:
    """Polygon (or MultiPolygon for disconnected labels) of each non-zero label, image coordinates.

    ``simplify`` is the Douglas-Peucker tolerance in pixels (0: exact pixel edges). Topology is
    preserved per label (no self-intersections, holes kept).
    """
    val, r, c0, c1 = label_runs(labels)
    if ids is not None:
        sel = np.isin(val, ids)
        val, r, c0, c1 = val[sel], r[sel], c0[sel], c1[sel]
    out: dict[int, shapely.Geometry] = {}
    if len(val) == 0:
        return out
    order = np.argsort(val, kind="stable")
    val, r, c0, c1 = val[order], r[order], c0[order], c1[order]
    uniq, first = np.unique(val, return_index=True)
    bounds = np.r_[first, len(val)]
    for k, lab in enumerate(uniq):
        s = slice(bounds[k], bounds[k + 1])
        r0, r1, a, b = merge_runs(r[s], c0[s], c1[s])
        boxes = shapely.box(a, r0, b, r1)
        geom = shapely.union_all(boxes)
        if simplify > 0:
            geom = geom.simplify(simplify, preserve_topology=True)
        if not geom.is_valid:
            geom = shapely.make_valid(geom)
        out[int(lab)] = geom
    return out


def geodesic_split(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Share ``mask`` between the seed labels (uint16, 0 = none) by geodesic (4-connected)
    distance: a marker flood (cv2.watershed) on an image that is flat inside the mask and a
    wall outside it, so the flood fills the mask from the seeds before it crosses a wall."""
    k = int(seeds.max())
    img = np.zeros((*mask.shape, 3), dtype=np.uint8)
    img[~mask] = 255
    markers = np.where(mask, seeds, k + 1).astype(np.int32)
    cv2.watershed(img, markers)
    lab = np.where(mask & (markers > 0) & (markers <= k), markers, 0).astype(np.uint16)
    kernel = np.ones((3, 3), np.uint8)
    todo = mask & (lab == 0)  # the flood's dividing lines (-1) and anything unreached
    for _ in range(4):
        if not todo.any():
            break
        dil = cv2.dilate(lab, kernel)
        grow = todo & (dil > 0)
        lab[grow] = dil[grow]
        todo &= ~grow
    return lab
