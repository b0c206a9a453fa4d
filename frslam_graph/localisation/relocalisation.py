"""Relocalise a LiDAR scan against a registered floor plan (map frame; metres, radians).

The plan (a :class:`~frslam_graph.floorplan.FloorPlan` already in map metres, e.g.
``registration.apply(plan)``) is turned into a **signed distance field** of its walls: free
space is every room eroded by ``wall_offset`` (half the wall thickness; two rooms sharing a
boundary get a wall band of ``2 * wall_offset`` between them) plus an opening at every door
joining two rooms and along every shared boundary no plan wall runs along (open-plan areas);
the field is positive in free space, negative in walls and outside, zero on
the wall surfaces, rasterised with :mod:`frslam_graph.raster` and ``cv2.distanceTransform``.
A :class:`Relocaliser` builds it once per plan (the cache) and then, for a scan given as points
in ``base_link`` (N, 2) and a prior pose of ``base_link`` in ``map``:

1. subsamples the points on a voxel grid (at most ``max_points``);
2. runs a two-level correlative search over (x, y, θ) in a window around the prior (a
   branch-and-bound-lite: every coarse cell gets a lower bound of the truncated cost from the
   1-Lipschitz distance field, the most promising cells are expanded on a fine grid), all
   candidate poses × points evaluated at once with numpy;
3. refines the best candidate (and the best few *separated* ones) by Levenberg-Marquardt on the
   field with a Tukey (truncated) kernel, so furniture and clutter not in the plan are ignored;
4. reports the pose, a 3×3 covariance ``σ² · H⁻¹`` (inflated, floored, eigenvalues capped so a
   degenerate direction, e.g. along a corridor, shows as a large variance), the inlier fraction
   as ``score`` and ``ambiguity`` = best separated competitor / best (soft scores).

Covariances are in the tangent space of the pose as (x, y, θ) in map (the same vector the graph
uses for ``PriorFactorPose2`` up to the rotation of the translation block, see
:func:`frslam_graph.odometry.motion_model.tangent_cov`).
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import shapely
from shapely.geometry import LineString, Polygon

from frslam_graph.errors import FloorPlanError, FrslamError
from frslam_graph.floorplan.openings import open_boundaries
from frslam_graph.raster import RasterFrame, rasterise_polygons
from frslam_graph.se2 import wrap

_CHI2_3_99 = 11.345
#: m; the field's distance where it holds no information (:meth:`Relocaliser.ignoring`)
IGNORED = 10.0


# --------------------------------------------------------------------------- distance field
@dataclass(frozen=True)
class PlanField:
    """Signed distance (metres) to the plan's wall surfaces on a raster, with its gradient.

    ``data[..., 0]`` is the distance (> 0 free, < 0 in walls / outside), ``data[..., 1:]`` its
    gradient (d/dx, d/dy). Row 0 is the lowest y (see :class:`~frslam_graph.raster.RasterFrame`).
    """

    frame: RasterFrame
    data: np.ndarray  # (H, W, 3) float32
    wall_offset: float

    @property
    def sdf(self) -> np.ndarray:
        return self.data[..., 0]

    @classmethod
    def from_plan(
        cls,
        plan,
        resolution: float = 0.025,
        wall_offset: float = 0.06,
        margin: float = 1.0,
        max_pixels: int = 8_000_000,
    ) -> PlanField:
        """Field of ``plan`` (map metres). ``wall_offset`` is half the wall thickness (metres).

        Buildings needing more than ``max_pixels`` get a coarser resolution."""
        if not (np.isfinite(resolution) and resolution > 0):
            raise FrslamError(f"resolution must be positive, got {resolution}", where="resolution")
        if plan.units != "m" and plan.metres_per_unit != 1.0:
            raise FloorPlanError(
                f"the plan is in {plan.units!r}, not metres: register it first (frslam register PLAN MAP.yaml writes it in metres; in Python registration.apply(plan))",
                source=plan.source,
                where="units",
            )
        b = plan.bounds
        pixels = (b[2] - b[0] + 2 * margin) * (b[3] - b[1] + 2 * margin) / resolution**2
        if pixels > max_pixels:  # a very large building: a coarser field rather than gigabytes
            resolution = float(resolution * np.sqrt(pixels / max_pixels))
        offset = max(float(wall_offset), 0.75 * resolution)  # keep a wall band between rooms
        try:
            frame = RasterFrame.around(plan.bounds, resolution, margin=margin + offset)
        except ValueError as exc:
            raise FrslamError(
                f"plan too large for a {resolution} m field ({exc}); is it in metres?",
                source=plan.source,
                where="plan",
            ) from None
        free = rasterise_polygons(free_space_polygons(plan, offset), frame)
        d_out = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        d_in = cv2.distanceTransform((1 - free).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        sdf = np.where(free > 0, d_out - 0.5, -(d_in - 0.5)).astype(np.float32) * np.float32(resolution)
        gy, gx = np.gradient(sdf, resolution)
        data = np.ascontiguousarray(np.stack([sdf, gx, gy], axis=-1).astype(np.float32))
        return cls(frame, data, offset)

    def lookup(self, xy: np.ndarray, outside: float = -1.0) -> np.ndarray:
        """Bilinear (value, d/dx, d/dy) at (N, 2) points -> (N, 3); ``outside`` off the raster."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        h, w = self.frame.shape
        u = (xy[:, 0] - self.frame.origin[0]) / self.frame.resolution - 0.5
        v = (xy[:, 1] - self.frame.origin[1]) / self.frame.resolution - 0.5
        i0 = np.floor(u)
        j0 = np.floor(v)
        fu = (u - i0)[:, None]
        fv = (v - j0)[:, None]
        ok = (i0 >= 0) & (i0 < w - 1) & (j0 >= 0) & (j0 < h - 1)
        base = np.where(ok, j0 * w + i0, 0).astype(np.intp)
        flat = self.data.reshape(-1, 3)
        a, b = flat[base], flat[base + 1]  # the four corners, (N, 3) each
        c, d = flat[base + w], flat[base + w + 1]
        out = a + fu * (b - a)
        out += fv * ((c + fu * (d - c)) - out)
        out[~ok] = (outside, 0.0, 0.0)
        return out

    def nearest_abs(self, col: np.ndarray, row: np.ndarray, outside: float) -> np.ndarray:
        """|distance| at integer pixel indices (any shape); ``outside`` off the raster."""
        h, w = self.frame.shape
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        flat = np.where(ok, row * w + col, 0)
        vals = np.abs(self.data[..., 0].reshape(-1)[flat])
        return np.where(ok, vals, outside)


def free_space_polygons(plan, wall_offset: float) -> list[Polygon]:
    """Rooms eroded by ``wall_offset`` plus an opening at every door joining two rooms and along
    every shared room boundary no plan wall runs along (metres; see
    :func:`~frslam_graph.floorplan.openings.open_boundaries`)."""
    polys: list = []
    for r in plan.rooms:
        g = r.polygon.buffer(-wall_offset, join_style="mitre", mitre_limit=3.0)
        if not g.is_empty:
            polys.append(g)
    doors = plan.doors
    if any(len(set(d.rooms)) < 2 for d in doors):
        linked = plan.link_doors(tol=max(0.3, 4.0 * wall_offset))
        doors = [d if len(set(d.rooms)) == 2 else ld for d, ld in zip(doors, linked.doors, strict=True)]
    envelope = shapely.union_all([r.polygon for r in plan.rooms]).buffer(
        wall_offset, join_style="mitre", mitre_limit=3.0
    )
    for d in doors:
        if len(set(d.rooms)) < 2 or d.width <= 1e-9:
            continue
        seg = LineString([d.a, d.b])
        reach = max(plan.room(rid).polygon.distance(seg) for rid in set(d.rooms))
        depth = 2.0 * wall_offset + 0.5 + 2.0 * reach
        a, b = np.asarray(d.a, float), np.asarray(d.b, float)
        u = b - a
        n = np.array([-u[1], u[0]]) / max(float(np.hypot(*u)), 1e-12) * (depth / 2.0)
        opening = Polygon([a - n, b - n, b + n, a + n]).intersection(envelope)
        if not opening.is_empty:
            polys.append(opening)
    # boundaries between rooms that no plan wall runs along (an open living-dining-kitchen)
    bare, _ = open_boundaries(plan, 2.0 * wall_offset)
    polys += [g for g in (o.intersection(envelope) for o in bare) if not g.is_empty]
    return polys


# --------------------------------------------------------------------------- result
@dataclass
class Relocalisation:
    """Pose of ``base_link`` in ``map`` from matching a scan against the plan.

    ``covariance``: 3×3 over (x, y, θ) (metres², radians²). ``score``: fraction of the
    (subsampled) scan points within ``inlier_distance`` of a plan wall. ``ambiguity``: soft score
    of the best pose *separated* from the winner (not within its covariance, nor closer than the
    separation distances) divided by the winner's, in [0, 1]; 0 when no competitor exists.
    ``ok`` False with a ``reason`` when the match failed (too few points, nothing fits).
    """

    ok: bool
    pose: np.ndarray
    covariance: np.ndarray
    score: float
    ambiguity: float
    reason: str = ""
    soft_score: float = 0.0
    n_points: int = 0
    prior: np.ndarray = field(default_factory=lambda: np.zeros(3))
    runner_up: np.ndarray | None = None
    time_s: float = 0.0

    @property
    def std(self) -> np.ndarray:
        """Standard deviations (x, y, θ)."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))


# --------------------------------------------------------------------------- relocaliser
@dataclass
class RelocaliserParams:
    """Search and noise parameters of :class:`Relocaliser` (metres, radians)."""

    resolution: float = 0.025
    wall_offset: float = 0.06
    window_xy: float = 0.75
    window_theta: float = np.deg2rad(15.0)
    coarse_xy: float = 0.15
    coarse_theta: float = np.deg2rad(3.0)
    fine_splits: tuple[int, int] = (3, 3)  # children per coarse cell: per translation axis, in θ
    expand: int = 32  # coarse cells expanded on the fine grid
    voxel: float = 0.15
    max_points: int = 160
    prior_tiebreak: float = 0.002  # search cost added at the window's edge (cost is in [0, 1])
    search_points: int = 64  # the correlative search uses an even subset of these
    min_points: int = 20
    truncation: float = 0.3
    inlier_distance: float = 0.1
    min_score: float = 0.2  # below this inlier fraction the match has failed
    separation_xy: float = 0.3
    separation_theta: float = np.deg2rad(8.0)
    competitors: int = 3
    lm_iterations: int = 15
    sensor_sigma: float = 0.02  # floor of the per-point residual sigma (m)
    cov_inflation: float = 4.0  # points are not independent; plans are not exact
    sigma_floor_xy: float = 0.02
    sigma_floor_theta: float = np.deg2rad(0.3)
    max_sigma_xy: float = 10.0
    max_sigma_theta: float = np.pi


class Relocaliser:
    """Scan-to-plan matcher for one plan in map metres (the distance field is built once)."""

    def __init__(self, plan, params: RelocaliserParams | None = None, **overrides) -> None:
        p = params or RelocaliserParams()
        if overrides:
            p = RelocaliserParams(**{**p.__dict__, **overrides})
        self.params = p
        self.plan = plan
        self.field = PlanField.from_plan(plan, p.resolution, p.wall_offset)
        self._padded: tuple[float, np.ndarray] | None = None
        #: (points (K, 2) in map metres, radius m) whose surroundings the field ignores, or None
        self.ignored: tuple[np.ndarray, float] | None = None
        #: m; RMS of how far the plan is drawn off the building (:meth:`drawn_off`), 0 if exact
        self.drawing_sigma = 0.0

    def drawn_off(self, sigma: float) -> Relocaliser:
        """A copy (the same field) whose reported covariances include a plan drawn off the building
        by an RMS of ``sigma`` metres: an error every scan point shares, so it does not shrink
        with their number. ``self`` when ``sigma`` is already its own."""
        sigma = max(float(sigma), 0.0)
        if sigma == self.drawing_sigma:
            return self
        out = copy.copy(self)
        out.drawing_sigma = sigma
        return out

    def ignoring(self, points: np.ndarray, radius: float) -> Relocaliser:
        """A copy whose field holds no information within ``radius`` metres of ``points`` ((K, 2)
        in map metres; e.g. plan walls the map has seen through): the distance there is
        :data:`IGNORED` with a zero gradient, so a scan or map point there is an outlier (Tukey
        weight 0, soft score 0, no wall in the searches and fits) and no wall is counted there.
        ``self`` when ``points`` is empty; ``ignored`` of the copy adds ``points`` to this one's."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if not len(pts):
            return self
        f = self.field
        h, w = f.frame.shape
        c = np.floor(f.frame.to_pixel(pts)).astype(np.intp)
        ok = (c[:, 0] >= 0) & (c[:, 0] < w) & (c[:, 1] >= 0) & (c[:, 1] < h)
        mask = np.zeros((h, w), np.uint8)
        mask[c[ok, 1], c[ok, 0]] = 1
        k = max(int(np.ceil(radius / f.frame.resolution)), 0)
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))) > 0
        data = f.data.copy()
        data[mask] = (IGNORED, 0.0, 0.0)
        out = copy.copy(self)
        out.field = PlanField(f.frame, data, f.wall_offset)
        out._padded = None
        if self.ignored is not None:  # the pieces ignored before stay ignored
            pts, radius = np.vstack((self.ignored[0], pts)), max(self.ignored[1], float(radius))
        out.ignored = (pts, float(radius))
        return out

    # ------------------------------------------------------------------ public
    def relocalise(
        self,
        points: np.ndarray,
        prior: np.ndarray,
        window_xy: float | None = None,
        window_theta: float | None = None,
    ) -> Relocalisation:
        """Match ``points`` ((N, 2) in base_link) in a window around ``prior`` (x, y, θ in map)."""
        t0 = time.perf_counter()
        p = self.params
        prior = np.asarray(prior, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(prior)):
            raise FrslamError("prior pose must be finite (x, y, theta)", where="prior")
        wxy = p.window_xy if window_xy is None else float(window_xy)
        wth = p.window_theta if window_theta is None else float(window_theta)
        pts = subsample(np.asarray(points, dtype=np.float64).reshape(-1, 2), p.voxel, p.max_points)
        if len(pts) < p.min_points:
            return self._fail(f"too few valid points ({len(pts)} < {p.min_points})", prior, len(pts), t0)
        cands, costs = self._search(pts, prior, wxy, wth)
        best = self._refine(pts, cands[0])
        best_pose, best_soft = best
        # competitors: separated (greedy non-maximum suppression) candidates, refined
        comp = [self._refine(pts, cands[k]) for k in self._spread(np.asarray(cands), p.competitors)]
        comp.sort(key=lambda t: -t[1])
        if comp and comp[0][1] > best_soft + 0.01 and self._separated(comp[0][0], best_pose):
            (best_pose, best_soft), comp[0] = comp[0], (best_pose, best_soft)
        res = self.field.lookup(self._transform(pts, best_pose), outside=-p.truncation)[:, 0]
        informed, score, best_soft_seen = self._reported(res, best_soft)
        cov, reported = self._covariance(pts, best_pose)
        info = np.linalg.inv(cov)
        ambiguity, runner = 0.0, None
        for pose_c, soft_c in sorted(comp, key=lambda t: -t[1]):
            d = _pose_diff(pose_c, best_pose)
            if self._separated(pose_c, best_pose) and float(d @ info @ d) > _CHI2_3_99:
                ambiguity = float(min(1.0, soft_c / max(best_soft, 1e-9)))
                runner = pose_c
                break
        ok, reason = True, ""
        if informed < p.min_points:
            ok, reason = False, f"too few points where the plan is not ignored ({informed} < {p.min_points})"
        elif score < p.min_score:
            ok, reason = False, f"no fit: inlier fraction {score:.2f} < {p.min_score:.2f}"
        return Relocalisation(
            ok=ok,
            pose=best_pose,
            covariance=reported,
            score=score,
            ambiguity=ambiguity,
            reason=reason,
            soft_score=best_soft_seen,
            n_points=len(pts),
            prior=prior,
            runner_up=runner,
            time_s=time.perf_counter() - t0,
        )

    def evaluate(self, points: np.ndarray, pose: np.ndarray) -> tuple[float, float]:
        """(inlier fraction, soft score) of ``points`` (base_link) at ``pose`` without searching,
        as :meth:`relocalise` reports them (:meth:`_reported`)."""
        p = self.params
        pts = subsample(np.asarray(points, dtype=np.float64).reshape(-1, 2), p.voxel, p.max_points)
        if not len(pts):
            return 0.0, 0.0
        r = self.field.lookup(self._transform(pts, np.asarray(pose, float)), outside=-p.truncation)[:, 0]
        return self._reported(r, _soft(r, p.truncation))[1:]

    def _reported(self, res: np.ndarray, soft: float) -> tuple[int, float, float]:
        """(informed points, inlier fraction, soft score) reported for a scan whose points have
        field residuals ``res`` (m) and whose soft score over all its points is ``soft``: the
        points around the wall pieces ignored (no information there) count neither way, so a scan
        half in a part of the building the plan draws differently fits the rest as well as any.
        :meth:`relocalise` and :meth:`evaluate` report alike, so their scores compare."""
        p = self.params
        score = float(np.mean(np.abs(res) < p.inlier_distance))
        informed = int(np.count_nonzero(res < 0.5 * IGNORED)) if self.ignored is not None else len(res)
        if p.min_points <= informed < len(res):
            share = informed / len(res)
            return informed, score / share, soft / share
        return informed, score, soft

    def fit_points(self, xy_map: np.ndarray, distance: float | None = None) -> float:
        """Fraction of map points (N, 2) within ``distance`` (default ``inlier_distance``,
        metres) of a plan wall, among those where the field holds information: a point in the
        surroundings of the wall pieces this relocaliser ignores (:meth:`ignoring`: the plan is
        drawn differently there) counts neither for nor against it; 0 when no point is left."""
        xy_map = np.asarray(xy_map, dtype=np.float64).reshape(-1, 2)
        if not len(xy_map):
            return 0.0
        tol = self.params.inlier_distance if distance is None else float(distance)
        r = self.field.lookup(xy_map, outside=-max(self.params.truncation, tol + 1.0))[:, 0]
        if self.ignored is not None:
            r = r[r < 0.5 * IGNORED]
            if not len(r):
                return 0.0
        return float(np.mean(np.abs(r) < tol))

    # ------------------------------------------------------------------ internals
    def _fail(self, reason: str, prior: np.ndarray, n: int, t0: float) -> Relocalisation:
        p = self.params
        cov = np.diag([p.max_sigma_xy**2, p.max_sigma_xy**2, p.max_sigma_theta**2])
        return Relocalisation(
            False, prior.copy(), cov, 0.0, 1.0, reason, 0.0, n, prior, None, time.perf_counter() - t0
        )

    def _separated(self, a: np.ndarray, b: np.ndarray) -> bool:
        return bool(self._separated_from(np.asarray(a, float).reshape(1, 3), b)[0])

    def _separated_from(self, poses: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Which of ``poses`` (N, 3) are farther than the separation distances from ``ref``."""
        d = poses - np.asarray(ref, float)
        dth = np.abs((d[:, 2] + np.pi) % (2 * np.pi) - np.pi)
        return (np.hypot(d[:, 0], d[:, 1]) > self.params.separation_xy) | (dth > self.params.separation_theta)

    def _spread(self, poses: np.ndarray, n: int) -> list[int]:
        """Greedy non-maximum suppression: indices of up to ``n`` of ``poses[1:]`` (in order),
        each separated from ``poses[0]`` and from those taken before it."""
        taken: list[int] = []
        ok = self._separated_from(poses, poses[0])
        while len(taken) < n:
            nxt = np.flatnonzero(ok)
            if not len(nxt):
                break
            taken.append(int(nxt[0]))
            ok &= self._separated_from(poses, poses[taken[-1]])
        return taken

    @staticmethod
    def _transform(pts: np.ndarray, pose: np.ndarray) -> np.ndarray:
        c, s = np.cos(pose[2]), np.sin(pose[2])
        return np.column_stack(
            (c * pts[:, 0] - s * pts[:, 1] + pose[0], s * pts[:, 0] + c * pts[:, 1] + pose[1])
        )

    def _search(
        self, pts: np.ndarray, prior: np.ndarray, wxy: float, wth: float
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """Candidate poses sorted by cost (best first), from the two-level search."""
        p, f = self.params, self.field
        res = f.frame.resolution
        tau = p.truncation
        if len(pts) > p.search_points:
            pts = pts[np.linspace(0, len(pts) - 1, p.search_points).round().astype(np.intp)]
        ranges = np.hypot(pts[:, 0], pts[:, 1])
        sxy = min(p.coarse_xy, 2 * wxy) if wxy > 0 else p.coarse_xy
        sxy = max(res, round(sxy / res) * res)  # whole pixels: translations become index offsets
        sth = min(p.coarse_theta, 2 * wth) if wth > 0 else p.coarse_theta
        nxy = int(np.floor(wxy / sxy + 1e-9))
        nth = int(np.floor(wth / sth + 1e-9))
        ths = prior[2] + sth * np.arange(-nth, nth + 1)
        if wth >= np.pi - 1e-9:  # full turn: no duplicate at ±pi
            ths = ths[: int(round(2 * np.pi / sth))]
        offs = sxy * np.arange(-nxy, nxy + 1)
        # coarse: nearest-pixel |d| at cell centres, and a Lipschitz lower bound per cell
        slack = ((sxy / 2) * np.sqrt(2.0) + ranges * (sth / 2) + res).astype(np.float32)
        cost_c, lb_c = self._grid_costs(pts, prior[:2], ths, offs, slack, tau)
        # a faint pull towards the prior breaks ties along flat (degenerate) directions
        eps = p.prior_tiebreak
        sq = (offs / max(wxy, res)) ** 2
        pen = eps * (((ths - prior[2]) / max(wth, 1e-3)) ** 2)[:, None, None] + eps * (
            sq[None, :, None] + sq[None, None, :]
        )
        cost_c = cost_c + pen
        lb_c = lb_c + pen
        flat_cost = cost_c.reshape(-1)
        flat_lb = lb_c.reshape(-1)
        upper = flat_cost.min()
        order = np.argsort(flat_lb, kind="stable")
        promising = order[flat_lb[order] <= upper][: p.expand]
        best_centre = int(np.argmin(flat_cost))
        if best_centre not in promising:
            promising = np.append(promising[: p.expand - 1], best_centre)
        ti, xi, yi = np.unravel_index(promising, cost_c.shape)
        # fine: children of the promising cells
        kxy, kth = p.fine_splits
        cxy = sxy * ((np.arange(kxy) + 0.5) / kxy - 0.5)
        cth = sth * ((np.arange(kth) + 0.5) / kth - 0.5)
        child = np.stack(np.meshgrid(cxy, cxy, cth, indexing="ij"), axis=-1).reshape(-1, 3)
        centres = np.column_stack((prior[0] + offs[xi], prior[1] + offs[yi], ths[ti]))
        fine = (centres[:, None, :] + child[None, :, :]).reshape(-1, 3)
        d = fine - prior
        fine_cost = self._pose_costs(pts, fine, tau) + eps * (
            (d[:, 0] ** 2 + d[:, 1] ** 2) / max(wxy, res) ** 2 + (d[:, 2] / max(wth, 1e-3)) ** 2
        )
        # pool: fine children then the coarse centres, best first
        coarse_poses = np.stack(
            np.meshgrid(ths, prior[0] + offs, prior[1] + offs, indexing="ij"), axis=-1
        ).reshape(-1, 3)[:, [1, 2, 0]]
        allp = np.vstack([fine, coarse_poses])
        allc = np.concatenate([fine_cost, flat_cost])
        idx = np.argsort(allc, kind="stable")[: 64 + p.competitors * 16]
        return [allp[i] for i in idx], allc[idx]

    def _grid_costs(self, pts, origin, ths, offs, slack, tau):
        """Truncated cost and its lower bound for every (θ, x, y) on a grid, nearest-pixel lookup.

        ``offs`` are whole multiples of the resolution, so every translation is an index offset.
        """
        f = self.field
        res = f.frame.resolution
        ox, oy = f.frame.origin
        h, w = f.frame.shape
        c, s = np.cos(ths)[:, None], np.sin(ths)[:, None]
        col = np.floor((c * pts[:, 0] - s * pts[:, 1] + origin[0] - ox) / res).astype(np.intp)  # (T, N)
        row = np.floor((s * pts[:, 0] + c * pts[:, 1] + origin[1] - oy) / res).astype(np.intp)
        k = np.round(offs / res).astype(np.intp)
        # padded |sdf| (one border pixel = tau) so clipping sends everything off the raster there
        cc = np.clip(col[:, None, :] + k[None, :, None] + 1, 0, w + 1)  # (T, X, N)
        rr = np.clip(row[:, None, :] + k[None, :, None] + 1, 0, h + 1)  # (T, Y, N)
        flat = rr[:, None, :, :] * (w + 2) + cc[:, :, None, :]  # (T, X, Y, N)
        d = self._abs_padded(tau).take(flat)  # already truncated at tau
        lb = np.maximum(d - slack, np.float32(0.0))
        n = pts.shape[0] * tau * tau
        return np.einsum("...n,...n->...", d, d) / n, np.einsum("...n,...n->...", lb, lb) / n

    def _abs_padded(self, tau: float) -> np.ndarray:
        """Flat |sdf| (float32) with a one-pixel border of ``tau`` (cached)."""
        if self._padded is None or self._padded[0] != tau:
            a = np.pad(np.abs(self.field.sdf), 1, constant_values=np.float32(tau))
            self._padded = (tau, np.minimum(a, np.float32(tau)).reshape(-1))
        return self._padded[1]

    def _pose_costs(self, pts, poses, tau):
        f = self.field
        res = f.frame.resolution
        ox, oy = f.frame.origin
        h, w = f.frame.shape
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        col = np.floor((c * pts[:, 0] - s * pts[:, 1] + poses[:, :1] - ox) / res).astype(np.intp)
        row = np.floor((s * pts[:, 0] + c * pts[:, 1] + poses[:, 1:2] - oy) / res).astype(np.intp)
        flat = np.clip(row + 1, 0, h + 1) * (w + 2) + np.clip(col + 1, 0, w + 1)
        d = self._abs_padded(tau).take(flat)
        return np.einsum("pn,pn->p", d, d) / (pts.shape[0] * tau * tau)

    def _residuals(self, pts: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (N,) and Jacobians (N, 3) wrt (x, y, θ) of the field at the points."""
        w = self._transform(pts, pose)
        look = self.field.lookup(w, outside=-self.params.truncation)
        r, g = look[:, 0], look[:, 1:]
        dx, dy = w[:, 0] - pose[0], w[:, 1] - pose[1]
        jac = np.column_stack((g[:, 0], g[:, 1], -g[:, 0] * dy + g[:, 1] * dx))
        return r, jac

    def _refine(self, pts: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, float]:
        """Levenberg-Marquardt with a Tukey kernel; returns (pose, soft score)."""
        p = self.params
        pose = np.asarray(start, dtype=np.float64).copy()
        lam = 1e-3
        r, jac = self._residuals(pts, pose)
        for it in range(p.lm_iterations):
            tau = p.truncation if it < 3 else 0.5 * p.truncation
            w = tukey_weights(r, tau)
            if w.sum() < 3:
                break
            jw = jac * w[:, None]
            h = jw.T @ jac
            b = jw.T @ r
            cost0 = float(np.sum(w * r * r))
            step = -np.linalg.solve(h + lam * (np.diag(np.diag(h)) + 1e-9 * np.eye(3)), b)
            step[:2] *= min(1.0, 0.2 / max(np.hypot(*step[:2]), 1e-12))
            step[2] = np.clip(step[2], -0.05, 0.05)
            cand = pose + step
            r2, jac2 = self._residuals(pts, cand)
            cost1 = float(np.sum(w * r2 * r2))
            if cost1 <= cost0:
                pose, r, jac = cand, r2, jac2
                lam = max(lam * 0.3, 1e-6)
                # converged: the step is far below the sensor noise, or the cost stalls
                # (kernel width changes after iteration 3, so never stop before it)
                small = np.hypot(*step[:2]) < 2e-3 and abs(step[2]) < 3e-4
                if it >= 3 and (small or cost0 - cost1 <= 1e-4 * cost0):
                    break
            else:
                lam *= 10.0
                if lam > 1e4:
                    break
        if abs(pose[2]) > np.pi:  # wrapping changes nothing but the angle's representation
            pose[2] = wrap(pose[2])
        return pose, _soft(r, p.truncation)

    def _covariance(self, pts: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """σ² H⁻¹ from the inliers at ``pose``, inflated, floored and capped per direction; and the
        covariance reported, which adds the plan's drawing error (:meth:`drawn_off`): σ_d² W H⁻¹,
        W the inliers' total weight (an offset every point shares, the geometry's H)."""
        p = self.params
        r, jac = self._residuals(pts, pose)
        w = tukey_weights(r, 0.5 * p.truncation)
        h = (jac * w[:, None]).T @ jac
        wsum = float(w.sum())
        dof = max(wsum - 3.0, 1.0)
        sigma2 = max(float(np.sum(w * r * r)) / dof, p.sensor_sigma**2)
        evals, evecs = np.linalg.eigh(h)
        cap = np.array([p.max_sigma_xy**2, p.max_sigma_xy**2, p.max_sigma_theta**2])
        inv = np.where(evals > 1e-12, 1.0 / np.maximum(evals, 1e-12), 1e12)
        floor = np.diag([p.sigma_floor_xy**2, p.sigma_floor_xy**2, p.sigma_floor_theta**2])

        def covariance(scale: np.ndarray) -> np.ndarray:
            cov = _cap_covariance((evecs * (scale * inv)) @ evecs.T, cap) + floor
            return 0.5 * (cov + cov.T)

        cov = covariance(sigma2 * p.cov_inflation)
        if self.drawing_sigma <= 0.0:
            return cov, cov
        return cov, covariance(sigma2 * p.cov_inflation + self.drawing_sigma**2 * max(wsum, 1.0))


# --------------------------------------------------------------------------- helpers
def relocalise(
    points: np.ndarray, plan, prior: np.ndarray, params: RelocaliserParams | None = None, **kw
) -> Relocalisation:
    """One-shot :meth:`Relocaliser.relocalise` (builds the plan's field; keep a
    :class:`Relocaliser` to reuse it)."""
    window_xy = kw.pop("window_xy", None)
    window_theta = kw.pop("window_theta", None)
    return Relocaliser(plan, params, **kw).relocalise(points, prior, window_xy, window_theta)


def subsample(points: np.ndarray, voxel: float, max_points: int) -> np.ndarray:
    """Finite points, one per ``voxel`` cell (the first), at most ``max_points`` spread evenly."""
    pts = points[np.all(np.isfinite(points), axis=1)]
    if not len(pts):
        return pts
    keys = np.floor(pts / voxel).astype(np.int64)
    _, first = np.unique(keys[:, 0] * 1_000_003 + keys[:, 1], return_index=True)
    # keep the scan's angular order so an even stride spreads the points around the robot
    first.sort()
    pts = pts[first]
    if len(pts) > max_points:
        pts = pts[np.linspace(0, len(pts) - 1, max_points).round().astype(np.intp)]
    return pts


def tukey_weights(r: np.ndarray, tau: float) -> np.ndarray:
    """Tukey (biweight) weights of residuals ``r`` (zero beyond ``tau``)."""
    a = np.abs(r) / tau
    return np.where(a < 1.0, (1.0 - a * a) ** 2, 0.0)


def _soft(r: np.ndarray, tau: float) -> float:
    a = np.minimum(np.abs(r) / tau, 1.0)
    return float(np.mean(1.0 - a * a))


def _pose_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.asarray(a, float) - np.asarray(b, float)
    d[2] = wrap(d[2])
    return d


def _cap_covariance(cov: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """Scale rows/columns so no variance exceeds ``cap`` (keeps correlations, stays PSD)."""
    d = np.sqrt(np.maximum(np.diag(cov), 1e-30))
    s = np.minimum(1.0, np.sqrt(cap) / d)
    return cov * s[:, None] * s[None, :]


__all__ = [
    "PlanField",
    "Relocalisation",
    "Relocaliser",
    "RelocaliserParams",
    "free_space_polygons",
    "relocalise",
    "subsample",
]
