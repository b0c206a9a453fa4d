"""MFR step 2, the plan side: a floor plan prepared for registration (plan units).

Its wall direction; per-room area moments and bounding boxes; boundary samples with inward
normals, leaving out doors and open-plan boundaries (no plan wall along them, as in R2V's
living-dining-kitchens); the room graph (doors, open-plan boundaries, shared walls for rooms
without doors), whose connected subsets the coarse search tries
(:mod:`frslam_graph.registration.subsets`); distance rasters to the plan's boundaries and
openings; grid points inside the rooms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import shapely

from frslam_graph.raster import RasterFrame
from frslam_graph.registration.mfr.geometry import dominant_angles
from frslam_graph.registration.refine import ring_edges, sample_boundaries
from frslam_graph.registration.subsets import adjacency_masks, link_doors, rings_moments
from frslam_graph.se2 import rot

SHIFT = 8  # cv2.fillPoly fractional bits
FIX = float(1 << SHIFT)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M, K) distances from points (M, 2) to segments a–b (K, 2 each)."""
    u = b - a
    l2 = np.maximum((u * u).sum(axis=1), 1e-300)
    rx = p[:, None, 0] - a[None, :, 0]
    ry = p[:, None, 1] - a[None, :, 1]
    t = np.clip((rx * u[None, :, 0] + ry * u[None, :, 1]) / l2[None, :], 0.0, 1.0)
    return np.hypot(rx - t * u[None, :, 0], ry - t * u[None, :, 1])


@dataclass
class PlanModel:
    """A floor plan prepared for registration (plan units)."""

    ids: list[str]
    polygons: list
    rings: list[np.ndarray]
    ring_room: np.ndarray
    doors: np.ndarray  # (D, 4)
    angle: float
    moments: np.ndarray  # (n, 6) in the frame rotated by -angle
    bounds: np.ndarray  # (n, 4) in the frame rotated by -angle
    adjacency: np.ndarray
    area: float
    diag: float
    room_rings: list[list[np.ndarray]]
    room_holes: list[list[np.ndarray]]
    room_areas: np.ndarray
    perimeter: float
    samples: np.ndarray  # (M, 2) boundary points on walls (door openings, open-plan boundaries left out)
    sample_step: float  # their spacing (plan units)
    sample_normals: np.ndarray  # (M, 2) unit inward normals
    sample_room: np.ndarray  # (M,) room index of each sample
    plan_dt: np.ndarray  # plan units to the nearest room boundary, on plan_frame
    open_dt: np.ndarray | None  # plan units to the nearest opening (door, open-plan boundary)
    plan_frame: RasterFrame
    inner: np.ndarray  # (P, 2) grid points inside rooms
    inner_onehot: np.ndarray  # (P, n) their room
    inner_counts: np.ndarray  # (n,) float32 inner_onehot.sum(axis=0): points per room
    door_width: float  # median door width (plan units), 0 without doors
    coarse_samples: np.ndarray  # (M', 2) a subsample of ``samples``
    coarse_onehot: np.ndarray  # (M', n) their room
    coarse_normals: np.ndarray  # (M', 2) their unit inward normals


def prepare_plan(
    plan,
    *,
    adjacency: str = "doors",
    samples: int = 1000,
    dt_px: int = 240,
    inner_points: int = 1200,
    coarse_samples: int = 500,
) -> PlanModel:
    """Room polygons, rings, moments and the room graph of a FloorPlan."""
    rooms = list(plan.rooms)
    polys = [r.polygon for r in rooms]
    rings, ring_room, room_rings, room_holes = [], [], [], []
    for i, p in enumerate(polys):
        p = shapely.orient_polygons(p)  # exterior counter-clockwise: the room on the left
        rings.append(np.asarray(p.exterior.coords)[:-1])
        ring_room.append(i)
        room_rings.append([rings[-1]])
        room_holes.append([])
        for hole in p.interiors:
            rings.append(np.asarray(hole.coords)[:-1])
            ring_room.append(i)
            room_holes[-1].append(rings[-1])
    starts, ends, edge_ring = ring_edges(rings)
    ring_room_arr = np.array(ring_room)
    edge_room = ring_room_arr[edge_ring]
    n = len(rooms)
    angle = dominant_angles(ends - starts, max_peaks=1)[0]
    if abs(angle) < math.radians(0.5):  # a plan drawn axis-aligned: its own axes, exactly
        angle = 0.0
    turn = rot(-angle)
    moments = rings_moments(starts @ turn.T, ends @ turn.T, edge_room, n)
    xy = starts @ turn.T
    bounds = np.full((n, 4), np.inf)
    bounds[:, 2:] = -np.inf
    np.minimum.at(bounds[:, 0], edge_room, xy[:, 0])
    np.minimum.at(bounds[:, 1], edge_room, xy[:, 1])
    np.maximum.at(bounds[:, 2], edge_room, xy[:, 0])
    np.maximum.at(bounds[:, 3], edge_room, xy[:, 1])
    minx, miny = starts.min(axis=0)
    maxx, maxy = starts.max(axis=0)
    diag = float(math.hypot(maxx - minx, maxy - miny))
    doors_list = list(plan.doors)
    door_rooms = link_doors(rooms, doors_list, 0.025 * diag)
    doors = np.array([[*d.a, *d.b] for d in doors_list], dtype=np.float64).reshape(-1, 4)
    perimeter = float(np.hypot(*(ends - starts).T).sum())
    step = perimeter / samples
    pts, nrm, owner = sample_boundaries(rings, step, doors, door_tol=0.012 * diag)
    owner_room = ring_room_arr[owner]
    bare_pts = np.zeros((0, 2))
    # open plans: a boundary between two rooms that no plan wall runs along is not a wall (and
    # links the rooms)
    walls = getattr(plan, "walls", None)
    if walls is not None and len(walls):
        segs = np.vstack([np.asarray(walls, dtype=np.float64).reshape(-1, 4), doors])
        tol = 0.01 * diag
        supported = _segment_distance(pts, segs[:, :2], segs[:, 2:]).min(axis=1) <= tol
        bare = np.flatnonzero(~supported)
        if len(bare):
            d = _segment_distance(pts[bare], starts, ends)  # (U, E)
            d[edge_room[None, :] == owner_room[bare, None]] = np.inf
            nearest = np.full((len(bare), n), np.inf)
            np.minimum.at(nearest.T, edge_room, d.T)
            other = np.argmin(nearest, axis=1)
            close = nearest[np.arange(len(bare)), other] <= tol
            pairs = np.sort(np.column_stack([owner_room[bare][close], other[close]]), axis=1)
            if len(pairs):
                uniq, counts = np.unique(pairs, axis=0, return_counts=True)
                # both rooms sample the shared stretch: half the count times the spacing
                for (i, j), c in zip(uniq.tolist(), counts.tolist(), strict=True):
                    if 0.5 * c * step >= 0.025 * diag:
                        door_rooms.append((i, j))
            # only a boundary shared with another room can be open; outer walls stay walls
            keep = np.ones(len(pts), bool)
            keep[bare[close]] = False
            bare_pts = pts[~keep]
            pts, nrm, owner_room = pts[keep], nrm[keep], owner_room[keep]
    adj = adjacency_masks(rooms, door_rooms, mode=adjacency, touch_tol=0.01 * diag)
    pres = diag / dt_px
    pframe = RasterFrame.around((minx, miny, maxx, maxy), pres, margin=0.05 * diag)
    lines = np.zeros(pframe.shape, np.uint8)
    cells = np.floor((pts - pframe.origin) / pres).astype(np.intp)
    lines[np.clip(cells[:, 1], 0, pframe.height - 1), np.clip(cells[:, 0], 0, pframe.width - 1)] = 1
    openings = np.zeros(pframe.shape, np.uint8)
    for x1, y1, x2, y2 in doors:
        a, b = (np.array([[x1, y1], [x2, y2]]) - pframe.origin) / pres - 0.5
        a, b = tuple(np.round(a * FIX).astype(int)), tuple(np.round(b * FIX).astype(int))
        cv2.line(openings, a, b, 1, 1, cv2.LINE_8, SHIFT)
    # a closed door looks like a wall: map walls at plan doors are explained too (recall)
    plan_dt = cv2.distanceTransform(1 - (lines | openings), cv2.DIST_L2, 3) * np.float32(pres)
    if len(bare_pts):
        cells = np.floor((bare_pts - pframe.origin) / pres).astype(np.intp)
        openings[np.clip(cells[:, 1], 0, pframe.height - 1), np.clip(cells[:, 0], 0, pframe.width - 1)] = 1
    open_dt = (
        cv2.distanceTransform(1 - openings, cv2.DIST_L2, 3) * np.float32(pres) if openings.any() else None
    )
    area = float(moments[:, 0].sum())
    cell = math.sqrt(area / inner_points)
    iframe = RasterFrame.around((minx, miny, maxx, maxy), cell)
    lab = fill_rooms(room_rings, room_holes, range(n), np.eye(3), iframe, labels=True)
    ir, ic = np.nonzero(lab)
    inner = (np.column_stack([ic, ir]) + 0.5) * cell + iframe.origin
    inner_room = lab[ir, ic] - 1
    empty = np.setdiff1d(np.arange(n), inner_room)  # rooms too small for the grid: one point each
    if len(empty):
        extra = np.array([polys[i].representative_point().coords[0] for i in empty])
        inner = np.vstack([inner, extra])
        inner_room = np.concatenate([inner_room, empty])
    eye = np.eye(n)
    cstride = max(1, len(pts) // coarse_samples)
    inner_onehot = eye[inner_room].astype(np.float32)
    return PlanModel(
        ids=[r.id for r in rooms],
        polygons=polys,
        rings=rings,
        ring_room=np.array(ring_room),
        doors=doors,
        angle=angle,
        moments=moments,
        bounds=bounds,
        adjacency=adj,
        area=area,
        diag=diag,
        room_rings=room_rings,
        room_holes=room_holes,
        room_areas=moments[:, 0].copy(),
        perimeter=perimeter,
        samples=pts,
        sample_step=step,
        sample_normals=nrm,
        sample_room=owner_room,
        plan_dt=plan_dt,
        open_dt=open_dt,
        plan_frame=pframe,
        inner=inner,
        inner_onehot=inner_onehot,
        inner_counts=inner_onehot.sum(axis=0),
        door_width=float(np.median(np.hypot(doors[:, 2] - doors[:, 0], doors[:, 3] - doors[:, 1])))
        if len(doors)
        else 0.0,
        coarse_samples=pts[::cstride],
        coarse_onehot=eye[owner_room[::cstride]].astype(np.float32),
        coarse_normals=nrm[::cstride],
    )


def fill_rooms(
    room_rings,
    room_holes,
    rooms,
    matrix: np.ndarray,
    frame: RasterFrame,
    labels: bool = False,
    label_dtype: type = np.int32,
) -> np.ndarray:
    """Rasterise plan rooms (indices) under ``matrix`` (plan -> frame metres) with cv2.fillPoly at
    sub-pixel precision; a pixel is inside when its centre is. Mask (uint8) or 1-based labels
    (``label_dtype``: uint8 holds up to 255 rooms)."""
    m = np.diag([1.0 / frame.resolution, 1.0 / frame.resolution, 1.0]) @ matrix
    m[:2, 2] -= np.asarray(frame.origin) / frame.resolution + 0.5
    a, t = m[:2, :2], m[:2, 2]
    img = np.zeros(frame.shape, label_dtype if labels else np.uint8)
    rooms = list(rooms)
    ext = _fixed_rings([r for i in rooms for r in room_rings[i]], a, t)
    holes = _fixed_rings([r for i in rooms for r in room_holes[i]], a, t)
    if labels:
        at = 0
        for i in rooms:
            k = len(room_rings[i])
            cv2.fillPoly(img, ext[at : at + k], int(i) + 1, lineType=cv2.LINE_8, shift=SHIFT)
            at += k
    elif ext:
        cv2.fillPoly(img, ext, 1, lineType=cv2.LINE_8, shift=SHIFT)
    if holes:
        cv2.fillPoly(img, holes, 0, lineType=cv2.LINE_8, shift=SHIFT)
    return img


def _fixed_rings(rings: list[np.ndarray], a: np.ndarray, t: np.ndarray) -> list[np.ndarray]:
    """Each ring (k, 2) as ``np.round((r @ a.T + t) * FIX).astype(np.int32).reshape(-1, 1, 2)``
    (cv2.fillPoly's fixed-point vertices): each ring's own product, the element operations on
    all rings at once (the same values)."""
    if not rings:
        return []
    q = np.concatenate([r @ a.T for r in rings])
    q += t
    q *= FIX
    q = np.round(q).astype(np.int32)
    out, at = [], 0  # np.split's pieces (views of q), without its per-piece overhead
    for r in rings:
        out.append(q[at : at + len(r)].reshape(-1, 1, 2))
        at += len(r)
    return out
