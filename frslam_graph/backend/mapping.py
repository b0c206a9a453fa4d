"""LiDAR occupancy map from keyframe scans at their current pose estimates (log-odds).

Units: metres, radians, frame ``map``. Each keyframe contributes its planar end points (in
``base_link``, beam order) and the sensor origin. Per scan:

* hits: the cells the end points fall in (each counted once per scan);
* misses: the star polygon of :func:`free_polygon` filled with OpenCV at sub-cell precision in a
  window around the scan (no per-beam Python loop), each cell counted at most once per scan. Each
  beam clears only up to where it comes within ``end_margin`` (1.5 cells) of the surface it hits
  (``end_margin / sin(incidence)`` before its end point), so the cells next to a hit stay and a
  beam grazing a wall does not eat it; the wedge between two adjacent beams is cleared only up to the *shorter*
  of the two (a depth discontinuity does not clear the region behind the near object, a beam
  grazing a wall does not clear the wall between its neighbours' end points); beams without a
  return (the gaps in the beam angles: NaN / max range readings are absent from the points)
  clear up to ``no_return_range`` (3 m): far enough to mark open space near the robot, short
  enough that a missed return (dark or glass surface) rarely clears through a wall;
* a cell a beam ends in is never cleared by the same scan.

:class:`OccupancyMapper` keeps per-cell hit / miss counts on a grid that grows as needed and is
*incremental*: new keyframes are added, keyframes whose pose estimate moved (after a prior or a
loop closure) are subtracted at their old pose and added at the new one (exact, counts are
integers), so repeated map requests during a run cost little. Cell log-odds =
hits · l_hit + misses · l_miss, with a hit worth ~40 misses (a wall cell hit by a few scans
stays occupied although other scans' free space grazes it; an object seen once and then seen
through many times is cleared); occupied (100) above ``occupied_logodds``, free (0) below
``free_logodds``, unknown (-1) otherwise. Output follows nav_msgs/OccupancyGrid: row 0 is the
lowest y, ``origin`` the lower-left corner of cell (0, 0), yaw 0.

:func:`endpoint_share` measures a map against the scans: the share of end points (at the final
poses) on or next to an occupied cell (:func:`scans_endpoint_share`: of keyframe scans, in chunks).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from frslam_graph import limits
from frslam_graph.errors import ConfigError
from frslam_graph.se2 import wrap

L_HIT = 0.85
L_MISS = -0.02
FREE_LOGODDS = -0.01
# The map the floor-plan registration reads compares the plan's rooms with free space: it keeps
# the balanced weights of before, under which free space wins over a few stray hits (with the
# wall-keeping weights above, regime-B house 026f's ATE with the plan went 0.043 -> 0.056 m).
FREE_SPACE_WEIGHTS = {"l_miss": -0.4, "free_logodds": -0.3}
END_MARGIN_CELLS = 1.5  # a beam stops clearing this many cells from the surface it hits
NO_RETURN_RANGE = 3.0  # m: how far a beam without a return clears
MAX_GAP = np.pi / 2  # rad: adjacent end points further apart in angle bound no free wedge
_SHIFT = 4
_SUB = 1 << _SHIFT
_GROW = 64  # cells of slack added when the grid grows


def end_margin_along_beams(vx: np.ndarray, vy: np.ndarray, r: np.ndarray, margin: float) -> np.ndarray:
    """How far (M,) before its end point each beam stops clearing, so that it stays ``margin``
    (metres) away from the surface it hits: ``margin / sin(incidence)``, at most the range ``r``.

    ``vx``, ``vy`` (M,): beams sensor -> end point in beam order, ``r`` (M,) their lengths. The
    surface direction at end point i is that of the chord between the end points two beams either
    side (less sensitive to range noise than the adjacent ones); at a depth discontinuity that
    chord is nearly radial, so the beam clears less: the safe side.
    """
    px = np.concatenate((vx[:1], vx[:1], vx, vx[-1:], vx[-1:]))
    py = np.concatenate((vy[:1], vy[:1], vy, vy[-1:], vy[-1:]))
    tx, ty = px[4:] - px[:-4], py[4:] - py[:-4]
    sin_inc = np.abs(vx * ty - vy * tx) / np.maximum(r * np.sqrt(tx * tx + ty * ty), 1e-12)
    return np.minimum(margin / np.maximum(sin_inc, 1e-3), r)


def free_polygon(
    origin: np.ndarray, ends: np.ndarray, end_margin: float, no_return_range: float = NO_RETURN_RANGE
) -> np.ndarray:
    """Vertices (P, 2) of the region one scan saw free, a polygon star-shaped about the sensor.

    ``origin`` (2,): the sensor; ``ends`` (M >= 2, 2): end points in beam order (any frame, metres;
    the result is in the same frame). Beam i clears up to where it comes within ``end_margin`` of
    the surface it hits (:func:`end_margin_along_beams`). The beam increment is the median angle
    step between adjacent end points; a step of k increments (k >= 2, within a quarter increment)
    holds k - 1 beams without a return, which clear up to ``no_return_range``. Between adjacent
    beams the wedge is cleared up to the shorter of the two clearing ranges (vertices: beam b at
    its range, beam b at the wedge range, beam b+1 at the wedge range, ...). Adjacent end points
    whose angle step is <= 0 or > :data:`MAX_GAP` are not joined (the wedge range is 0).
    """
    ox, oy = float(origin[0]), float(origin[1])
    vx, vy = ends[:, 0] - ox, ends[:, 1] - oy
    r = np.sqrt(vx * vx + vy * vy)
    th = np.arctan2(vy, vx)
    clear = r - end_margin_along_beams(vx, vy, r, end_margin)
    d = (np.diff(th) + np.pi) % (2.0 * np.pi) - np.pi
    s = 1.0
    if 2 * np.count_nonzero(d < 0.0) > len(d):  # beams in clockwise order
        s, d = -1.0, -d
    joined = (d > 1e-9) & (d <= MAX_GAP)
    dj = d[joined]
    inc = float(np.partition(dj, len(dj) // 2)[len(dj) // 2]) if len(dj) else 0.0
    missing = np.zeros(len(d), np.int64)
    if inc > 0.0:
        q = d / inc
        steps = np.rint(q)
        gap = joined & (steps >= 2.0) & (np.abs(q - steps) < 0.25)
        missing[gap] = steps[gap] - 1
    if missing.any():  # every beam: each return followed by the beams without a return after it
        counts = np.append(1 + missing, 1)
        first = np.cumsum(counts) - counts
        beam = np.repeat(np.arange(len(r)), counts)
        j = np.arange(len(beam)) - np.repeat(first, counts)  # 0: the return, > 0: no return
        ang = th[beam] + (s * inc) * j
        rng = np.where(j == 0, clear[beam], no_return_range)
        last_of_group = first[1:] - 1
    else:
        ang, rng, last_of_group = th, clear, slice(None)
    wedge = np.minimum(rng[:-1], rng[1:])
    wedge[last_of_group] *= joined  # pairs of returns not joined: no wedge
    n = len(ang)
    a = np.empty(3 * n - 2)
    rr = np.empty(3 * n - 2)
    a[0::3], a[1::3], a[2::3] = ang, ang[:-1], ang[1:]
    rr[0::3], rr[1::3], rr[2::3] = rng, wedge, wedge
    out = np.empty((3 * n - 1, 2))
    out[0] = ox, oy
    out[1:, 0] = ox + rr * np.cos(a)
    out[1:, 1] = oy + rr * np.sin(a)
    return out


def scan_points_in_map(poses: np.ndarray, scans: Sequence[np.ndarray]) -> np.ndarray:
    """End points (N, 2) in ``map`` of keyframe scans ``scans[k]`` (M_k, 2, base_link) at ``poses`` (K, 3)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(poses) != len(scans):
        raise ValueError(f"{len(poses)} poses for {len(scans)} scans")
    if not len(scans):
        return np.zeros((0, 2))
    pts = np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in scans])
    pose = np.repeat(poses, [len(np.asarray(p).reshape(-1, 2)) for p in scans], axis=0)
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    return np.column_stack(
        (pose[:, 0] + c * pts[:, 0] - s * pts[:, 1], pose[:, 1] + s * pts[:, 0] + c * pts[:, 1])
    )


def endpoint_share(grid, points_in_map: np.ndarray) -> float:
    """Share of ``points_in_map`` (N, 2, metres, ``map``) in a cell of ``grid`` (OccupancyGrid) that
    is occupied or 8-adjacent to an occupied one (within one cell); points off the grid count as
    misses. NaN without points."""
    pts = np.asarray(points_in_map, dtype=np.float64).reshape(-1, 2)
    if not len(pts):
        return float("nan")
    return _on_wall(_near_walls(grid), grid, pts) / len(pts)


#: end points looked up at once by :func:`scans_endpoint_share` (~16 MB per (N, 2) float64 array)
ENDPOINT_CHUNK = 1 << 20


def scans_endpoint_share(grid, poses: np.ndarray, scans: Sequence[np.ndarray]) -> float:
    """:func:`endpoint_share` of the keyframe scans ``scans[k]`` (M_k, 2, base_link) at ``poses``
    (K, 3) (:func:`scan_points_in_map`), the same value, a chunk of about :data:`ENDPOINT_CHUNK`
    end points at a time: all of a 2-h recording's at once (14,000 keyframes of 720 beams) took
    ~1 GB of temporaries at the end of its run."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(poses) != len(scans):
        raise ValueError(f"{len(poses)} poses for {len(scans)} scans")
    sizes = np.array([len(np.asarray(p).reshape(-1, 2)) for p in scans], dtype=np.int64)
    total = int(sizes.sum())
    if not total:
        return float("nan")
    near = _near_walls(grid)
    ends = np.cumsum(sizes)
    on, lo = 0, 0
    while lo < len(scans):  # whole keyframes, at least one
        hi = max(lo + 1, int(np.searchsorted(ends, ends[lo] - sizes[lo] + ENDPOINT_CHUNK, side="right")))
        on += _on_wall(near, grid, scan_points_in_map(poses[lo:hi], scans[lo:hi]))
        lo = hi
    return on / total


def _near_walls(grid) -> np.ndarray:
    """(H, W) bool: cells occupied or 8-adjacent to an occupied one."""
    return cv2.dilate(grid.occupied_mask().astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def _on_wall(near: np.ndarray, grid, pts: np.ndarray) -> int:
    """How many of ``pts`` (N, 2, map) lie in a ``near`` cell (points off the grid: none)."""
    if not len(pts):
        return 0
    cr = np.floor(grid.world_to_cell(pts)).astype(np.int64)
    inside = (cr[:, 0] >= 0) & (cr[:, 0] < grid.width) & (cr[:, 1] >= 0) & (cr[:, 1] < grid.height)
    return int(np.count_nonzero(near[cr[inside, 1], cr[inside, 0]]))


class OccupancyMapper:
    """Incremental hit / miss counts of keyframe scans (see module docstring).

    ``end_margin`` (m, default 1.5 cells): free space stops this far from the surface a beam hits;
    ``no_return_range`` (m): how far a beam without a return clears.
    """

    def __init__(
        self,
        resolution: float = 0.05,
        pose_tolerance_xy: float | None = None,
        pose_tolerance_theta: float = np.deg2rad(0.2),
        l_hit: float = L_HIT,
        l_miss: float = L_MISS,
        occupied_logodds: float = 0.5,
        free_logodds: float = FREE_LOGODDS,
        end_margin: float | None = None,
        no_return_range: float = NO_RETURN_RANGE,
    ):
        if not (np.isfinite(resolution) and resolution > 0):
            raise ValueError(f"resolution must be positive, got {resolution!r}")
        self.resolution = float(resolution)
        self.tol_xy = 0.25 * self.resolution if pose_tolerance_xy is None else float(pose_tolerance_xy)
        self.tol_th = float(pose_tolerance_theta)
        self.l_hit, self.l_miss = l_hit, l_miss
        self.occupied_logodds, self.free_logodds = occupied_logodds, free_logodds
        self.end_margin = END_MARGIN_CELLS * self.resolution if end_margin is None else float(end_margin)
        self.no_return_range = float(no_return_range)
        self._hits = np.zeros((0, 0), np.int32)
        self._misses = np.zeros((0, 0), np.int32)
        self._c0 = np.zeros(2, np.int64)  # global cell (ix, iy) of array element [0, 0]
        self._poses: list[np.ndarray | None] = []  # pose each keyframe is inserted at

    def __len__(self) -> int:
        return sum(p is not None for p in self._poses)

    # ------------------------------------------------------------------ updates
    def update(
        self,
        poses: np.ndarray,
        scans: Sequence[np.ndarray],
        origins: Sequence[np.ndarray] | None = None,
    ) -> int:
        """Bring the counts to ``poses`` (K, 3) for keyframe scans ``scans[k]`` (M_k, 2) in base_link.

        Keyframes beyond the ones known are added; known ones are re-inserted when their pose
        moved more than the tolerance. Returns the number of scans (re-)inserted.
        """
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        if len(poses) != len(scans):
            raise ValueError(f"{len(poses)} poses for {len(scans)} scans")
        if len(poses) < len(self._poses):  # fewer keyframes than before: start again
            self.reset()
        n_old = len(self._poses)
        moved = []
        if n_old:
            old = np.array([p if p is not None else np.full(3, np.nan) for p in self._poses])
            d_xy = np.hypot(*(poses[:n_old, :2] - old[:, :2]).T)
            d_th = np.abs(wrap(poses[:n_old, 2] - old[:, 2]))
            moved = np.flatnonzero(~((d_xy <= self.tol_xy) & (d_th <= self.tol_th))).tolist()
        if n_old and len(moved) > 0.6 * n_old:
            self.reset()
            n_old, moved = 0, []
        count = 0
        for k in moved:
            o = self._origin(origins, k)
            if self._poses[k] is not None:
                self._insert(self._poses[k], scans[k], o, -1)
            self._poses[k] = None
            if self._insert(poses[k], scans[k], o, +1):
                self._poses[k] = poses[k].copy()
            count += 1
        for k in range(n_old, len(poses)):
            ok = self._insert(poses[k], scans[k], self._origin(origins, k), +1)
            self._poses.append(poses[k].copy() if ok else None)
            count += 1
        return count

    def reset(self) -> None:
        self._hits = np.zeros((0, 0), np.int32)
        self._misses = np.zeros((0, 0), np.int32)
        self._poses = []

    @staticmethod
    def _origin(origins, k) -> np.ndarray:
        return np.zeros(2) if origins is None else np.asarray(origins[k], dtype=np.float64)[:2]

    def _insert(self, pose: np.ndarray, pts: np.ndarray, origin: np.ndarray, sign: int) -> bool:
        """Add (``sign`` +1) or subtract (-1) one scan at ``pose``; False when it has < 2 points."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if len(pts) < 2:
            return False
        c, s = np.cos(pose[2]), np.sin(pose[2])
        ow = np.array([pose[0] + c * origin[0] - s * origin[1], pose[1] + s * origin[0] + c * origin[1]])
        ew = np.empty_like(pts)  # end points: base_link -> map
        ew[:, 0] = pose[0] + c * pts[:, 0] - s * pts[:, 1]
        ew[:, 1] = pose[1] + s * pts[:, 0] + c * pts[:, 1]
        poly = free_polygon(ow, ew, self.end_margin, self.no_return_range) / self.resolution
        xs = np.concatenate((poly[:, 0], ew[:, 0] / self.resolution))  # window: polygon and hits
        ys = np.concatenate((poly[:, 1], ew[:, 1] / self.resolution))
        lo = np.floor([xs.min(), ys.min()]).astype(np.int64)
        hi = np.floor([xs.max(), ys.max()]).astype(np.int64) + 1
        self._ensure(lo, hi)
        a0 = lo - self._c0  # window in array indices
        shape = (int(hi[1] - lo[1]), int(hi[0] - lo[0]))
        mask = np.zeros(shape, dtype=np.uint8)
        pix = np.round((poly - lo - 0.5) * _SUB).astype(np.int32)  # cell centres at integer + 0.5
        cv2.fillPoly(mask, [pix.reshape(-1, 1, 2)], 1, lineType=cv2.LINE_8, shift=_SHIFT)
        hc = np.floor(ew[:, 0] / self.resolution).astype(np.int64) - lo[0]
        hr = np.floor(ew[:, 1] / self.resolution).astype(np.int64) - lo[1]
        mask[hr, hc] = 0  # a cell a beam ends in is never cleared by the same scan
        rows, cols = slice(a0[1], a0[1] + shape[0]), slice(a0[0], a0[0] + shape[1])
        # fancy-index += / -= counts a repeated cell once: each cell one hit per scan at most
        if sign > 0:
            self._misses[rows, cols] += mask
            self._hits[hr + a0[1], hc + a0[0]] += 1
        else:
            self._misses[rows, cols] -= mask
            self._hits[hr + a0[1], hc + a0[0]] -= 1
        return True

    def _ensure(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Grow the arrays so global cells [lo, hi) fit."""
        h, w = self._hits.shape
        c1 = self._c0 + np.array([w, h])
        if h and w and np.all(lo >= self._c0) and np.all(hi <= c1):
            return
        if not (h and w):
            new0, new1 = lo - _GROW, hi + _GROW
        else:
            new0 = np.minimum(self._c0, lo - _GROW)
            new1 = np.maximum(c1, hi + _GROW)
        nw, nh = (new1 - new0).tolist()
        if nw * nh > limits.MAX_GRID_CELLS:
            raise ConfigError(
                f"an occupancy grid of {nw:,} x {nh:,} cells at {self.resolution:g} m is over the limit of "
                f"{limits.MAX_GRID_CELLS:,} cells (MAX_GRID_CELLS, frslam_graph.limits); use a coarser resolution",
                where="resolution",
            )
        hits = np.zeros((nh, nw), np.int32)
        misses = np.zeros((nh, nw), np.int32)
        if h and w:
            off = self._c0 - new0
            hits[off[1] : off[1] + h, off[0] : off[0] + w] = self._hits
            misses[off[1] : off[1] + h, off[0] : off[0] + w] = self._misses
        self._hits, self._misses, self._c0 = hits, misses, new0

    # ------------------------------------------------------------------ output
    def arrays(self, margin: float = 0.5) -> tuple[np.ndarray, float, tuple[float, float, float]]:
        """(data int8 (H, W), resolution, origin (x, y, 0)) cropped to the observed cells + margin."""
        seen = (self._hits > 0) | (self._misses > 0)
        if not seen.any():
            return np.full((1, 1), -1, np.int8), self.resolution, (0.0, 0.0, 0.0)
        rows = np.flatnonzero(seen.any(axis=1))
        cols = np.flatnonzero(seen.any(axis=0))
        m = int(np.ceil(margin / self.resolution))
        r0, r1 = max(rows[0] - m, 0), min(rows[-1] + m + 1, seen.shape[0])
        c0, c1 = max(cols[0] - m, 0), min(cols[-1] + m + 1, seen.shape[1])
        hits = self._hits[r0:r1, c0:c1]
        misses = self._misses[r0:r1, c0:c1]
        logodds = hits * self.l_hit + misses * self.l_miss
        data = np.full(hits.shape, -1, dtype=np.int8)
        data[(logodds < self.free_logodds) & (misses > 0)] = 0
        data[(logodds > self.occupied_logodds) & (hits > 0)] = 100
        origin = ((self._c0[0] + c0) * self.resolution, (self._c0[1] + r0) * self.resolution, 0.0)
        return data, self.resolution, (float(origin[0]), float(origin[1]), 0.0)

    def grid(self, margin: float = 0.5):
        """The map as :class:`frslam_graph.occupancy.OccupancyGrid`."""
        from frslam_graph.occupancy import OccupancyGrid

        data, res, origin = self.arrays(margin)
        return OccupancyGrid(data, res, origin)


def occupancy_arrays(
    poses: np.ndarray,
    scans: Sequence[np.ndarray],
    origins: Sequence[np.ndarray] | None = None,
    resolution: float = 0.05,
    margin: float = 0.5,
    **kwargs,
) -> tuple[np.ndarray, float, tuple[float, float, float]]:
    """One-shot occupancy of keyframe scans: (data int8 (H, W), resolution, origin (x, y, 0)).

    ``poses`` (K, 3): base_link in map. ``scans[k]`` (M_k, 2): end points in base_link.
    ``origins[k]``: the sensor position (x, y) in base_link (default (0, 0)).
    """
    mapper = OccupancyMapper(resolution, **kwargs)
    mapper.update(poses, scans, origins)
    return mapper.arrays(margin)


def occupancy_grid(
    poses: np.ndarray,
    scans: Sequence[np.ndarray],
    origins: Sequence[np.ndarray] | None = None,
    resolution: float = 0.05,
    **kwargs,
):
    """:func:`occupancy_arrays` wrapped in :class:`frslam_graph.occupancy.OccupancyGrid`."""
    from frslam_graph.occupancy import OccupancyGrid

    data, res, origin = occupancy_arrays(poses, scans, origins, resolution, **kwargs)
    return OccupancyGrid(data, res, origin)


__all__ = [
    "OccupancyMapper",
    "endpoint_share",
    "free_polygon",
    "occupancy_arrays",
    "occupancy_grid",
    "scan_points_in_map",
    "scans_endpoint_share",
]
