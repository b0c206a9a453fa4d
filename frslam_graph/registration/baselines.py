"""Classical image-registration baselines for floor plan -> occupancy grid (paper Table I rows).

* :func:`register_features` with ORB, SIFT or AKAZE: keypoints + descriptors on both images,
  brute-force k-NN matching with Lowe's ratio test, then a full affine (6 dof, so it can express
  flip and aspect) by RANSAC (``cv2.estimateAffine2D``). Descriptors are not mirror-invariant,
  so the plan is also tried mirrored (``try_mirror``) and the hypothesis with more inliers wins.
* :func:`register_ecc`: ``cv2.findTransformECCWithMask`` (MOTION_AFFINE), multi-start over the 8
  dihedral initialisations (plan bounding box fitted onto the map's free-space bounding box),
  on an image pyramid: every start at the coarsest level, the best ``refine_top`` refined on
  the finer levels; the template mask is the map's observed area.

Images share one look: free space / room interiors white, walls / outside / unknown black,
row 0 = lowest y. The map image is the grid cropped to its observed cells; the full plan is
rasterised at a resolution that makes its bounding-box diagonal as long, in pixels, as the
map's. Results are plan coordinates -> map metres (3×3), decomposed by
:meth:`Registration.from_matrix`. Failures return ``ok == False`` with a reason, never raise.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from frslam_graph.raster import RasterFrame, rasterise_polygons
from frslam_graph.registration.paper import DIHEDRAL
from frslam_graph.registration.result import Registration, matrix_from_params
from frslam_graph.se2 import to_matrix

__all__ = [
    "BASELINES",
    "MapImage",
    "PlanImage",
    "map_image",
    "plan_image",
    "register_akaze",
    "register_ecc",
    "register_features",
    "register_orb",
    "register_sift",
]


@dataclass(frozen=True)
class MapImage:
    """Grid cropped to its observed cells. ``px_to_map``: cv2 pixel coords (centre of pixel (c, r)
    at (c, r)) -> map metres."""

    image: np.ndarray  # uint8, 255 free, 0 otherwise
    known: np.ndarray  # uint8, 255 observed (free or occupied)
    px_to_map: np.ndarray
    free_bbox: tuple[int, int, int, int]  # (c0, r0, c1, r1) of free pixels, inclusive-exclusive

    def scaled(self, f: float) -> MapImage:
        """The same map resampled by factor ``f`` (< 1 shrinks); transforms kept consistent."""
        h, w = self.image.shape
        size = (max(1, round(w * f)), max(1, round(h * f)))
        fx, fy = size[0] / w, size[1] / h
        img = cv2.resize(self.image, size, interpolation=cv2.INTER_AREA)
        known = cv2.resize(self.known, size, interpolation=cv2.INTER_NEAREST)
        # cv2 coords: x_s = (x + 0.5) * f - 0.5
        back = np.array([[1 / fx, 0, 0.5 / fx - 0.5], [0, 1 / fy, 0.5 / fy - 0.5], [0, 0, 1.0]])
        c0, r0, c1, r1 = self.free_bbox
        bbox = (int(c0 * fx), int(r0 * fy), max(int(round(c1 * fx)), 1), max(int(round(r1 * fy)), 1))
        return MapImage(img, known, self.px_to_map @ back, bbox)


@dataclass(frozen=True)
class PlanImage:
    """Full plan rasterised; ``plan_to_px``: plan coordinates -> cv2 pixel coords."""

    image: np.ndarray  # uint8, 255 inside rooms, 0 on room borders / outside
    plan_to_px: np.ndarray


def map_image(grid: Any, margin: int = 4) -> MapImage | None:
    """The observed part of ``grid`` as an image, or None when nothing is free."""
    data = np.asarray(grid.data)
    known = data >= 0
    free = (data >= 0) & (data < 50)
    if not free.any():
        return None
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    r0, r1 = max(rows[0] - margin, 0), min(rows[-1] + 1 + margin, data.shape[0])
    c0, c1 = max(cols[0] - margin, 0), min(cols[-1] + 1 + margin, data.shape[1])
    img = (free[r0:r1, c0:c1] * 255).astype(np.uint8)
    kn = (known[r0:r1, c0:c1] * 255).astype(np.uint8)
    fr, fc = np.flatnonzero(img.any(axis=1)), np.flatnonzero(img.any(axis=0))
    ox, oy, *rest = (float(v) for v in grid.origin)
    yaw = rest[0] if rest else 0.0
    res = float(grid.resolution)
    world = to_matrix((ox, oy, yaw))
    px = np.array([[res, 0, res * (c0 + 0.5)], [0, res, res * (r0 + 0.5)], [0, 0, 1.0]])
    return MapImage(img, kn, world @ px, (int(fc[0]), int(fr[0]), int(fc[-1] + 1), int(fr[-1] + 1)))


def plan_image(plan: Any, target_diag_px: float, wall_px: int = 2, max_side: int = 1500) -> PlanImage:
    """Rasterise the full plan with its bounding-box diagonal ≈ ``target_diag_px`` pixels; room
    borders are drawn black ``wall_px`` wide (the map's walls are not free either)."""
    minx, miny, maxx, maxy = plan.bounds
    diag = math.hypot(maxx - minx, maxy - miny)
    res = diag / max(target_diag_px, 16.0)
    res = max(res, max(maxx - minx, maxy - miny) / max_side)
    frame = RasterFrame.around((minx, miny, maxx, maxy), res, margin=4 * res)
    polys = [r.polygon for r in plan.rooms]
    img = rasterise_polygons(polys, frame) * 255
    to_px = frame.pixel_matrix()
    rings = []
    for p in polys:
        for ring in [p.exterior, *p.interiors]:
            xy = np.asarray(ring.coords) @ to_px[:2, :2].T + to_px[:2, 2] - 0.5
            rings.append(np.round(xy * 16).astype(np.int32).reshape(-1, 1, 2))
    if wall_px > 0:
        cv2.polylines(img, rings, True, 0, thickness=wall_px, lineType=cv2.LINE_8, shift=4)
        # doors between two rooms are open in a LiDAR map: open them in the plan image too
        segs = [
            np.array([d.a, d.b], float) @ to_px[:2, :2].T + to_px[:2, 2] - 0.5
            for d in getattr(plan, "doors", ())
            if len(set(d.rooms)) == 2
        ]
        if segs:
            lines = [np.round(sg * 16).astype(np.int32).reshape(-1, 1, 2) for sg in segs]
            cv2.polylines(img, lines, False, 255, thickness=wall_px + 2, lineType=cv2.LINE_8, shift=4)
            img[rasterise_polygons(polys, frame) == 0] = 0  # never open a door to the outside
    shift = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])
    return PlanImage(np.ascontiguousarray(img), shift @ to_px)


def _prepare(
    plan: Any, grid: Any, method: str, t0: float, max_side: int = 0
) -> tuple[MapImage, PlanImage] | Registration:
    if len(plan.rooms) == 0:
        return Registration.failure("plan has no rooms", method=method, time_s=time.perf_counter() - t0)
    mi = map_image(grid)
    if mi is None:
        return Registration.failure(
            "map has no free cells (empty or all unknown)", method=method, time_s=time.perf_counter() - t0
        )
    if max_side and max(mi.image.shape) > max_side:
        mi = mi.scaled(max_side / max(mi.image.shape))
    h, w = mi.image.shape
    return mi, plan_image(plan, math.hypot(h, w))


def _h(a: np.ndarray) -> np.ndarray:
    return np.vstack([a, [0.0, 0.0, 1.0]])


def _make_detector(kind: str) -> tuple[Any, int]:
    if kind == "orb":
        return cv2.ORB_create(nfeatures=3000), cv2.NORM_HAMMING
    if kind == "sift":
        return cv2.SIFT_create(nfeatures=3000), cv2.NORM_L2
    if kind == "akaze":
        # OpenCV 5 moved AKAZE out of the main modules (opencv-contrib's xfeatures2d has it)
        create = getattr(cv2, "AKAZE_create", None) or getattr(
            getattr(cv2, "xfeatures2d", None), "AKAZE_create", None
        )
        if create is None:
            raise ValueError(
                f"AKAZE is not available in this OpenCV build ({cv2.__version__}); install opencv-contrib"
            )
        return create(), cv2.NORM_HAMMING
    raise ValueError(f"unknown feature type {kind!r}")


def register_features(
    plan: Any,
    grid: Any,
    kind: str = "orb",
    ratio: float = 0.9,
    ransac_px: float = 4.0,
    min_inliers: int = 6,
    try_mirror: bool = True,
    blur: float = 1.5,
    pad: int = 32,
    scales: tuple[float, ...] = (1.0,),
    **_: Any,
) -> Registration:
    """Feature matching + RANSAC affine (``kind`` in orb / sift / akaze). See module docstring.

    ``scales``: plan renderings relative to the map-diagonal match (several = multi-scale).
    """
    t0 = time.perf_counter()
    prep = _prepare(plan, grid, kind, t0)
    if isinstance(prep, Registration):
        return prep
    mi, pi = prep

    def fail(reason: str, **details: Any) -> Registration:
        return Registration.failure(reason, method=kind, time_s=time.perf_counter() - t0, **details)

    try:
        det, norm = _make_detector(kind)
    except ValueError as exc:
        return fail(str(exc))

    # pad: ORB/SIFT ignore a border band (ORB's edgeThreshold is 31 px), which on a small
    # partial map is most of the image
    def prepare(img: np.ndarray) -> np.ndarray:
        img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
        return cv2.GaussianBlur(img, (0, 0), blur) if blur > 0 else img

    kp_m, des_m = det.detectAndCompute(prepare(mi.image), None)
    if des_m is None or len(kp_m) < 3:
        return fail(f"only {0 if des_m is None else len(kp_m)} keypoints in the map image")
    pts_m = np.float32([k.pt for k in kp_m])
    matcher = cv2.BFMatcher(norm)
    unpad = np.array([[1, 0, -pad], [0, 1, -pad], [0, 0, 1.0]])
    hyps: list[tuple[int, np.ndarray, int]] = []  # (inliers, plan -> map metres 3x3, n matches)
    diag = math.hypot(*mi.image.shape)
    for scale in scales:
        pi_s = pi if scale == 1.0 else plan_image(plan, diag * scale)
        plan_img = prepare(pi_s.image)
        hp = plan_img.shape[0]
        variants = [(False, plan_img)] + (
            [(True, np.ascontiguousarray(plan_img[::-1]))] if try_mirror else []
        )
        for mirrored, img in variants:
            kp_p, des_p = det.detectAndCompute(img, None)
            if des_p is None or len(kp_p) < 3:
                continue
            knn = matcher.knnMatch(des_p, des_m, k=2)
            good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
            if len(good) < 3:
                continue
            src = np.float32([kp_p[m.queryIdx].pt for m in good])
            dst = pts_m[[m.trainIdx for m in good]]
            a, inl = cv2.estimateAffine2D(
                src, dst, method=cv2.RANSAC, ransacReprojThreshold=ransac_px, maxIters=3000, confidence=0.995
            )
            if a is None or inl is None:
                continue
            m3 = _h(a)
            if mirrored:  # mirrored px (c, r) = (c, hp - 1 - r) of the original
                m3 = m3 @ np.array([[1, 0, 0], [0, -1, hp - 1], [0, 0, 1.0]])
            m3 = mi.px_to_map @ unpad @ m3 @ np.linalg.inv(unpad) @ pi_s.plan_to_px
            hyps.append((int(inl.sum()), m3, len(good)))
    if not hyps:
        return fail("too few feature matches for RANSAC")
    hyps.sort(key=lambda h: -h[0])
    inliers, matrix, n_good = hyps[0]
    if inliers < min_inliers:
        return fail(f"only {inliers} RANSAC inliers (need {min_inliers})", inliers=inliers)
    if not np.all(np.isfinite(matrix)) or abs(np.linalg.det(matrix[:2, :2])) < 1e-12:
        return fail("degenerate affine estimate")
    second = hyps[1][0] if len(hyps) > 1 else 0
    return Registration.from_matrix(
        matrix,
        score=inliers / max(n_good, 1),
        ambiguity=second / inliers,
        rooms=tuple(plan.room_ids),
        method=kind,
        time_s=time.perf_counter() - t0,
        details={"inliers": inliers, "matches": n_good},
    )


def register_orb(plan: Any, grid: Any, **kw: Any) -> Registration:
    """ORB + RANSAC affine."""
    return register_features(plan, grid, kind="orb", **kw)


def register_sift(plan: Any, grid: Any, **kw: Any) -> Registration:
    """SIFT + RANSAC affine."""
    return register_features(plan, grid, kind="sift", **kw)


def register_akaze(plan: Any, grid: Any, **kw: Any) -> Registration:
    """AKAZE + RANSAC affine."""
    return register_features(plan, grid, kind="akaze", **kw)


def _bbox_init(plan: Any, pi: PlanImage, mi: MapImage, flipped: bool, k: int) -> np.ndarray:
    """Plan px -> map px (3×3) putting the dihedrally transformed plan bbox on the map's free bbox."""
    g = matrix_from_params(flipped, k * math.pi / 2, 1.0, 1.0)
    minx, miny, maxx, maxy = plan.bounds
    corners = np.array([[minx, miny], [maxx, miny], [maxx, maxy], [minx, maxy]]) @ g[:2, :2].T
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    c0, r0, c1, r1 = mi.free_bbox
    sx, sy = (c1 - c0) / (hi[0] - lo[0]), (r1 - r0) / (hi[1] - lo[1])
    fit = np.array([[sx, 0, c0 - 0.5 - sx * lo[0]], [0, sy, r0 - 0.5 - sy * lo[1]], [0, 0, 1.0]])
    return fit @ g @ np.linalg.inv(pi.plan_to_px)


def register_ecc(
    plan: Any,
    grid: Any,
    levels: int = 3,
    iterations: int = 40,
    refine_top: int = 2,
    blur: int = 5,
    max_side: int = 256,
    **_: Any,
) -> Registration:
    """ECC (affine) with 8 dihedral starts on a pyramid; the map image is first shrunk to at most
    ``max_side`` pixels (0: full resolution). See module docstring."""
    t0 = time.perf_counter()
    prep = _prepare(plan, grid, "ecc", t0, max_side=max_side)
    if isinstance(prep, Registration):
        return prep
    mi, pi = prep
    tmpl = [mi.image.astype(np.float32) / 255.0]
    tmask = [mi.known]
    inp = [pi.image.astype(np.float32) / 255.0]
    for _ in range(levels - 1):
        tmpl.append(cv2.pyrDown(tmpl[-1]))
        tmask.append(np.ascontiguousarray(tmask[-1][::2, ::2]))  # pyrDown keeps even pixels
        inp.append(cv2.pyrDown(inp[-1]))
    imask = [np.full(i.shape, 255, np.uint8) for i in inp]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-5)

    def run(w_full: np.ndarray, lvl: int) -> tuple[float, np.ndarray]:
        """One ECC run at pyramid level ``lvl`` from a full-resolution map px -> plan px warp.
        pyrDown keeps every second pixel, so level-l coordinates are full ones times 2^-l."""
        s = np.diag([0.5**lvl, 0.5**lvl, 1.0])
        w = (s @ w_full @ np.linalg.inv(s))[:2].astype(np.float32)
        cc, w = cv2.findTransformECCWithMask(
            tmpl[lvl], inp[lvl], tmask[lvl], imask[lvl], w, cv2.MOTION_AFFINE, crit, blur
        )
        return float(cc), np.linalg.inv(s) @ _h(w.astype(np.float64)) @ s

    results: list[tuple[float, np.ndarray, tuple[bool, int]]] = []
    top = levels - 1
    for g in DIHEDRAL:
        w0 = np.linalg.inv(_bbox_init(plan, pi, mi, *g))  # map px -> plan px
        try:
            cc, w = run(w0, top)
        except cv2.error:
            continue
        results.append((cc, w, g))
    if not results:
        return Registration.failure(
            "ECC did not converge from any start", method="ecc", time_s=time.perf_counter() - t0
        )
    results.sort(key=lambda r: -r[0])
    refined = []
    for cc, w, g in results[:refine_top]:
        try:
            for lvl in range(top - 1, -1, -1):
                cc, w = run(w, lvl)
        except cv2.error:
            continue
        refined.append((cc, w, g))
    if not refined:
        refined = results[:1]
    refined.sort(key=lambda r: -r[0])
    cc, w, g = refined[0]
    try:
        a3 = np.linalg.inv(w)  # plan px -> map px
    except np.linalg.LinAlgError:
        return Registration.failure("ECC warp is singular", method="ecc", time_s=time.perf_counter() - t0)
    matrix = mi.px_to_map @ a3 @ pi.plan_to_px
    others = [r[0] for r in results if r[2] != g]
    second = max(others) if others else 0.0
    return Registration.from_matrix(
        matrix,
        score=max(cc, 0.0),
        ambiguity=float(np.clip(second / cc, 0.0, 1.0)) if cc > 0 else 1.0,
        rooms=tuple(plan.room_ids),
        method="ecc",
        time_s=time.perf_counter() - t0,
        details={"start": [bool(g[0]), 90 * g[1]]},
    )


BASELINES = {"orb": register_orb, "sift": register_sift, "akaze": register_akaze, "ecc": register_ecc}
