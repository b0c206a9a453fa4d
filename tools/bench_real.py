"""Registration on real maps and on independent map styles (issue 21, deliverable 3).

Run through ``tools/bench_registration.py --real`` (or this file directly). Rows:

* **Halmstad** (``halmstad/``): each of the 18 Tango sensor maps (``OccupancyGrid.from_image``
  at ``--resolution``, default 0.05 m per pixel: the images state none) against its building's
  layout drawing (``FloorPlan.load``). Truth: the similarity (with or without a flip, whichever
  fits better) fitted to the annotated points. The annotation CSVs count rows from the *bottom*
  of the image (y up: checked on the four maps MFR registers, where the other conventions put
  the fit 30-90 annotation residuals away), so plan y = ``layout_row`` and map y =
  ``map_row`` × resolution. Reported: flip, rotation error, scale error (geometric mean of the
  two scales against the truth's), RMS error at the annotated points over the annotation's own
  RMS residual. ``E5_08`` (distorted, 156 px residual) is reported apart.
* **IPA** (``floorplans/ipa/``): ``lab_intel.png`` against ``intel_map.png`` and
  ``Freiburg52_scan.png`` against ``freiburg_building52.png``; truth: the similarity fitted to
  hand-annotated points in ``tests/data/ipa_*_points.csv`` (plan_col, plan_row, map_col,
  map_row; image rows from the top; each file's header says how they were picked and the
  residual: 4.8 map px for Freiburg 52, 4.2 for Intel, the plans being schematic). The maps are
  read at 0.05 m per pixel (the images state none). A pair whose CSV is missing has no row
  (``tests/data/intel_lab_plan_points.csv`` pairs lab_intel.png with frslam's own map of the
  Intel log, which a run must make first).
* **PRBonn identity**: ``GMapRoomSeg.png`` (with ``GMap.yaml``, metres) as the plan of
  ``GMap.yaml``: the truth is the identity; target within 0.1 m and 0.5 degrees.
* **Independent map styles** from R2V plans (not the simulator's ``partial_map``):
  ``thick``: walls 0.15-0.35 m thick seen two cells deep, furniture against the walls, rooms
  behind open doors partly seen, unknown holes and spurious hits; ``tango``: free space with
  ragged edges, walls drawn on only part of the boundary (free runs straight into unknown,
  as in the Halmstad maps), explored rooms only partly seen, clutter strokes. Truth: the
  distortion's matrix, as in the simulator rows.

Units: metres and degrees in the tables; image pixels in the CSVs.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
TEST_DATA = REPO / "tests" / "data"
HALMSTAD_BUILDINGS = ("E5", "HIH")
DISTORTED = ("E5_08",)
STYLES = ("thick", "tango")
IPA_PAIRS = (  # (name, plan image, map image, annotation CSV in tests/data)
    ("intel", "lab_intel.png", "intel_map.png", "ipa_intel_map_points.csv"),
    ("freiburg52", "Freiburg52_scan.png", "freiburg_building52.png", "ipa_freiburg52_points.csv"),
)


# ----------------------------------------------------------------------------- ground truth
def read_points(path: Path) -> np.ndarray:
    """The (N, 4) numbers of an annotation CSV: ``#`` comment lines and the column-name row
    skipped, the first four columns kept (a text column after them may hold anything)."""
    rows = []
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#") or not (line[0].isdigit() or line[0] in "+-."):
            continue
        rows.append([float(v) for v in line.split(",")[:4]])
    if not rows:
        raise ValueError(f"{path}: no annotated points")
    return np.asarray(rows, dtype=float)


def ipa_points(path: Path, plan_height: int, map_height: int, resolution: float = 0.05):
    """(plan points in the plan image's frame (px, y up), map points in metres (y up)) of an IPA
    annotation CSV whose rows count from the top of each image."""
    pts = read_points(path)
    plan_pts = np.column_stack([pts[:, 0] + 0.5, plan_height - pts[:, 1] - 0.5])
    map_pts = np.column_stack([pts[:, 2] + 0.5, map_height - pts[:, 3] - 0.5]) * resolution
    return plan_pts, map_pts


def scale_of(m: np.ndarray) -> float:
    """Geometric-mean scale of a 3x3 similarity / affinity (its linear part's sqrt |det|)."""
    return math.sqrt(abs(float(np.linalg.det(m[:2, :2]))))


def rms_at(m: np.ndarray, src: np.ndarray, dst: np.ndarray) -> float:
    """RMS distance (units of ``dst``) between ``m`` (3x3) applied to ``src`` (N, 2) and ``dst``."""
    d = src @ m[:2, :2].T + m[:2, 2] - dst
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float]:
    """The similarity (3x3, with a flip when that fits better) taking ``src`` (N, 2) to ``dst``
    (N, 2) in the least-squares sense (Umeyama), and its RMS residual (units of ``dst``)."""
    best: tuple[np.ndarray, float] | None = None
    for flip in (False, True):
        s = src * np.array([1.0, -1.0 if flip else 1.0])
        ms, md = s.mean(axis=0), dst.mean(axis=0)
        a, b = s - ms, dst - md
        u, sv, vt = np.linalg.svd(b.T @ a / len(s))
        d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
        rot = u @ d @ vt
        scale = float((sv * np.diag(d)).sum() / ((a**2).sum() / len(s)))
        m = np.eye(3)
        m[:2, :2] = scale * rot @ np.diag([1.0, -1.0 if flip else 1.0])
        m[:2, 2] = md - scale * rot @ ms
        res = rms_at(m, src, dst)
        if best is None or res < best[1]:
            best = (m, res)
    assert best is not None
    return best


def halves(map_pts: np.ndarray) -> list[np.ndarray]:
    """Two boolean masks of N annotated points: either side of the median along the map points'
    principal axis (N, 2)."""
    c = map_pts - map_pts.mean(axis=0)
    proj = c @ np.linalg.svd(c, full_matrices=False)[2][0]
    return [proj < np.median(proj), proj >= np.median(proj)]


def halves_scales(plan_pts: np.ndarray, map_pts: np.ndarray) -> tuple[float, float]:
    """Each half's (:func:`halves`) own similarity's scale relative to the whole's, minus 1: how
    far the map is from one similarity of the plan (a Tango map bent or stretched in one part:
    Halmstad E5_02's halves -9.9 / +3.9 %). Point noise alone gives a few tenths of a per cent."""
    whole = scale_of(fit_similarity(plan_pts, map_pts)[0])
    h1, h2 = (scale_of(fit_similarity(plan_pts[m], map_pts[m])[0]) / whole - 1.0 for m in halves(map_pts))
    return h1, h2


def point_rows(
    reg: Any, truth: np.ndarray, plan_pts: np.ndarray, map_pts: np.ndarray, residual: float
) -> dict:
    """Flip, rotation and scale against ``truth`` (plan -> map) and the error at the annotated
    points relative to the annotation's own RMS ``residual`` (map units)."""
    from frslam_graph.registration.result import params_from_matrix

    tf, tr, tsx, tsy, _, _ = params_from_matrix(truth)
    row: dict[str, Any] = {
        "ok": bool(reg.ok),
        "reason": reg.reason,
        "score": float(reg.score),
        "ambiguity": float(reg.ambiguity),
        "ambiguous": bool(reg.details.get("ambiguous", reg.ambiguity >= 0.9)) if reg.ok else False,
        "residual": residual,
    }
    m = reg.matrix
    placed = reg.ok or "quality" in reg.details  # a refused match still has a placement
    if not placed or not np.all(np.isfinite(m)) or abs(np.linalg.det(m[:2, :2])) < 1e-300:
        row.update(
            flip_ok=False, rot_err_deg=math.nan, scale_err=math.nan, aspect_err=math.nan, err_ratio=math.nan
        )
        return row
    ef, er, esx, esy, _, _ = params_from_matrix(m)
    drot = (math.degrees(er - tr) + 180.0) % 360.0 - 180.0
    err = rms_at(m, plan_pts, map_pts)
    row.update(
        flip_ok=bool(ef) == bool(tf),
        rot_err_deg=abs(drot),
        scale_err=math.sqrt(esx * esy) / math.sqrt(tsx * tsy) - 1.0,
        aspect_err=(esy / esx) / (tsy / tsx) - 1.0,
        err_ratio=err / max(residual, 1e-12),
    )
    return row


# ----------------------------------------------------------------------------- real rows
def _register(plan: Any, grid: Any, method: str) -> tuple[Any, float, float]:
    """(Registration, wall seconds, CPU seconds of this process: the machine may be shared)."""
    from frslam_graph.registration import register

    c0, t0 = time.process_time(), time.perf_counter()
    reg = register(plan, grid, method=method)
    return reg, time.perf_counter() - t0, time.process_time() - c0


def halmstad_cases(
    data: Path, resolution: float = 0.05
) -> Iterator[tuple[str, str, Any, Path, np.ndarray, np.ndarray]]:
    """Each Halmstad sensor map: (building, map name, its layout as a FloorPlan, the map image's
    path, the annotated points in the plan (N, 2, plan pixels) and in the map (N, 2, metres at
    ``resolution``)); see the module docstring for the points' convention."""
    from frslam_graph.floorplan import FloorPlan

    for b in HALMSTAD_BUILDINGS:
        folder = data / "halmstad" / b
        plan = FloorPlan.load(folder / "layout" / f"{b}_layout.png")
        for path in sorted((folder / "sensor_maps").glob("*.png")):
            pts = np.loadtxt(
                folder / "annotations" / f"{path.stem}_to_layout.csv", delimiter=",", skiprows=1, ndmin=2
            )
            map_pts = np.column_stack([pts[:, 0] + 0.5, pts[:, 1]]) * resolution
            plan_pts = np.column_stack([pts[:, 2] + 0.5, pts[:, 3]])
            yield b, path.stem, plan, path, plan_pts, map_pts


def _annotated_row(
    kind: str,
    case: str,
    building: str,
    plan: Any,
    grid: Any,
    plan_pts: np.ndarray,
    map_pts: np.ndarray,
    method: str,
) -> dict[str, Any]:
    """The row of one registration of ``plan`` on ``grid`` scored against annotated points
    (``plan_pts`` in plan units, ``map_pts`` in metres): truth their similarity (:func:`point_rows`)."""
    truth, res = fit_similarity(plan_pts, map_pts)
    reg, secs, cpu = _register(plan, grid, method)
    row = {
        "set": kind,
        "case": case,
        "building": building,
        "n_rooms": len(plan.rooms),
        "time_s": secs,
        "cpu_s": cpu,
    }
    row.update(point_rows(reg, truth, plan_pts, map_pts, res))
    row["residual_px"] = res / grid.resolution
    return row


def halmstad_rows(data: Path, resolution: float = 0.05, method: str = "mfr") -> list[dict[str, Any]]:
    """One row per Halmstad sensor map (see the module docstring)."""
    from frslam_graph.occupancy import OccupancyGrid

    rows = []
    for b, name, plan, path, plan_pts, map_pts in halmstad_cases(data, resolution):
        grid = OccupancyGrid.from_image(path, resolution)
        row = _annotated_row("halmstad", name, b, plan, grid, plan_pts, map_pts, method)
        row["halves_scale"] = halves_scales(plan_pts, map_pts)
        rows.append(row)
    return rows


def ipa_rows(data: Path, method: str = "mfr", annotations: Path = TEST_DATA) -> list[dict[str, Any]]:
    """The IPA plan / real map pairs with a hand-annotated CSV in ``annotations``."""
    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.occupancy import OccupancyGrid

    rows = []
    for name, plan_file, map_file, csv in IPA_PAIRS:
        if not (annotations / csv).exists():
            continue
        folder = data / "floorplans" / "ipa"
        plan = FloorPlan.load(folder / plan_file)
        res = 0.05
        grid = OccupancyGrid.from_image(folder / map_file, res)
        hp = cv2.imread(str(folder / plan_file), cv2.IMREAD_GRAYSCALE).shape[0]
        hm = grid.height
        plan_pts, map_pts = ipa_points(annotations / csv, hp, hm, res)
        rows.append(_annotated_row("ipa", name, name, plan, grid, plan_pts, map_pts, method))
    return rows


def prbonn_identity_row(data: Path, method: str = "mfr") -> dict[str, Any]:
    """GMapRoomSeg.png (metres, GMap.yaml's frame) as the plan of GMap.yaml: truth = identity."""
    from frslam_graph.floorplan import FloorPlan
    from frslam_graph.occupancy import OccupancyGrid
    from frslam_graph.registration.result import params_from_matrix

    folder = data / "prbonn"
    plan = FloorPlan.load(folder / "GMapRoomSeg.png")
    grid = OccupancyGrid.load(folder / "GMap.yaml")
    reg, secs, cpu = _register(plan, grid, method)
    # error of the placement: worst displacement of the plan's room corners (metres)
    pts = np.concatenate([np.asarray(r.polygon.exterior.coords) for r in plan.rooms])
    m = reg.matrix if np.all(np.isfinite(reg.matrix)) else np.eye(3)
    disp = float(np.max(np.hypot(*(pts @ m[:2, :2].T + m[:2, 2] - pts).T)))
    flip, rot, sx, sy, _, _ = params_from_matrix(m)
    return {
        "set": "prbonn_identity",
        "case": "GMapRoomSeg on GMap",
        "n_rooms": len(plan.rooms),
        "ok": bool(reg.ok),
        "reason": reg.reason,
        "flip_ok": not flip,
        "rot_err_deg": abs((math.degrees(rot) + 180.0) % 360.0 - 180.0),
        "max_disp_m": disp,
        "scale_err": math.sqrt(sx * sy) - 1.0,
        "score": float(reg.score),
        "ambiguity": float(reg.ambiguity),
        "time_s": secs,
        "cpu_s": cpu,
    }


# ----------------------------------------------------------------------------- map styles
def _explore(house: Any, share: float, rng: np.random.Generator) -> list[str]:
    """A connected set of rooms grown to ``share`` of the area from a random room of a part of
    the house that holds that share (``partial_map.random_start_room``: R2V plans miss doors, and
    a start in a closet would explore 1 %)."""
    from frslam_graph.datasets.simulator.partial_map import random_start_room

    areas = {r.id: r.polygon.area for r in house.plan.rooms}
    adjacency = house.adjacency()
    total = sum(areas.values())
    chosen = [random_start_room(house, share, rng)]
    while sum(areas[r] for r in chosen) < share * total * 0.97:
        frontier = sorted({n for r in chosen for n in adjacency[r]} - set(chosen))
        if not frontier:
            break
        chosen.append(frontier[int(rng.integers(len(frontier)))])
    return chosen


def _disc(radius_cells: float) -> np.ndarray:
    r = max(1, int(round(radius_cells)))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _smooth_noise(shape: tuple[int, int], rng: np.random.Generator, sigma_cells: float) -> np.ndarray:
    """A smooth random field of unit standard deviation."""
    f = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma_cells)
    return f / max(float(f.std()), 1e-9)


def wall_cells(plan: Any, frame: Any, thick: float) -> np.ndarray:
    """(H, W) bool: the cells of ``frame`` whose centre lies within half a wall of a room boundary
    of ``plan`` (metres), the wall centred on the boundary as the plan draws it.

    Half a wall is ``(round(thick / 2 / resolution) + 0.5)`` cells: on average as many cells
    across as the disc of that radius dilating a one-cell edge. That edge (the first cell past
    each change of room label along +x and +y) put every wall half a cell off its boundary, in
    +x and +y: the map then showed the rooms shifted by (0.025, 0.025) m from the truth, and
    the IoU_a of right placements lost 2.8 points to it."""
    import shapely

    from frslam_graph.raster import rasterise_polygons

    half = (round(0.5 * thick / frame.resolution) + 0.5) * frame.resolution
    lines = shapely.MultiLineString(
        [np.asarray(ring.coords) for r in plan.rooms for ring in (r.polygon.exterior, *r.polygon.interiors)]
    )
    return rasterise_polygons([lines.buffer(half)], frame).astype(bool)


def styled_map(house: Any, style: str, share: float, rng: np.random.Generator, resolution: float = 0.05):
    """(OccupancyGrid, explored room ids, covered share: the plan's area in explored rooms the map
    shows) of ``house`` (simulator House, used for its metric plan and its door graph only)
    drawn in ``style`` (see the module docstring)."""
    import shapely

    from frslam_graph.floorplan.openings import open_boundaries
    from frslam_graph.occupancy import OccupancyGrid
    from frslam_graph.raster import RasterFrame, rasterise_polygons

    hplan = house.plan
    explored = _explore(house, share, rng)
    frame = RasterFrame.around(house.bounds, resolution, margin=1.0)
    ids = [r.id for r in hplan.rooms]
    labels = rasterise_polygons([r.polygon for r in hplan.rooms], frame, values=list(range(1, len(ids) + 1)))
    inside = labels > 0
    # walls: room boundaries grown to the style's thickness, door openings cut out
    thick = rng.uniform(0.15, 0.35) if style == "thick" else rng.uniform(0.08, 0.2)
    wall = wall_cells(hplan, frame, thick)
    # door openings across the wall between the door's two rooms (R2V door segments may lie up to
    # a wall's width off the rooms' shared boundary: the opening reaches them, as the simulator's)
    doors = []
    for d in hplan.doors:
        if len(set(d.rooms)) != 2:
            continue
        seg = shapely.LineString([d.a, d.b])
        ra, rb = (hplan.room(rid).polygon for rid in d.rooms)
        reach = max(ra.distance(seg), rb.distance(seg))
        near = reach + thick + 2 * resolution  # the raster wall is at least a cell either side
        doors.append(seg.buffer(near, cap_style="flat") & ra.buffer(near) & rb.buffer(near))
    # and no wall where the plan splits one open space into rooms (its rooms are connected there)
    doors += [o.buffer(0.5 * thick) for o in open_boundaries(hplan, thick)[0]]
    if doors:
        wall &= ~rasterise_polygons(doors, frame).astype(bool)
    index = {r: i + 1 for i, r in enumerate(ids)}
    lut = np.zeros(len(ids) + 1, bool)
    lut[[index[r] for r in explored]] = True
    seen = lut[labels] & ~wall
    if style == "tango":  # explored rooms only partly seen (not the first): a half-plane cut
        for r in explored[1:]:
            if rng.random() < 0.5:
                continue
            cells = labels == index[r]
            rr, cc = np.nonzero(cells)
            ang = rng.uniform(0, 2 * np.pi)
            proj = rr * math.sin(ang) + cc * math.cos(ang)
            q = rng.uniform(0.0, 0.35)
            # a Tango tablet sees the part of a room it walks through: never cut off a door to
            # another explored room (the room would no longer connect the map); the other side,
            # or no cut when doors lie on both
            ends = [
                (d.a, d.midpoint, d.b)
                for d in hplan.doors
                if r in d.rooms and any(o in explored and o != r for o in d.rooms)
            ]
            door_px = frame.to_pixel(np.asarray(ends, float).reshape(-1, 2)) if ends else np.empty((0, 2))
            door_proj = door_px[:, 1] * math.sin(ang) + door_px[:, 0] * math.cos(ang)
            margin = 0.5 / resolution
            for sign in (1.0, -1.0):
                cut = np.quantile(sign * proj, q)
                if np.all(sign * door_proj >= cut + margin):
                    proj = sign * proj
                    break
            else:
                continue
            drop = np.zeros_like(cells)
            drop[rr[proj < cut], cc[proj < cut]] = True
            seen &= ~drop
    # rooms behind an open door to an explored room: a part seen through the door
    for d in hplan.doors:
        if len(set(d.rooms)) != 2:
            continue
        a, b = d.rooms
        if (a in explored) == (b in explored):
            continue
        other = b if a in explored else a
        if rng.random() < 0.3:
            continue
        cone = shapely.Point(d.midpoint).buffer(rng.uniform(1.0, 3.0))
        seen |= rasterise_polygons([cone], frame).astype(bool) & (labels == index[other]) & ~wall
    # the free space must be reachable: keep the largest component
    n, comp, stats, _ = cv2.connectedComponentsWithStats(seen.astype(np.uint8), connectivity=8)
    if n > 1:
        seen = comp == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    free = seen.copy()
    occ = np.zeros_like(free)
    if style == "thick":
        # walls seen two cells deep; furniture against the walls (its outline seen, inside unknown)
        near = cv2.dilate(free.astype(np.uint8), _disc(2)).astype(bool)
        occ = near & ~free & (wall | ~inside)
        for r in explored:
            poly = hplan.room(r).polygon
            for _ in range(int(rng.integers(1, 4))):
                p = np.asarray(poly.exterior.interpolate(rng.uniform(0, poly.exterior.length)).coords[0])
                w, h = rng.uniform(0.4, 1.2, size=2)
                box = shapely.box(p[0] - w / 2, p[1] - h / 2, p[0] + w / 2, p[1] + h / 2) & poly
                if box.is_empty:
                    continue
                fm = rasterise_polygons([box], frame).astype(bool) & free
                inner = cv2.erode(fm.astype(np.uint8), _disc(1)).astype(bool)
                free &= ~fm
                occ |= fm & ~inner
        # noise: unknown holes, spurious hits, missing wall cells
        n_holes = int(free.sum() * resolution**2 / 8.0)
        rr, cc = np.nonzero(free)
        for k in rng.integers(0, len(rr), size=n_holes) if len(rr) else []:
            rad = int(rng.uniform(0.1, 0.4) / resolution)
            hole = np.zeros(free.shape, np.uint8)
            cv2.circle(hole, (int(cc[k]), int(rr[k])), rad, 1, -1)
            free &= ~hole.astype(bool)
        specks = free & (rng.random(free.shape) < 0.002)
        free &= ~specks
        occ |= specks
        occ &= rng.random(occ.shape) > 0.05
    else:
        # ragged free edge, walls on part of the boundary only, clutter strokes near walls
        field = _smooth_noise(free.shape, rng, 3.0)
        grow = cv2.dilate(free.astype(np.uint8), _disc(2)).astype(bool) & inside & ~wall
        shrink = cv2.erode(free.astype(np.uint8), _disc(2)).astype(bool)
        free = np.where(field > 0.7, grow, np.where(field < -0.7, shrink, free))
        ring = cv2.dilate(free.astype(np.uint8), _disc(1)).astype(bool) & ~free
        drawn = _smooth_noise(free.shape, rng, 8.0) > -0.2  # about 60 % of the boundary
        occ = ring & drawn
        clutter = (_smooth_noise(free.shape, rng, 1.5) > 2.2) & free
        clutter &= ~cv2.erode(free.astype(np.uint8), _disc(0.6 / resolution)).astype(bool)
        free &= ~clutter
        occ |= clutter
    data = np.full(free.shape, -1, np.int8)
    data[free] = 0
    data[occ] = 100
    grid = OccupancyGrid(data, resolution, (frame.origin[0], frame.origin[1], 0.0)).crop_to_known(
        margin_cells=3
    )
    # the share of the plan the map shows: explored rooms of which the map holds a part (a closet
    # behind thick walls, or a room whose plan door lies elsewhere, may not be in it)
    present = np.bincount(labels[free], minlength=len(ids) + 1) * resolution**2
    shown = [r for r in explored if present[index[r]] >= 0.2 * hplan.room(r).polygon.area]
    covered = sum(hplan.room(r).polygon.area for r in shown) / sum(r.polygon.area for r in hplan.rooms)
    return grid, explored, covered


def style_rows(
    data: Path,
    n_plans: int = 20,
    seed: int = 0,
    completeness: tuple[int, ...] = (50, 75, 100),
    rotsets: tuple[str, ...] = ("step90", "any"),
    styles: tuple[str, ...] = STYLES,
    method: str = "mfr",
) -> list[dict[str, Any]]:
    """Registration rows on R2V plans drawn by the independent map styles."""
    from bench_registration import ROTSETS, _evaluate, select_plans
    from frslam_graph.datasets.simulator import Distortion, House

    from frslam_graph.floorplan import FloorPlan

    plans, _ = select_plans(data, n_plans, seed)
    rows = []
    for i, path in enumerate(plans):
        plan = FloorPlan.load(path)
        for rs in rotsets:
            rng_d = np.random.default_rng([seed, i, ROTSETS.index(rs), 21])
            dist = Distortion.random(rng_d, rotation=rs, plan_bounds=plan.bounds)
            house = House.from_plan(plan, dist)
            for si, style in enumerate(styles):
                for comp in completeness:
                    rng_m = np.random.default_rng([seed, i, ROTSETS.index(rs), comp, si, 21])
                    try:
                        grid, explored, covered = styled_map(house, style, comp / 100.0, rng_m)
                    except Exception as exc:  # a map that cannot be drawn: counted, not fatal
                        rows.append(
                            {"set": "style", "style": style, "case": path.stem, "setup_error": repr(exc)}
                        )
                        continue
                    reg, secs, cpu = _register(plan, grid, method)
                    row = {
                        "set": "style",
                        "style": style,
                        "case": path.stem,
                        "plan_index": i,
                        "n_rooms": len(plan.rooms),
                        "rotset": rs,
                        "completeness": comp,
                        "covered": round(covered, 4),
                        "time_s": secs,
                        "cpu_s": cpu,
                    }
                    row.update(_evaluate(plan, reg, dist.matrix))
                    rows.append(row)
    return rows


def other_building_rows(
    data: Path,
    n_plans: int = 12,
    seed: int = 0,
    completeness: tuple[int, ...] = (50, 100),
    method: str = "mfr",
) -> list[dict[str, Any]]:
    """Negative cases: R2V plan i against a map of plan i + 1 (simulator, ``thick`` and ``tango``
    maps, 90-degree rotations); any accepted registration is wrong."""
    from bench_registration import select_plans
    from frslam_graph.datasets.simulator import Distortion, House, partial_map

    from frslam_graph.floorplan import FloorPlan

    plans = [FloorPlan.load(p) for p in select_plans(data, n_plans, seed)[0]]
    rows = []
    for i, plan in enumerate(plans):
        other = plans[(i + 1) % len(plans)]
        dist = Distortion.random(
            np.random.default_rng([seed, i, 5]), rotation="step90", plan_bounds=other.bounds
        )
        house = House.from_plan(other, dist)
        for style in ("simulator", *STYLES):
            for comp in completeness:
                rng = np.random.default_rng([seed, i, comp, len(style)])
                if style == "simulator":
                    grid, _ = partial_map(house, comp / 100.0, rng)
                else:
                    grid, _, _ = styled_map(house, style, comp / 100.0, rng)
                reg, secs, cpu = _register(plan, grid, method)
                flagged = bool(reg.details.get("ambiguous", False)) if reg.ok else False
                rows.append(
                    {
                        "set": "other",
                        "style": style,
                        "case": f"{i}",
                        "completeness": comp,
                        "ok": bool(reg.ok),
                        "ambiguous": flagged,
                        "quality": float(reg.details.get("quality", 0.0)),
                        "time_s": secs,
                        "cpu_s": cpu,
                    }
                )
    return rows


# ----------------------------------------------------------------------------- report
def _pct(x: float) -> str:
    return f"{100.0 * x:.1f}"


def _point_table(rows: list[dict[str, Any]], title: str) -> list[str]:
    out = [
        f"#### {title}",
        "",
        "| map | rooms | ok | flip | rot. err (deg) | scale err (%) | aspect err (%) | err / annot. residual "
        "| residual (px) | halves' scales (%) | score | ambiguity | time (s) | reason |",
        "|---|---:|:-:|:-:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        h = r.get("halves_scale")
        halves_cell = f"{100 * h[0]:+.1f} / {100 * h[1]:+.1f}" if h else "-"
        out.append(
            f"| {r['case']} | {r['n_rooms']} | {'yes' if r['ok'] else 'no'} | {'right' if r['flip_ok'] else 'WRONG'} "
            f"| {r['rot_err_deg']:.1f} | {100 * r['scale_err']:+.1f} | {100 * r['aspect_err']:+.1f} "
            f"| {r['err_ratio']:.1f} | {r['residual_px']:.1f} | {halves_cell} | {r['score']:.2f} | {r['ambiguity']:.2f} "
            f"| {r['time_s']:.2f} | {r['reason'][:70]} |"
        )
    return out + [""]


def _point_summary(rows: list[dict[str, Any]], label: str) -> list[str]:
    if not rows:
        return []
    n = len(rows)
    right = [r["ok"] and r["flip_ok"] and r["rot_err_deg"] <= 2.0 for r in rows]  # NaN compares False
    scale = [r["ok"] and abs(r["scale_err"]) <= 0.02 for r in rows]
    pts = [r["ok"] and r["err_ratio"] <= 2.0 for r in rows]
    placed = [r["flip_ok"] and r["rot_err_deg"] <= 2.0 for r in rows]
    spread = ""
    if all(r.get("halves_scale") for r in rows):
        # the scale of some part of the map: within 2 % of the span of its halves' own scales
        part = [
            r["ok"]
            and min(0.0, *r["halves_scale"]) - 0.02 <= r["scale_err"] <= max(0.0, *r["halves_scale"]) + 0.02
            for r in rows
        ]
        spread = f", within 2 % of the span of the map's halves' own scales: {_pct(np.mean(part))} %"
    return [
        f"- {label} (n = {n}): accepted with flip + rotation within 2 deg: {_pct(np.mean(right))} % "
        f"(target >= 95); scale within 2 %: {_pct(np.mean(scale))} % (target: all){spread}; error at the annotated "
        f"points <= 2x residual: {_pct(np.mean(pts))} % (target: all); flip + rotation right including refused "
        f"placements: {_pct(np.mean(placed))} %; median time {np.median([r['time_s'] for r in rows]):.2f} s wall, "
        f"{np.median([r['cpu_s'] for r in rows]):.2f} s CPU",
    ]


def _style_table(rows: list[dict[str, Any]]) -> list[str]:
    out = [
        "#### Independent map styles (R2V plans): flip / rotation (5 deg) / IoU_a / ok (%), wrong matches not flagged",
        "",
        "| style | rotation set | completeness | n | flip | rotation | IoU_a | ok | wrong, not flagged ambiguous "
        "| median wall / CPU time (ms), plans <= 12 rooms |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    groups: dict[tuple, list] = defaultdict(list)
    for r in rows:
        groups[(r["style"], r["rotset"], r["completeness"])].append(r)
    for (style, rs, comp), g in sorted(groups.items()):
        small = [r["time_s"] for r in g if r["n_rooms"] <= 12]
        small_cpu = [r["cpu_s"] for r in g if r["n_rooms"] <= 12]
        wrong_unflagged = np.mean([r["wrong"] and not r["ambiguous"] for r in g])
        out.append(
            f"| {style} | {rs} | {comp} | {len(g)} | {_pct(np.mean([r['flip_ok'] for r in g]))} "
            f"| {_pct(np.mean([r['rot_ok'] for r in g]))} | {_pct(np.mean([r['iou_a'] for r in g]))} "
            f"| {_pct(np.mean([r['ok'] for r in g]))} | {_pct(wrong_unflagged)} "
            f"| {1000 * np.median(small) if small else float('nan'):.1f} / "
            f"{1000 * np.median(small_cpu) if small_cpu else float('nan'):.1f} |"
        )
    asked = [r for r in rows if r["completeness"] >= 50]
    ge50 = [r for r in asked if r["covered"] >= 0.5]
    if ge50:
        out.append("")
        for label, sel in (("asked", asked), ("shown", ge50)):
            flip, rot = np.mean([r["flip_ok"] for r in sel]), np.mean([r["rot_ok"] for r in sel])
            iou = np.mean([r["iou_a"] for r in sel])
            wu = np.mean([r["wrong"] and not r["ambiguous"] for r in sel])
            small = [r["time_s"] for r in sel if r["n_rooms"] <= 12]
            small_cpu = [r["cpu_s"] for r in sel if r["n_rooms"] <= 12]
            what = (
                "maps asked for >= 50 % of the plan"
                if label == "asked"
                else "of these, maps whose explored rooms shown hold >= 50 % of the plan's area"
            )
            out.append(
                f"- {what} (n = {len(sel)}): flip {_pct(flip)} % (target >= 99), rotation "
                f"{_pct(rot)} % (>= 99), IoU_a {_pct(iou)} % (>= 95), wrong and not flagged ambiguous {_pct(wu)} % "
                f"of all cases (<= 1), median time {1000 * np.median(small):.1f} ms wall, "
                f"{1000 * np.median(small_cpu):.1f} ms CPU (<= 20 on plans <= 12 rooms)"
            )
    return out + [""]


def report_real(rows: list[dict[str, Any]], cmd: str) -> str:
    """Markdown of all real and style rows, with the issue's targets beside the figures."""
    lines = [
        "### Registration on real maps and independent map styles (issue 21)",
        "",
        f"Command: `{cmd}`",
        "",
    ]
    halm = [r for r in rows if r.get("set") == "halmstad"]
    main = [r for r in halm if r["case"] not in DISTORTED]
    if halm:
        lines += _point_table(
            halm, "Halmstad: Tango sensor maps against the layouts (truth: annotated points)"
        )
        lines += _point_summary(main, "Halmstad without E5_08")
        lines += _point_summary([r for r in halm if r["case"] in DISTORTED], "E5_08 (badly distorted, apart)")
        lines.append("")
    ipa = [r for r in rows if r.get("set") == "ipa"]
    if ipa:
        lines += _point_table(ipa, "IPA plans against real SLAM maps (truth: hand-annotated points)")
    prb = [r for r in rows if r.get("set") == "prbonn_identity"]
    for r in prb:
        met = r["ok"] and r["flip_ok"] and r["max_disp_m"] <= 0.1 and r["rot_err_deg"] <= 0.5
        lines += [
            "#### PRBonn: GMapRoomSeg.png as the plan of GMap.yaml (truth: identity)",
            "",
            "| ok | flip | rot. err (deg) | max displacement of room corners (m) | scale err (%) | score | time (s) | target |",
            "|:-:|:-:|---:|---:|---:|---:|---:|---|",
            f"| {'yes' if r['ok'] else 'no'} | {'right' if r['flip_ok'] else 'WRONG'} | {r['rot_err_deg']:.2f} "
            f"| {r['max_disp_m']:.3f} | {100 * r['scale_err']:+.2f} | {r['score']:.2f} | {r['time_s']:.2f} "
            f"| within 0.1 m and 0.5 deg: **{'met' if met else 'NOT met'}** {r['reason'][:60]} |",
            "",
        ]
    sty = [r for r in rows if r.get("set") == "style" and "setup_error" not in r]
    if sty:
        lines += _style_table(sty)
    other = [r for r in rows if r.get("set") == "other"]
    if other:
        lines += [
            "#### Another building: plan i against a map of plan i + 1 (every accepted match is wrong)",
            "",
            "| map style | n | accepted (%) | accepted, not flagged ambiguous (%) |",
            "|---|---:|---:|---:|",
        ]
        for style in sorted({r["style"] for r in other}):
            g = [r for r in other if r["style"] == style]
            lines.append(
                f"| {style} | {len(g)} | {_pct(np.mean([r['ok'] for r in g]))} "
                f"| {_pct(np.mean([r['ok'] and not r['ambiguous'] for r in g]))} |"
            )
        lines.append("")
    errs = [r for r in rows if "setup_error" in r]
    if errs:
        lines += [f"Maps that could not be drawn: {len(errs)} (first: {errs[0]['setup_error']})", ""]
    return "\n".join(lines)


def run_real(
    data: Path,
    *,
    resolution: float = 0.05,
    n_plans: int = 20,
    seed: int = 0,
    completeness: tuple[int, ...] = (50, 75, 100),
    rotsets: tuple[str, ...] = ("step90", "any"),
    parts: tuple[str, ...] = ("halmstad", "ipa", "prbonn", "styles", "other"),
) -> list[dict[str, Any]]:
    """All rows of the real benchmark (sequential: tens of registrations, a few minutes)."""
    rows: list[dict[str, Any]] = []
    if "halmstad" in parts:
        rows += halmstad_rows(data, resolution)
    if "ipa" in parts:
        rows += ipa_rows(data)
    if "prbonn" in parts:
        rows.append(prbonn_identity_row(data))
    if "styles" in parts and n_plans > 0:
        rows += style_rows(data, n_plans, seed, completeness, rotsets)
    if "other" in parts:
        rows += other_building_rows(data, seed=seed)
    return rows
