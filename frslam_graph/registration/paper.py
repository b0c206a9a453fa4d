"""Paper-faithful MFR registration (FR-SLAM, Section III-A: Alg. 1, eqs. 2–7).

Frames and units: plan coordinates (plan units, y up) -> map metres (the grid's world frame).
Images use the grid convention (row 0 = lowest y, column = x), so an array flip of the rows is the
plan mirror ``diag(1, -1)`` and ``np.rot90(a, -k)`` is a counter-clockwise rotation by k·90°.

Reading of the paper used here (stated because the text is loose):

* **Alg. 1 room subsets.** The base is the living room (all rooms of type ``living_room``; if the
  plan has none, the largest room — R2V plans often label the living-dining-kitchen ``kitchen``).
  Alg. 1 collects the bedrooms and adds every combination of them to the living room: one image
  per subset ``living ∪ C`` for each ``C ⊆ bedrooms`` (sizes 0..n, so also the living room alone
  and the living room with all bedrooms). Other rooms (kitchen, bathroom, corridor, closet, ...)
  appear in no Alg. 1 combination. Eq. (1) defines F over subsets S ⊆ H of *all* rooms, so the
  whole plan f(H) is an element of F; we add it as one more image (``include_full=True``),
  without which a fully explored map could never be matched by its own plan. All other subsets
  of eq. (1) (2^n) are not enumerated, as Alg. 1 does not.
* **LiDAR map preprocessing** (eqs. 2–4): :func:`~frslam_graph.registration.preprocess.preprocess_map`.
* **Alg. 2.** Both images (cropped to their bounding boxes) are resized to ``size``×``size``
  (200), the plan image goes through the 8 morphological transformations (4 rotations by 90°,
  with and without a flip), IoU = S_inter / S_union (eq. 6) against the map image; the best IoU
  over all subsets and transformations wins. Only these 8 transformations exist in the paper's
  model: a map rotated by any other angle cannot be matched (the benchmark's "any angle" set
  shows what that costs). The paper computes the areas with Harris corners +
  the shoelace formula (eq. 5); ``area="pixels"`` (default) counts pixels, which is what the
  polygon areas approximate; ``area="shoelace"`` applies eq. (5) to the vertices of the
  region's contours (``cv2.findContours`` vertices stand in for Harris corners).
* **Scale** (eq. 7): S_H = H1/H2, S_V = V1/V2 from the bounding boxes of the transformed plan
  subset (H1, V1, plan units) and of the preprocessed LiDAR map (H2, V2, metres); the plan ->
  map scale is their inverse. The paper gives no translation; we place the transformed subset's
  bounding box on the map's bounding box (min corners coincide), which is what its overlay does.

``score`` = best IoU; ``ambiguity`` = best IoU of any *other* flip/rotation / best IoU.

**Doubt.** Alg. 2 always returns its best placement, however poor. A match whose score is below
``doubt_score`` (:data:`DOUBT_SCORE`) or whose ambiguity is above ``doubt_ambiguity``
(:data:`DOUBT_AMBIGUITY`) is returned ``ok`` with a ``doubt`` (:func:`paper_doubt`): its
``verdict`` is ``"doubtful"``, ``frslam register`` says so and exits 1, and the SLAM pipeline
does not use it. The thresholds are the rule that keeps the most right matches while leaving at
most 1 % of all cases wrong and unflagged on the registration benchmark (``tools/README.md``,
"Paper mode: doubtful matches", with the distributions and the commands). The paper's IoU of a
whole footprint is high under most of the 8 transformations, so on its own the ambiguity
separates right from wrong poorly (median 0.96 for right matches, 0.99 for wrong ones); the
score carries most of the rule, and the ambiguity test catches near-ties (symmetric layouts).
"""

from __future__ import annotations

import math
import time
from itertools import combinations
from typing import Any

import cv2
import numpy as np

from frslam_graph.raster import RasterFrame, rasterise_polygons
from frslam_graph.registration.preprocess import PreprocessedMap, preprocess_map
from frslam_graph.registration.result import Registration, matrix_from_params

__all__ = [
    "DIHEDRAL",
    "DOUBT_AMBIGUITY",
    "DOUBT_SCORE",
    "dihedral_image",
    "paper_doubt",
    "paper_subsets",
    "register_paper",
    "shoelace_area",
]

#: below this best IoU a paper-mode match is doubtful (tools/README.md: "Paper mode: doubtful matches")
DOUBT_SCORE = 0.96
#: above this ambiguity (runner-up flip/rotation IoU / best IoU) a paper-mode match is doubtful
DOUBT_AMBIGUITY = 0.99

# the 8 morphological transformations: (flipped, k) with matrix R(k·90°) · diag(1, -1 if flipped)
DIHEDRAL: tuple[tuple[bool, int], ...] = tuple((f, k) for f in (False, True) for k in range(4))


def dihedral_image(img: np.ndarray, flipped: bool, k: int) -> np.ndarray:
    """Image of the plan under R(k·90°)·diag(1, -1 if flipped) (row 0 = lowest y convention)."""
    out = img[::-1] if flipped else img
    return np.rot90(out, -k)


def paper_subsets(plan: Any, include_full: bool = True, max_bedrooms: int = 10) -> list[tuple[str, ...]]:
    """Alg. 1: room-id subsets ``living ∪ C`` for every combination C of bedrooms (+ the full plan).

    More than ``max_bedrooms`` bedrooms: only the ``max_bedrooms`` largest are combined (2^n images).
    """
    rooms = list(plan.rooms)
    living = [r for r in rooms if r.type == "living_room"]
    if not living:
        living = [max(rooms, key=lambda r: r.polygon.area)]
    base = tuple(r.id for r in living)
    bedrooms = [r for r in rooms if r.type == "bedroom" and r.id not in base]
    bedrooms = sorted(bedrooms, key=lambda r: -r.polygon.area)[:max_bedrooms]
    ids = [r.id for r in bedrooms]
    subsets: list[tuple[str, ...]] = []
    for n in range(len(ids) + 1):
        for combo in combinations(ids, n):
            subsets.append(base + combo)
    if include_full:
        full = tuple(r.id for r in rooms)
        if set(full) not in [set(s) for s in subsets]:
            subsets.append(full)
    return subsets


def shoelace_area(mask: np.ndarray) -> float:
    """Area of a binary mask by eq. (5) on its contour vertices (outer rings minus holes)."""
    contours, hierarchy = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return 0.0
    total = 0.0
    for c, h in zip(contours, hierarchy[0], strict=True):
        p = c.reshape(-1, 2).astype(np.float64)
        x, y = p[:, 0], p[:, 1]
        s = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
        total += s if h[3] < 0 else -s
    return max(total, 0.0)


def paper_doubt(
    score: float, ambiguity: float, doubt_score: float = DOUBT_SCORE, doubt_ambiguity: float = DOUBT_AMBIGUITY
) -> str:
    """Why a paper-mode match is doubtful, or ``""`` when it is not.

    Args:
        score: best IoU of the match (0..1).
        ambiguity: best IoU of any other flip/rotation divided by ``score`` (0..1).
        doubt_score: a score below this is doubtful.
        doubt_ambiguity: an ambiguity above this is doubtful.

    Returns:
        ``""``, or every failed criterion with its numbers, joined by ``"; "``.
    """
    why = []
    if score < doubt_score:
        why.append(f"IoU {score:.2f} < {doubt_score:.2f}")
    if ambiguity > doubt_ambiguity:
        why.append(
            f"ambiguity {ambiguity:.3f} > {doubt_ambiguity:.2f}: another flip/rotation fits almost as well"
        )
    return "; ".join(why)


def _resize_binary(mask: np.ndarray, size: int) -> np.ndarray:
    small = cv2.resize(mask.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    return (small >= 0.5).astype(np.uint8)


def _iou(a: np.ndarray, b: np.ndarray, area: str) -> float:
    if area == "shoelace":
        inter = shoelace_area(a & b)
        union = shoelace_area(a | b)
    else:
        inter = float(np.count_nonzero(a & b))
        union = float(np.count_nonzero(a | b))
    return inter / union if union > 0 else 0.0


def register_paper(
    plan: Any,
    grid: Any,
    theta: int = 250,
    alpha: float = 0.25,
    epsilon: float = 0.1,
    size: int = 200,
    area: str = "pixels",
    include_full: bool = True,
    plan_pixels: int = 400,
    max_bedrooms: int = 10,
    min_score: float = 0.0,
    doubt_score: float = DOUBT_SCORE,
    doubt_ambiguity: float = DOUBT_AMBIGUITY,
    **_: Any,
) -> Registration:
    """Register ``plan`` to ``grid`` as the paper does (see the module docstring for the reading).

    theta, alpha, epsilon: LiDAR preprocessing (grey threshold, min component area in m²,
    polygon-fit tolerance in m); size: side of the resized images (200 in the paper); area:
    ``"pixels"`` or ``"shoelace"`` (eq. 5); plan_pixels: raster size of the plan's longer side
    before resizing; min_score: below this IoU the match is reported as failed; doubt_score,
    doubt_ambiguity: an ``ok`` match below / above these is flagged (``doubt``, see
    :func:`paper_doubt`).
    Returns a :class:`Registration` (``ok`` False with a ``reason`` on failure; ``verdict``
    ``"doubtful"`` for a doubtful match; never raises on a valid plan and grid).
    """
    t0 = time.perf_counter()

    def fail(reason: str, **details: Any) -> Registration:
        return Registration.failure(reason, method="paper", time_s=time.perf_counter() - t0, **details)

    if area not in ("pixels", "shoelace"):
        return fail(f"unknown area mode {area!r} (expected 'pixels' or 'shoelace')")
    rooms = list(plan.rooms)
    if len(rooms) < 2:
        return fail(f"plan has {len(rooms)} room(s); at least 2 are needed to fix rotation and flip")
    lidar: PreprocessedMap = preprocess_map(grid, theta=theta, alpha=alpha, epsilon=epsilon)
    if lidar.empty:
        return fail("map has no free area left after preprocessing (empty or all unknown)")
    l_star = _resize_binary(lidar.mask, size)

    # Plan label image, rasterised once; each subset image is a crop of a label lookup.
    minx, miny, maxx, maxy = plan.bounds
    extent = max(maxx - minx, maxy - miny)
    if not (np.isfinite(extent) and extent > 0):
        return fail("plan has zero extent")
    res = extent / plan_pixels
    frame = RasterFrame.around((minx, miny, maxx, maxy), res, margin=2 * res)
    labels = rasterise_polygons([r.polygon for r in rooms], frame, values=list(range(1, len(rooms) + 1)))
    index = {r.id: i + 1 for i, r in enumerate(rooms)}

    subsets = paper_subsets(plan, include_full=include_full, max_bedrooms=max_bedrooms)
    best_per_g = {g: (-1.0, -1) for g in DIHEDRAL}
    for s_idx, subset in enumerate(subsets):
        lut = np.zeros(len(rooms) + 1, np.uint8)
        lut[[index[i] for i in subset]] = 1
        sub = lut[labels]
        rr = np.flatnonzero(sub.any(axis=1))
        cc = np.flatnonzero(sub.any(axis=0))
        if rr.size == 0:
            continue
        f_star = _resize_binary(sub[rr[0] : rr[-1] + 1, cc[0] : cc[-1] + 1], size)
        for g in DIHEDRAL:
            iou = _iou(l_star, dihedral_image(f_star, *g), area)
            if iou > best_per_g[g][0]:
                best_per_g[g] = (iou, s_idx)

    ranked = sorted(best_per_g.items(), key=lambda kv: -kv[1][0])
    (flipped, k), (score, s_idx) = ranked[0]
    second = ranked[1][1][0]
    if s_idx < 0:
        return fail("no plan subset could be rasterised")
    if score <= min_score:
        return fail(f"best IoU {score:.3f} is not above min_score {min_score:.3f}", score=score)

    # eq. (7): bounding boxes of the transformed subset (plan units) and of the map (metres)
    subset = subsets[s_idx]
    g_mat = matrix_from_params(flipped, k * math.pi / 2, 1.0, 1.0)
    pts = np.vstack([np.asarray(plan.room(i).polygon.exterior.coords) for i in subset])
    pts = pts @ g_mat[:2, :2].T
    x0, y0 = pts.min(axis=0)
    h1, v1 = pts.max(axis=0) - (x0, y0)
    h2, v2 = lidar.size_m
    if h1 <= 0 or v1 <= 0:
        return fail("matched plan subset has a degenerate bounding box")
    hpx, wpx = lidar.shape
    to_px = np.array([[wpx / h1, 0.0, -x0 * wpx / h1], [0.0, hpx / v1, -y0 * hpx / v1], [0.0, 0.0, 1.0]])
    matrix = lidar.pixel_to_map @ to_px @ g_mat
    ambiguity = float(second / score) if score > 0 else 1.0
    return Registration.from_matrix(
        matrix,
        score=float(score),
        ambiguity=ambiguity,
        doubt=paper_doubt(float(score), ambiguity, doubt_score, doubt_ambiguity),
        rooms=tuple(subset),
        method="paper",
        time_s=time.perf_counter() - t0,
        candidates=[(float(v[0]), f, (90.0 * kk + 179.0) % 360.0 - 179.0) for (f, kk), v in ranked],
        details={"S_H": h1 / h2, "S_V": v1 / v2, "n_subsets": len(subsets), "map_bbox_m": (h2, v2)},
    )
