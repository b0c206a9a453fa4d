"""Sub-pixel refinement of a plan -> map registration on the map's free-space signed distance.

The map's free space F (full resolution) gives a signed distance field ``sdf`` in metres
(positive inside free space, zero on the free/non-free pixel edges, bilinear in between). A plan
room's boundary lies a constant ``delta`` *outside* the free space it encloses: the wall's
half-thickness for plans drawn on wall centre lines (R2V), about zero for room-segmentation plans.
Boundary points ``p`` of the plan rooms (plan units) are mapped by

    q = R(theta) · diag(1, ±1) · diag(exp(lsx), exp(lsy)) · p + t        (map metres)

and the residual ``r = sdf(q + delta · n)`` vanishes when the point, moved by ``delta`` along the
room's inward normal ``n`` (rotated into the map), lands on the free-space edge *of its own room*:
the crisp side of a wall, whatever the wall's thickness or whether its other side was seen.
Parameters
``(theta, tx, ty, lsx, lsy, delta)`` are estimated by iteratively reweighted Gauss-Newton with
Levenberg damping and Cauchy weights; a point counts only when the map is free two cells further
into its room, so the unexplored rooms of the plan (and the far side of walls) do not pull. The covariance of ``(tx, ty, theta)`` is ``sigma² (JᵀWJ)⁻¹``
(scales and delta marginalised), in metres and radians.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from frslam_graph.registration.result import matrix_from_params


@dataclass(frozen=True)
class DistanceField:
    """Bilinear fields over a pixel grid (row 0 = lowest y): ``sdf`` (metres) and ``known`` (0..1),
    here the free-space indicator: a point counts when the room side of it is free space."""

    sdf: np.ndarray
    known: np.ndarray
    resolution: float
    origin: tuple[float, float]

    @classmethod
    def from_masks(cls, free: np.ndarray, resolution: float, origin) -> DistanceField:
        """Signed distance to the edge of ``free`` (bool), and ``free`` as a float field."""
        free = np.ascontiguousarray(free, dtype=bool)
        f = free.view(np.uint8)  # bool is one byte of 0 / 1
        # 3x3-mask distances: both sides alike, so the zero crossing stays on the pixel edges
        d_in = cv2.distanceTransform(f, cv2.DIST_L2, cv2.DIST_MASK_3)
        d_out = cv2.distanceTransform(1 - f, cv2.DIST_L2, cv2.DIST_MASK_3)
        # np.where(free, d_in - 0.5, 0.5 - d_out) * resolution, in place (float32 throughout)
        sdf = np.subtract(d_in, np.float32(0.5), out=d_in)
        np.copyto(sdf, np.subtract(np.float32(0.5), d_out, out=d_out), where=~free)
        sdf *= np.float32(resolution)
        kn = free.astype(np.float32)
        return cls(sdf, kn, float(resolution), (float(origin[0]), float(origin[1])))

    def _cells(self, x: np.ndarray, y: np.ndarray):
        h, w = self.sdf.shape
        inv = 1.0 / self.resolution
        # (x - origin) * inv - 0.5, then np.clip's values by maximum / minimum (no -0.0 arises
        # here, NaN propagates alike), in place: the same roundings, less call overhead
        u = _offset_scaled(x, self.origin[0], inv)
        u -= 0.5
        v = _offset_scaled(y, self.origin[1], inv)
        v -= 0.5
        inside = (u >= 0) & (v >= 0) & (u < w - 1) & (v < h - 1)
        u = np.minimum(np.maximum(u, 0.0, out=u), w - 1.0001, out=u)
        v = np.minimum(np.maximum(v, 0.0, out=v), h - 1.0001, out=v)
        i0 = u.astype(np.intp)
        j0 = v.astype(np.intp)
        return j0 * w + i0, u - i0, v - j0, inside

    def sample(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """At points (x, y): bilinear sdf value, its gradient (gx, gy), and 1/0 inside/outside the grid."""
        k, fx, fy, inside = self._cells(x, y)
        return (*self._bilinear(k, fx, fy), inside)

    def sample_free(
        self, x: np.ndarray, y: np.ndarray, fx: np.ndarray, fy: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`sample` at (x, y) and :meth:`free_at` at (fx, fy) (arrays of one length), the
        cells of both found in one pass: the same values, element by element."""
        n = len(x)
        k, cx, cy, inside = self._cells(np.concatenate([x, fx]), np.concatenate([y, fy]))
        val, gx, gy = self._bilinear(k[:n], cx[:n], cy[:n])
        return val, gx, gy, inside[:n], self._free(k[n:], cx[n:], cy[n:], inside[n:])

    def _bilinear(self, k: np.ndarray, fx: np.ndarray, fy: np.ndarray):
        """sdf value and gradient at cells ``k`` with fractions (fx, fy) (:meth:`_cells`)."""
        w = self.sdf.shape[1]
        # the four corner values, each gathered contiguous (a (N, 4) gather left them strided)
        flat = self.sdf.ravel()
        v00, v10, v01, v11 = flat[k], flat[k + 1], flat[k + w], flat[k + (w + 1)]
        a = v10 - v00
        b = v11 - v01
        top = v00 + fx * a
        bot = v01 + fx * b
        d = bot - top
        val = top + fy * d
        gx = (a + fy * (b - a)) * (1.0 / self.resolution)
        gy = d * (1.0 / self.resolution)
        return val, gx, gy

    def _free(self, k: np.ndarray, fx: np.ndarray, fy: np.ndarray, inside: np.ndarray) -> np.ndarray:
        """Bilinear free indicator at cells ``k`` with fractions (fx, fy) (:meth:`_cells`)."""
        w = self.sdf.shape[1]
        flat = self.known.ravel()
        v00, v10, v01, v11 = flat[k], flat[k + 1], flat[k + w], flat[k + (w + 1)]
        top = v00 + fx * (v10 - v00)
        bot = v01 + fx * (v11 - v01)
        return (top + fy * (bot - top)) * inside

    def free_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear free indicator at points (x, y) (0 outside the grid)."""
        return self._free(*self._cells(x, y))


def _offset_scaled(v: np.ndarray, o: float, inv: float) -> np.ndarray:
    """``(v - o) * inv`` as a new array; ``v * inv`` when ``o`` is +0.0 (``v - 0.0`` is ``v`` for
    every float, -0.0 and NaN included: the same values, one pass fewer)."""
    if o == 0.0 and math.copysign(1.0, o) > 0:
        return v * inv
    out = v - o
    out *= inv
    return out


@dataclass
class RefineResult:
    """Refined parameters and fit statistics."""

    flipped: bool
    theta: float
    tx: float
    ty: float
    sx: float
    sy: float
    delta: float
    rms: float  # weighted RMS residual (m)
    inliers: float  # share of known-area points within 2 pixels of the walls
    n_points: int
    covariance: np.ndarray | None  # (x, y, theta)
    covariance_full: np.ndarray | None  # (theta, tx, ty, lsx, lsy, delta)
    pre: np.ndarray | None = None  # 3×3 applied to plan points before the parametrised transform
    # the last matrix and what it was computed from (see :attr:`matrix`)
    _matrix: tuple | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def matrix(self) -> np.ndarray:
        """The 3×3 placement (plan -> map) of the parameters, times ``pre``: a new array each time,
        computed once while the parameters and ``pre`` stay the same objects."""
        key = (self.flipped, self.theta, self.sx, self.sy, self.tx, self.ty, self.pre)
        got = self._matrix
        if got is None or not all(map(operator.is_, got[0], key)):  # identity: -0.0, NaN as they are
            m = matrix_from_params(*key[:6])
            got = self._matrix = (key, m if self.pre is None else m @ self.pre)
        return got[1].copy()

    def __getstate__(self) -> dict:
        """Pickled without the matrix kept by :attr:`matrix`."""
        state = dict(self.__dict__)
        state["_matrix"] = None
        return state


def refine(
    points: np.ndarray,
    normals: np.ndarray,
    field: DistanceField,
    flipped: bool,
    theta: float,
    tx: float,
    ty: float,
    sx: float,
    sy: float,
    *,
    delta: float = 0.0,
    delta_sigma: float = 0.1,
    delta_bounds: tuple[float, float] = (-0.1, 0.25),
    correlation: float = 1.0,
    fixed_delta_stages: int = 1,
    scales: tuple[float, ...] = (0.4, 0.15, 0.05),
    iterations: int = 8,
    map_walls: np.ndarray | None = None,
) -> RefineResult:
    """Gauss-Newton/LM on boundary ``points`` (N, 2, plan units) with unit inward ``normals``
    (N, 2, plan frame); see the module docstring.

    ``scales``: Cauchy scales (metres) of successive stages, coarse to fine (the last is floored
    at two pixels). ``delta`` starts at the given value with a Gaussian prior of ``delta_sigma``;
    it is held fixed in the first ``fixed_delta_stages`` stages (wide robust scales would trade it
    against the scales). ``correlation``: how many neighbouring points share one independent error
    (inflates the covariance).

    ``map_walls`` (K, 2, map metres; e.g. the map's wall-side free cells): a second, map-to-plan
    term. The boundary term alone is one-sided: a sample deep in free space (a doorway, a wall
    drawn off the building, free space seen through a window) keeps pulling outward through the
    Cauchy tail, while a sample pushed beyond the map's wall loses its room-side free test and
    stops pulling back, so the scales drift up (Halmstad E5: +1..+5 %). Each map wall cell must
    lie ``delta`` + half a cell inside the room from the line of a near plan boundary sample (the
    best of the :data:`WALL_NEIGHBOURS` nearest; the same Cauchy scale, which also bounds the pull
    of furniture and clutter); an over-scaled plan leaves them unexplained. The two terms get
    equal total weight (the cells' weights scaled by the number of boundary samples that count
    over K).
    """
    p = np.asarray(points, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    f = -1.0 if flipped else 1.0
    x = np.array([theta, tx, ty, np.log(sx), np.log(sy), delta], dtype=np.float64)
    delta0 = float(delta)
    res = field.resolution
    lam = 1e-3
    prior_w = (0.5 * field.resolution / delta_sigma) ** 2
    probe = 2.0 * field.resolution  # the room side of a point, this far inside its free edge
    jtj = None
    stage_scales = [max(s, 2.0 * res) for s in scales]
    w_all = np.zeros(len(p))
    r = np.zeros(len(p))
    # the columns contiguous: the same element operations, on unit strides
    px, py = np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1])
    n0, n1 = np.ascontiguousarray(nrm[:, 0]), f * nrm[:, 1]
    jac = np.empty((len(p), 6))
    # the plan samples' k-d tree (plan frame, scaled as started): map wall cells' candidates
    tree = cKDTree(p * np.array([sx, sy])) if map_walls is not None and len(p) else None
    # convergence: steps under 2e-4 m, 2e-6 rad, 2e-5 in the log scales; 10x those two-sided (its
    # candidates, renewed every third iteration, keep it hopping by ~0.3 mm: it rarely went under)
    tol = 1.0 if map_walls is None else 10.0
    if map_walls is not None:
        wall_x, wall_y = map_walls[:, 0], map_walls[:, 1]
        k_walls = min(WALL_NEIGHBOURS, len(p))
    for stage, c in enumerate(stage_scales):
        free_delta = stage >= fixed_delta_stages
        kn = cand = None
        for it in range(iterations):
            cth, sth = math.cos(x[0]), math.sin(x[0])
            # plan point scaled and flipped: (ex * px, f * ey * py), then rotated
            ax = math.exp(x[3]) * px
            ay = (f * math.exp(x[4])) * py
            # inward normal in the map (rotation and flip only)
            nx = cth * n0 - sth * n1
            ny = sth * n0 + cth * n1
            bx = cth * ax - sth * ay
            by = sth * ax + cth * ay
            # the point moved by t, then along its normal: (bx + tx) + delta * nx, as written out
            mx, my = bx + x[1], by + x[2]
            qx = mx + x[5] * nx
            qy = my + x[5] * ny
            if kn is None or it % 3 == 0:  # which points see free space on their room side
                d = x[5] + probe
                r, gx, gy, inside, kn = field.sample_free(qx, qy, mx + d * nx, my + d * ny)
            else:
                r, gx, gy, inside = field.sample(qx, qy)
            w_all = kn * inside / (1.0 + (r * (1.0 / c)) ** 2)
            # d q / d theta = J90 (q - t)
            jac[:, 0] = gy * (qx - x[1]) - gx * (qy - x[2])
            jac[:, 1] = gx
            jac[:, 2] = gy
            jac[:, 3] = (gx * cth + gy * sth) * ax
            jac[:, 4] = (gy * cth - gx * sth) * ay
            jac[:, 5] = (gx * nx + gy * ny) if free_delta else 0.0
            jw = jac * w_all[:, None]
            jtj = jac.T @ jw
            jtr = jw.T @ r
            if map_walls is not None:
                # the cells in the plan's scaled axes, as (ax, ay): R^T (cell - t)
                dx, dy = wall_x - x[1], wall_y - x[2]
                vx, vy = cth * dx + sth * dy, cth * dy - sth * dx
                e3, e4 = math.exp(-x[3]), math.exp(-x[4])
                if cand is None or it % 3 == 0:  # candidates: the cells taken into the plan frame
                    u = np.column_stack([vx * (sx * e3), vy * (f * sy * e4)])
                    cand = tree.query(u, k=k_walls)[1].reshape(len(u), k_walls)
                jm, rm, wm = _wall_terms(vx, vy, cand, n0, n1, ax, ay, e3, e4, cth, sth, x[5] + 0.5 * res, c)
                jm[:, 5] = -1.0 if free_delta else 0.0
                wm *= float((w_all > 0).sum()) / max(len(rm), 1)  # equal total weight
                jwm = jm * wm[:, None]
                jtj = jtj + jm.T @ jwm
                jtr = jtr + jwm.T @ rm
            x, stop = _lm_step(x, jtj, jtr, w_all, prior_w, delta0, lam, delta_bounds, tol)
            if stop:
                break
    return _result(flipped, x, w_all, r, jtj, res, correlation)


def _lm_step(
    x: np.ndarray,
    jtj: np.ndarray,
    jtr: np.ndarray,
    w_all: np.ndarray,
    prior_w: float,
    delta0: float,
    lam: float,
    delta_bounds: tuple[float, float],
    tol: float,
) -> tuple[np.ndarray, bool]:
    """One damped Gauss-Newton step of :func:`refine` from the normal equations ``jtj``, ``jtr``
    (the delta prior added here, in place) and the point weights ``w_all``: (the parameters,
    whether the iterations stop: a degenerate system, or converged)."""
    # Gaussian prior on delta, relative to a residual noise of half a pixel
    jtj[5, 5] += prior_w
    jtr[5] += prior_w * (x[5] - delta0)
    if not np.isfinite(jtj).all() or w_all.sum() < 6:
        return x, True
    # jtj + lam * np.diag(np.diag(jtj) + 1e-9), without building the diagonal matrix
    # (+ 0.0 off the diagonal as there: the same bits)
    dg = jtj.diagonal()
    a = jtj + 0.0
    a.ravel()[:: len(a) + 1] = dg + lam * (dg + 1e-9)
    try:
        step = -np.linalg.solve(a, jtr)
    except np.linalg.LinAlgError:
        return x, True
    if not np.isfinite(step).all() or abs(step[3]) > 1.0 or abs(step[4]) > 1.0:
        return x, True  # a degenerate system (too few points on walls): keep the last estimate
    x = x + step
    x[5] = min(max(float(x[5]), delta_bounds[0]), delta_bounds[1])  # np.clip's value, cheaper
    return x, bool(
        abs(step[0]) < 2e-6 * tol
        and abs(step[1]) + abs(step[2]) < 2e-4 * tol
        and abs(step[3]) + abs(step[4]) < 2e-5 * tol
    )


def _result(
    flipped: bool,
    x: np.ndarray,
    w_all: np.ndarray,
    r: np.ndarray,
    jtj: np.ndarray | None,
    res: float,
    correlation: float,
) -> RefineResult:
    """:func:`refine`'s answer from the last iteration's parameters ``x``, point weights, residuals
    and normal matrix."""
    wsum = float(w_all.sum())
    n_known = int((w_all > 0).sum())
    rms = float(np.sqrt((w_all * r * r).sum() / wsum)) if wsum > 0 else float("inf")
    known_pts = w_all > 0
    inl = float((np.abs(r.compress(known_pts)) < 2.0 * res).mean()) if known_pts.any() else 0.0
    cov3 = covf = None
    if jtj is not None and n_known > 6:
        try:
            sigma2 = float((w_all * r * r).sum() / max(wsum - 6.0, 1.0))
            # residuals of neighbouring points on a wall are correlated (the map's cells along a
            # wall err together): count one independent residual per ``correlation`` points
            covf = np.linalg.inv(jtj) * sigma2 * max(1.0, correlation)
            cov3 = covf.take(_XY_THETA, axis=0).take(_XY_THETA, axis=1)  # (tx, ty, theta)
        except np.linalg.LinAlgError:
            cov3 = covf = None
    return RefineResult(
        flipped=flipped,
        theta=float(x[0]),
        tx=float(x[1]),
        ty=float(x[2]),
        sx=float(np.exp(x[3])),
        sy=float(np.exp(x[4])),
        delta=float(x[5]),
        rms=rms,
        inliers=inl,
        n_points=n_known,
        covariance=cov3,
        covariance_full=covf,
    )


@dataclass(frozen=True)
class FitStart:
    """One start of :func:`refine_many`: :func:`refine`'s arguments but the shared ones."""

    points: np.ndarray  # (N, 2) plan units
    normals: np.ndarray  # (N, 2) unit inward normals, plan frame
    flipped: bool
    theta: float
    tx: float
    ty: float
    sx: float
    sy: float
    delta: float = 0.0
    correlation: float = 1.0


def refine_many(
    starts: list[FitStart],
    field: DistanceField,
    *,
    delta_sigma: float = 0.1,
    delta_bounds: tuple[float, float] = (-0.1, 0.25),
    fixed_delta_stages: int = 1,
    scales: tuple[float, ...] = (0.4, 0.15, 0.05),
    iterations: int = 8,
) -> list[RefineResult]:
    """:func:`refine` (one-sided: no ``map_walls``) of each start, the same answers, in order.

    The starts iterate together: each iteration's point operations (transform, field lookups,
    weights, Jacobian) run once on the points of every start still iterating, element by element
    as :func:`refine` does them; the normal equations (one matrix product per start, its own
    rows: a BLAS product's bits depend on its shape) and the step per start. A start stops where
    :func:`refine` stops it; what follows runs on those still going."""
    res = field.resolution
    lam = 1e-3
    prior_w = (0.5 * res / delta_sigma) ** 2
    probe = 2.0 * res
    stage_scales = [max(c, 2.0 * res) for c in scales]
    fits = []
    for st in starts:
        p = np.asarray(st.points, dtype=np.float64)
        nrm = np.asarray(st.normals, dtype=np.float64)
        f = -1.0 if st.flipped else 1.0
        fits.append(
            {
                "f": f,
                "x": np.array(
                    [st.theta, st.tx, st.ty, np.log(st.sx), np.log(st.sy), st.delta], dtype=np.float64
                ),
                "delta0": float(st.delta),
                "cols": (
                    np.ascontiguousarray(p[:, 0]),
                    np.ascontiguousarray(p[:, 1]),
                    np.ascontiguousarray(nrm[:, 0]),
                    f * nrm[:, 1],
                ),
                "w_all": np.zeros(len(p)),
                "r": np.zeros(len(p)),
                "jtj": None,
                "kn": None,
            }
        )
    for stage, c in enumerate(stage_scales):
        free_delta = stage >= fixed_delta_stages
        going = list(range(len(fits)))
        built: list[int] | None = None
        for it in range(iterations):
            if not going:
                break
            if built != going:  # the points of the starts still iterating
                lens = [len(fits[i]["r"]) for i in going]
                ends = np.cumsum(lens).tolist()
                px, py, n0, n1 = (np.concatenate([fits[i]["cols"][j] for i in going]) for j in range(4))
                jac = np.empty((len(px), 6))
                built = list(going)
            xs = [fits[i]["x"] for i in going]
            # each start's numbers, once per point: the same operands as refine's scalars
            cth = np.repeat([math.cos(x[0]) for x in xs], lens)
            sth = np.repeat([math.sin(x[0]) for x in xs], lens)
            ax = np.repeat([math.exp(x[3]) for x in xs], lens) * px
            ay = np.repeat([fits[i]["f"] * math.exp(fits[i]["x"][4]) for i in going], lens) * py
            tx = np.repeat([x[1] for x in xs], lens)
            ty = np.repeat([x[2] for x in xs], lens)
            dl = np.repeat([x[5] for x in xs], lens)
            nx = cth * n0 - sth * n1
            ny = sth * n0 + cth * n1
            bx = cth * ax - sth * ay
            by = sth * ax + cth * ay
            mx, my = bx + tx, by + ty
            qx = mx + dl * nx
            qy = my + dl * ny
            if it % 3 == 0:  # which points see free space on their room side
                d = np.repeat([x[5] + probe for x in xs], lens)
                r, gx, gy, inside, kn = field.sample_free(qx, qy, mx + d * nx, my + d * ny)
                for i, lo, hi in zip(going, [0, *ends[:-1]], ends, strict=True):
                    fits[i]["kn"] = kn[lo:hi]
            else:
                r, gx, gy, inside = field.sample(qx, qy)
                kn = np.concatenate([fits[i]["kn"] for i in going])
            w_all = kn * inside / (1.0 + (r * (1.0 / c)) ** 2)
            # d q / d theta = J90 (q - t)
            jac[:, 0] = gy * (qx - tx) - gx * (qy - ty)
            jac[:, 1] = gx
            jac[:, 2] = gy
            jac[:, 3] = (gx * cth + gy * sth) * ax
            jac[:, 4] = (gy * cth - gx * sth) * ay
            jac[:, 5] = (gx * nx + gy * ny) if free_delta else 0.0
            jw = jac * w_all[:, None]
            still = []
            for i, lo, hi in zip(going, [0, *ends[:-1]], ends, strict=True):
                ft = fits[i]
                ft["w_all"], ft["r"] = w_all[lo:hi], r[lo:hi]
                ft["jtj"] = jtj = jac[lo:hi].T @ jw[lo:hi]
                jtr = jw[lo:hi].T @ r[lo:hi]
                ft["x"], stop = _lm_step(
                    ft["x"], jtj, jtr, ft["w_all"], prior_w, ft["delta0"], lam, delta_bounds, 1.0
                )
                if not stop:
                    still.append(i)
            going = still
    return [
        _result(st.flipped, ft["x"], ft["w_all"], ft["r"], ft["jtj"], res, st.correlation)
        for st, ft in zip(starts, fits, strict=True)
    ]


# the rows / columns (tx, ty, theta) of the full covariance (theta, tx, ty, lsx, lsy, delta)
_XY_THETA = np.array([1, 2, 0])

# map wall cells matched to the best of this many nearest plan boundary samples (:func:`_wall_terms`)
WALL_NEIGHBOURS = 4


def _wall_terms(
    vx: np.ndarray,
    vy: np.ndarray,
    jj: np.ndarray,
    n0: np.ndarray,
    n1: np.ndarray,
    ax: np.ndarray,
    ay: np.ndarray,
    e3: float,
    e4: float,
    cth: float,
    sth: float,
    off: float,
    c: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map-to-plan term of :func:`refine`: (K, 6) Jacobian (its delta column left to the caller),
    (K,) residuals (metres) and Cauchy weights of the map wall cells, given turned into the plan's
    scaled axes (``vx``, ``vy``: R^T (cell - t), metres), against the lines of plan boundary
    samples (``ax``, ``ay``: scaled and flipped plan coordinates; ``n0``, ``n1``: plan normals,
    flipped; the lines' normals scale by ``e3``, ``e4`` = exp(-log scales)): of each cell's
    candidates ``jj`` (K, k sample indices, the nearest), the one whose line and side fit best (a
    wall between two plan rooms has samples of both on its centre line, with opposite normals). A
    wall cell's centre lies ``off`` (delta + half a cell) inside the room from the boundary. The
    same as in the map frame (a rotation keeps distances and cross products), fewer operations."""
    mx, my = n0[jj] * e3, n1[jj] * e4
    nl = np.maximum(np.hypot(mx, my), 1e-12)
    axj, ayj = ax[jj], ay[jj]
    sdk = ((vx[:, None] - axj) * mx + (vy[:, None] - ayj) * my) / nl
    # the best candidate of each cell, as a flat index into the (K, k) arrays
    pick = np.argmin(np.abs(sdk - off), axis=1) + np.arange(0, sdk.size, sdk.shape[1])
    rm = sdk.take(pick) - off
    nlj = nl.take(pick)
    mxj, myj = mx.take(pick) / nlj, my.take(pick) / nlj  # the line's unit normal (scaled axes)
    axp, ayp = axj.take(pick), ayj.take(pick)
    jm = np.empty((len(rm), 6))
    jm[:, 0] = mxj * ayp - myj * axp
    jm[:, 1] = sth * myj - cth * mxj
    jm[:, 2] = -(sth * mxj + cth * myj)
    jm[:, 3] = -mxj * axp
    jm[:, 4] = -myj * ayp
    return jm, rm, 1.0 / (1.0 + (rm * (1.0 / c)) ** 2)


def ring_edges(rings: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All edges of closed rings (first point not repeated): starts (E, 2), ends (E, 2), ring index (E,)."""
    a = np.concatenate(rings).astype(np.float64)
    sizes = np.array([len(r) for r in rings])
    first = np.cumsum(sizes) - sizes
    nxt = np.arange(len(a)) + 1
    nxt[first + sizes - 1] = first  # close each ring
    return a, a[nxt], np.repeat(np.arange(len(rings)), sizes)


def sample_boundaries(
    rings: list[np.ndarray], step: float, doors: np.ndarray | None = None, door_tol: float = 0.0
):
    """Points every ``step`` (plan units) along closed rings, minus those on door segments.

    Rings must have their room on the left (exterior counter-clockwise, holes clockwise).
    ``doors``: (D, 4) segments x1 y1 x2 y2; points within ``door_tol`` of a door are dropped.
    Returns (N, 2) points, (N, 2) unit inward normals and (N,) ring indices.
    """
    if not rings:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int)
    a, b, ring = ring_edges(rings)
    seg = b - a
    length = np.hypot(seg[:, 0], seg[:, 1])
    count = np.where(length > 0, np.maximum(1, np.ceil(length / step)), 0).astype(np.intp)
    total = int(count.sum())
    e = np.repeat(np.arange(len(a)), count)
    start = np.repeat(np.cumsum(count) - count, count)
    t = (np.arange(total) - start + 0.5) / count[e]
    p = a[e] + seg[e] * t[:, None]
    unit = seg / np.maximum(length, 1e-300)[:, None]
    nr = np.column_stack([-unit[e, 1], unit[e, 0]])
    o = ring[e]
    if doors is not None and len(doors) and door_tol > 0:
        d = np.asarray(doors, dtype=np.float64).reshape(-1, 4)
        a0, u = d[None, :, :2], d[None, :, 2:] - d[None, :, :2]
        l2 = np.maximum((u * u).sum(axis=-1), 1e-300)
        rel = p[:, None, :] - a0
        t = np.clip((rel * u).sum(axis=-1) / l2, 0.0, 1.0)
        dist = np.hypot(rel[..., 0] - t * u[..., 0], rel[..., 1] - t * u[..., 1])
        keep = np.all(dist > door_tol, axis=1)
        p, nr, o = p[keep], nr[keep], o[keep]
    return p, nr, o
