"""Session 21's exact CPU cuts of the MFR registration: each helper against the formula it replaces
(bit for bit, on random inputs and edge cases)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from shapely.geometry import box

from frslam_graph.floorplan import Door, FloorPlan, Room


def _old_dominant_angles(vectors: np.ndarray, max_peaks: int = 2, rel: float = 0.35) -> list[float]:
    """``geometry.dominant_angles`` as it was (main f4b4735)."""
    if len(vectors) > 6000:
        vectors = vectors[:: int(math.ceil(len(vectors) / 6000))]
    mag = np.hypot(vectors[:, 0], vectors[:, 1])
    ok = mag > 0
    if not ok.any():
        return [0.0]
    v, w = vectors[ok], mag[ok]
    a4 = np.mod(4.0 * np.arctan2(v[:, 1], v[:, 0]), 2 * np.pi)
    bins = 360
    hist = np.bincount((a4 / (2 * np.pi) * bins).astype(np.intp) % bins, weights=w, minlength=bins)
    half = 36
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / 12.0) ** 2)
    smooth = np.convolve(np.concatenate([hist[-half:], hist, hist[:half]]), kernel, mode="valid")
    is_peak = (smooth >= np.roll(smooth, 1)) & (smooth > np.roll(smooth, -1))
    peaks = np.flatnonzero(is_peak)
    peaks = peaks[np.argsort(-smooth[peaks], kind="stable")].tolist()
    out: list[float] = []
    for i in peaks[:max_peaks]:
        if out and smooth[i] < rel * smooth[peaks[0]]:
            break
        centre = (i + 0.5) / bins * 2 * np.pi
        d = np.angle(np.exp(1j * (a4 - centre)))
        near = np.abs(d) < np.radians(40.0)
        mean = centre + (np.sum(w[near] * d[near]) / max(np.sum(w[near]), 1e-12))
        ang = float(np.angle(np.exp(1j * mean)) / 4.0)
        if all(abs(np.angle(np.exp(4j * (ang - o)))) > np.radians(80.0) for o in out):
            out.append(ang)
    return out or [0.0]


def test_near_turns_equal_the_wrapped_differences_kept() -> None:
    # the complex exponential only near the peak: the same elements, in order, the same values
    from frslam_graph.registration.mfr.geometry import _near_turns

    rng = np.random.default_rng(3)
    a4 = np.mod(rng.uniform(-10, 10, 5000), 2 * np.pi)
    edges = np.radians([0.0, 39.999999, 40.0, 40.000001, 44.9, 45.0, 320.0, 319.99999, 359.9999])
    a4 = np.concatenate([a4, edges, 2 * np.pi - edges, [0.0, 2 * np.pi, np.nan]])
    w = rng.random(len(a4))
    for centre in [0.0087, 0.5, math.pi, 6.27, (359 + 0.5) / 360 * 2 * np.pi, *a4[-12:-1]]:
        with np.errstate(invalid="ignore"):
            d = np.angle(np.exp(1j * (a4 - centre)))
            near = np.abs(d) < np.radians(40.0)
            got_d, got_w = _near_turns(a4, centre, w)
        assert np.array_equal(got_d, d[near]) and np.array_equal(got_w, w[near])


@pytest.mark.parametrize("seed", range(6))
def test_dominant_angles_equal_the_former_computation(seed: int) -> None:
    from frslam_graph.registration.mfr.geometry import dominant_angles

    rng = np.random.default_rng(seed)
    n = [50, 900, 7000, 13000, 3000, 400][seed]
    ang = rng.choice([0.3, 0.3 + math.pi / 2, 1.1], n, p=[0.5, 0.3, 0.2]) + rng.normal(0, 0.05, n)
    vec = np.column_stack([np.cos(ang), np.sin(ang)]) * rng.uniform(0.01, 2.0, (n, 1))
    if seed % 2:
        vec[rng.random(n) < 0.1] = 0.0  # zero vectors: left out
    assert dominant_angles(vec) == _old_dominant_angles(vec)
    assert dominant_angles(vec[:, ::-1]) == _old_dominant_angles(vec[:, ::-1])
    assert dominant_angles(np.zeros((5, 2))) == _old_dominant_angles(np.zeros((5, 2))) == [0.0]


@pytest.mark.parametrize("seed", range(4))
def test_component_stats_equal_opencv_stats(seed: int) -> None:
    # areas, box sizes and centroids of connectedComponents' labels, from the mask's pixels
    from frslam_graph.registration.mfr.map_side import component_stats

    rng = np.random.default_rng(seed)
    for density in (0.0, 0.01, 0.1, 0.5):
        mask = (rng.random((37 + seed, 53)) < density).astype(np.uint8)
        mask = cv2.dilate(mask, np.ones((2, 1), np.uint8)) if seed % 2 else mask
        m, lab, st, cen = cv2.connectedComponentsWithStats(mask, connectivity=8)
        m2, lab2 = cv2.connectedComponents(mask, connectivity=8)
        assert m2 == m and np.array_equal(lab2, lab)
        area, width, height, centroid = component_stats(lab2, mask, m, boxes=True)
        assert np.array_equal(area, st[1:, cv2.CC_STAT_AREA])
        assert np.array_equal(width, st[1:, cv2.CC_STAT_WIDTH])
        assert np.array_equal(height, st[1:, cv2.CC_STAT_HEIGHT])
        assert centroid.shape == (m - 1, 2) and np.array_equal(centroid, cen[1:])
        assert np.array_equal(component_stats(lab2, mask, m)[0], area)


def _old_unexplored_cores(pockets: np.ndarray, radius_px: float) -> np.ndarray:
    p8 = pockets.astype(np.uint8)
    n, labels = cv2.connectedComponents(p8, connectivity=4)
    depth = np.zeros(n, np.float32)
    inside = pockets.ravel()
    np.maximum.at(depth, labels.ravel()[inside], cv2.distanceTransform(p8, cv2.DIST_L2, 3).ravel()[inside])
    core = depth >= radius_px
    core[0] = False
    return core[labels] if core.any() else np.zeros(pockets.shape, bool)


@pytest.mark.parametrize("seed", range(5))
def test_unexplored_cores_on_the_bounding_box_equal_the_whole_image(seed: int) -> None:
    from frslam_graph.registration.mfr.map_side import _unexplored_cores

    rng = np.random.default_rng(seed)
    shape = (120, 90)
    pockets = np.zeros(shape, np.uint8)
    for _ in range(rng.integers(0, 6)):  # blobs and boxes away from the border, some touching
        c = (int(rng.integers(2, 88)), int(rng.integers(2, 118)))
        cv2.circle(pockets, c, int(rng.integers(1, 30)), 1, -1)
        x, y = int(rng.integers(1, 80)), int(rng.integers(1, 110))
        cv2.rectangle(pockets, (x, y), (x + int(rng.integers(0, 25)), y + int(rng.integers(0, 40))), 1, -1)
    pockets[(rng.random(shape) < 0.02)] = 1
    pockets[0, :] = pockets[-1, :] = pockets[:, 0] = pockets[:, -1] = 0  # enclosed: never on the border
    pockets = pockets.astype(bool)
    for radius in (0.5, 3.0, 7.3, 20.0, 33.333333333333336):
        assert np.array_equal(_unexplored_cores(pockets, radius), _old_unexplored_cores(pockets, radius))
    assert not _unexplored_cores(np.zeros(shape, bool), 3.0).any()


def test_distance_field_in_place_equals_the_where_formula() -> None:
    from frslam_graph.registration.refine import DistanceField

    rng = np.random.default_rng(11)
    free = cv2.dilate((rng.random((60, 45)) < 0.05).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    for res in (0.05, 0.03, 0.1):
        f = free.astype(np.uint8)
        d_in = cv2.distanceTransform(f, cv2.DIST_L2, cv2.DIST_MASK_3)
        d_out = cv2.distanceTransform(1 - f, cv2.DIST_L2, cv2.DIST_MASK_3)
        sdf = np.where(free, d_in - 0.5, 0.5 - d_out).astype(np.float32, copy=False) * np.float32(res)
        field = DistanceField.from_masks(free, res, (0.0, 0.0))
        assert field.sdf.dtype == np.float32 and np.array_equal(field.sdf, sdf)
        assert np.array_equal(field.known, free.astype(np.float32))
        assert np.array_equal(DistanceField.from_masks(free.astype(np.uint8), res, (0.0, 0.0)).sdf, sdf)


def _old_coarse_hypotheses_at(pm, obs, masks, cases, ai, max_aspect, top_k, door_width_m):
    """``coarse._coarse_hypotheses_at`` as it was (one dihedral case at a time)."""
    from frslam_graph.registration.mfr.coarse import _features, door_prior, smallest_stable
    from frslam_graph.registration.mfr.geometry import DIHEDRAL, dihedral
    from frslam_graph.se2 import rot

    angle = obs.angles[ai]
    rm = rot(-angle)
    mc = rm @ obs.centroid
    mcov = rm @ obs.cov @ rm.T
    bx0, by0, bx1, by1 = obs.bboxes[ai]
    fmap = _features(obs.area, mc[0], mc[1], mcov[0, 0], mcov[0, 1], mcov[1, 1], bx0, by0, bx1, by1)
    costs, a_all, b_all, cx_all, cy_all = [], [], [], [], []
    for f, vx, vy, cx, cy in cases:
        a = np.sqrt(mcov[0, 0] / vx)
        b = np.sqrt(mcov[1, 1] / vy)
        ratio = b / a
        cost = np.sum((f - fmap) ** 2, axis=1) + 0.01 * np.log(ratio) ** 2
        cost = cost - 0.01 * np.log(np.maximum(door_prior(pm, np.sqrt(a * b), door_width_m), 1e-6))
        costs.append(np.where((ratio > max_aspect) | (ratio < 1.0 / max_aspect), np.inf, cost))
        a_all.append(a)
        b_all.append(b)
        cx_all.append(cx)
        cy_all.append(cy)
    costs = np.stack(costs, axis=1)
    flat = smallest_stable(costs.ravel(), top_k)
    flat = flat[np.isfinite(costs.ravel()[flat])]
    si, ji = np.divmod(flat, len(DIHEDRAL))
    a = np.stack(a_all, axis=1)[si, ji]
    b = np.stack(b_all, axis=1)[si, ji]
    cx = np.stack(cx_all, axis=1)[si, ji]
    cy = np.stack(cy_all, axis=1)[si, ji]
    gs = np.stack([dihedral(k, f) for k, f in DIHEDRAL])[ji]
    rp = rot(-pm.angle)
    rmap = rot(angle)
    lin = rmap[None] @ (np.stack([a, b], axis=1)[:, :, None] * gs) @ rp[None]
    t_al = np.column_stack([mc[0] - a * cx, mc[1] - b * cy])
    mats = np.zeros((len(flat), 3, 3))
    mats[:, :2, :2] = lin
    mats[:, :2, 2] = t_al @ rmap.T
    mats[:, 2, 2] = 1.0
    return {"mask": masks[si], "case": ji, "mats": mats, "cost": costs[si, ji], "angle": np.full(len(si), ai)}


def _grid_plan() -> FloorPlan:
    """Nine rooms on an uneven grid with doors (plan units)."""
    xs, ys = [0, 4, 7, 12], [0, 3, 8, 10]
    rooms = [
        Room(f"r{i}{j}", "room", box(xs[i], ys[j], xs[i + 1], ys[j + 1])) for i in range(3) for j in range(3)
    ]
    doors = []
    for i in range(3):
        for j in range(3):
            if i < 2:
                y = 0.5 * (ys[j] + ys[j + 1])
                doors.append(
                    Door(f"h{i}{j}", (xs[i + 1], y - 0.4), (xs[i + 1], y + 0.4), (f"r{i}{j}", f"r{i + 1}{j}"))
                )
            if j < 2:
                x = 0.5 * (xs[i] + xs[i + 1])
                doors.append(
                    Door(f"v{i}{j}", (x - 0.4, ys[j + 1]), (x + 0.4, ys[j + 1]), (f"r{i}{j}", f"r{i}{j + 1}"))
                )
    return FloorPlan(rooms, doors, units="px", name="grid")


def _seen_grid(yaw: float):
    """:func:`_grid_plan` placed in metres (x0.4 / x0.45, turned by ``yaw``, shifted) and a map
    showing four of its rooms: (the plan, its placement plan -> map, the OccupancyGrid)."""
    from frslam_graph.occupancy import OccupancyGrid
    from frslam_graph.raster import RasterFrame, rasterise_plan
    from frslam_graph.se2 import to_matrix

    plan = _grid_plan()
    truth = to_matrix((1.0, -2.0, yaw)) @ np.diag([0.4, 0.45, 1.0])
    house = plan.transformed(truth, units="m")
    seen = ["r00", "r10", "r11", "r21"]
    frame = RasterFrame.around(house.subset(seen).bounds, 0.05, margin=0.6)
    lab = rasterise_plan(house, frame, rooms=seen, labels=True)
    free = cv2.erode((lab > 0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    occ = (lab > 0) & ~free
    grid = OccupancyGrid.from_masks(free, occ, 0.05, (frame.origin[0], frame.origin[1], 0.0))
    return plan, truth, grid


@pytest.mark.parametrize("yaw", [0.0, 0.35])
def test_coarse_hypotheses_stacked_equal_case_by_case(yaw: float) -> None:
    from frslam_graph.registration.mfr import coarse
    from frslam_graph.registration.mfr.map_side import observe_map
    from frslam_graph.registration.mfr.plan_side import prepare_plan
    from frslam_graph.registration.subsets import connected_subsets

    plan, _, grid = _seen_grid(yaw)
    obs, pm = observe_map(grid), prepare_plan(plan)
    masks = connected_subsets(pm.adjacency, max_per_level=3000)
    cases = coarse.dihedral_cases(coarse.subset_geometry(pm, masks))
    by_case = [tuple(u[j] for u in cases) for j in range(len(coarse.DIHEDRAL))]  # the former layout
    got = coarse.coarse_hypotheses(
        pm, obs, masks, max_aspect=1.6, top_k=64, door_width_m=(0.3, 4.0), cases=cases
    )
    parts = [
        _old_coarse_hypotheses_at(pm, obs, masks, by_case, ai, 1.6, 64, (0.3, 4.0))
        for ai in range(len(obs.angles))
    ]
    pool = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(pool["cost"], kind="stable")[:64]
    assert len(order) > 10
    for k, v in pool.items():
        assert np.array_equal(got[k], v[order]), k


def test_label_counts_on_an_empty_mask_are_the_zeros_placed_rooms_iou_skips_to() -> None:
    # placed_rooms_iou skips the histogram of the unexplored cells when there is none
    from frslam_graph.registration.mfr.fine import _label_counts

    labels = np.random.default_rng(2).integers(0, 9, (40, 50)).astype(np.uint8)
    got = _label_counts(labels, np.zeros(labels.shape, bool), 8)
    assert got.dtype == np.int64 and np.array_equal(got, np.zeros(8, np.int64))


def _old_fill_rooms(room_rings, room_holes, rooms, matrix, frame, labels=False, label_dtype=np.int32):
    """``plan_side.fill_rooms`` as it was: ring by ring."""
    from frslam_graph.registration.mfr.plan_side import FIX, SHIFT

    m = np.diag([1.0 / frame.resolution, 1.0 / frame.resolution, 1.0]) @ matrix
    m[:2, 2] -= np.asarray(frame.origin) / frame.resolution + 0.5
    a, t = m[:2, :2], m[:2, 2]
    img = np.zeros(frame.shape, label_dtype if labels else np.uint8)
    ext, holes = [], []
    for i in rooms:
        for r in room_rings[i]:
            ext.append(np.round((r @ a.T + t) * FIX).astype(np.int32).reshape(-1, 1, 2))
        if labels:
            cv2.fillPoly(img, ext, int(i) + 1, lineType=cv2.LINE_8, shift=SHIFT)
            ext = []
        for r in room_holes[i]:
            holes.append(np.round((r @ a.T + t) * FIX).astype(np.int32).reshape(-1, 1, 2))
    if ext:
        cv2.fillPoly(img, ext, 1, lineType=cv2.LINE_8, shift=SHIFT)
    if holes:
        cv2.fillPoly(img, holes, 0, lineType=cv2.LINE_8, shift=SHIFT)
    return img


def test_fill_rooms_batched_equals_ring_by_ring() -> None:
    from frslam_graph.raster import RasterFrame
    from frslam_graph.registration.mfr.plan_side import fill_rooms, prepare_plan
    from frslam_graph.se2 import to_matrix

    plan = _grid_plan()
    rooms = list(plan.rooms)
    rooms[4] = Room(rooms[4].id, "room", rooms[4].polygon.difference(box(5, 4.5, 6, 6)))  # a hole
    pm = prepare_plan(FloorPlan(rooms, list(plan.doors), units="px", name="holes"))
    assert any(pm.room_holes)
    frame = RasterFrame(0.05, (-1.0, -3.0), (160, 200))
    for yaw, sx in ((0.0, 0.5), (0.3, 0.41), (-1.2, 0.66)):
        m = to_matrix((0.4, -0.7, yaw)) @ np.diag([sx, -0.9 * sx, 1.0])
        for sel in (range(9), [4], [0, 4, 8], []):
            for lab, dt in ((False, np.uint8), (True, np.int32), (True, np.uint8)):
                got = fill_rooms(pm.room_rings, pm.room_holes, sel, m, frame, labels=lab, label_dtype=dt)
                want = _old_fill_rooms(
                    pm.room_rings, pm.room_holes, sel, m, frame, labels=lab, label_dtype=dt
                )
                assert got.dtype == want.dtype and np.array_equal(got, want)


def test_lookup_cells_without_a_zero_origin_equal_the_subtraction() -> None:
    from frslam_graph.registration.mfr.geometry import _scaled

    rng = np.random.default_rng(5)
    for v in (rng.normal(0, 3, (7, 300)).astype(np.float32), rng.normal(0, 3, 500)):
        v.flat[:4] = [-0.0, 0.0, np.nan, -np.inf]
        for o, inv in ((0.0, np.float32(20.0)), (-0.0, np.float32(33.333332)), (0.35, np.float32(20.0))):
            want = v - np.float32(o)
            want *= inv
            got = _scaled(v, o, inv)
            assert got.dtype == want.dtype and np.array_equal(got, want, equal_nan=True)
            assert np.array_equal(np.signbit(got), np.signbit(want))
