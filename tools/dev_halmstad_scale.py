"""Dev diagnosis (session 15, issue 21): where MFR's scale goes wrong on the Halmstad maps.

    FRSLAM_SHARED_DATA=/work/shared/data python tools/dev_halmstad_scale.py [--only E5_06] [--trace]
    python tools/dev_halmstad_scale.py --synthetic

Per map, scale errors (%) against the annotation truth (the similarity fitted to the annotated
points, as in ``bench_real.py``) of:

* the stages of one registration: the best screened placement (``scr``: after the screenings and
  any wide search), the final fit's start (``pol``: the best after the scale polish), the one-sided final fit (``fin``, its wall
  offset ``d1`` in m) and the answer (``ans``: the two-sided scales where ``d1`` < -0.025 m);
  ``--trace`` also prints every stage's placements (coarse hypotheses, screenings, wide search,
  polish) with their keys;
* the refinements started from the truth (in the registration's grid frame): the screening fit
  (``Tscr``), the one-sided final fit (``T1``) and the two-sided one (``T2``): a fit that drifts
  from the truth has its optimum elsewhere (the evidence, as that fit weighs it, prefers
  another scale); one that stays has lost the truth's basin earlier, at its start;
* the map's own non-rigidity: the annotated points split at the median of their principal axis,
  each half's own similarity's scale against the whole's (``h1``, ``h2``), and the RMS error
  (m) at each half's points of the truth and of the answer (``rms h1``, ``rms h2``: truth/answer).

``--synthetic``: the suspected cause in isolation, on the tests' seven-room plan
(``tests/test_registration.py``; five rooms explored, walls a one-cell ring): the unexplored rooms
seen 0 / 1 / 2 m deep behind the open doors, and 0 / 1 / 2 m of free space seen through window
gaps (every fourth metre of the outer walls): the answer's scale error and the screening and final
fits' drift from the truth.

Frames: plan units -> map metres (``truth``, answers); the refinements in the grid frame of the
map's known-area crop (``MapObservation.to_map``). Scales are geometric means of the two axes'.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_real as br  # noqa: E402

from frslam_graph.occupancy import OccupancyGrid  # noqa: E402
from frslam_graph.raster import RasterFrame, rasterise_plan  # noqa: E402
from frslam_graph.registration import register  # noqa: E402
from frslam_graph.registration.mfr import coarse, fine  # noqa: E402
from frslam_graph.registration.mfr import register as mfr_register  # noqa: E402


class Tracer:
    """Wraps the MFR stages for one registration at a time: records the placements each stage
    hands on (matrices, plan -> grid frame) and the inputs of the final fit."""

    def __init__(self) -> None:
        self.events: list[tuple[str, list[tuple[np.ndarray, float]]]] = []
        self.ctx: dict[str, Any] = {}
        self._orig = (fine.screen, coarse.wide_search, fine.polish_scales, mfr_register._final, coarse.search)
        tracer = self
        screen, wide, polish, final, search = self._orig

        def t_screen(pm, obs, chosen, opts, tol):
            screen(pm, obs, chosen, opts, tol)
            tracer.events.append(("screen", [(h.refined.matrix, h.quick) for h in chosen]))

        def t_wide(pm, obs, seeds, opts, tol, k, **kw):
            out = wide(pm, obs, seeds, opts, tol, k, **kw)
            tracer.events.append((f"wide ({len(seeds)} seeds)", [(h.matrix, h.key) for h in out[:6]]))
            return out

        def t_polish(pm, obs, h, opts, tol):
            polish(pm, obs, h, opts, tol)
            tracer.events.append(("polish", [(h.refined.matrix, h.quick)]))

        def t_final(pm, obs, best, opts, tol_f):
            out = final(pm, obs, best, opts, tol_f)
            tracer.ctx.update(pm=pm, obs=obs, opts=opts, screened=out[0], final=out[1])
            return out

        def t_search(pm, obs, masks, opts, **kw):
            hyps, rotations = search(pm, obs, masks, opts, **kw)
            tracer.events.append(("coarse (top 8)", [(h.matrix, h.key) for h in hyps[:8]]))
            return hyps, rotations

        fine.screen = t_screen
        coarse.wide_search = t_wide
        fine.polish_scales = t_polish
        mfr_register._final = t_final
        coarse.search = t_search

    def clear(self) -> None:
        self.events.clear()
        self.ctx.clear()


def from_truth(ctx: dict[str, Any], truth_grid: np.ndarray) -> dict[str, Any]:
    """The screening, one-sided and two-sided final refinements started at ``truth_grid``."""
    pm, obs, opts = ctx["pm"], ctx["obs"], ctx["opts"]
    final_kw = dict(
        scales=(0.05,),
        spacing_px=opts["sample_px"],
        max_points=opts["max_points"],
        iterations=opts["iterations"],
    )
    return {
        "Tscr": fine.refine_from(
            pm,
            obs,
            truth_grid,
            opts["delta"],
            opts,
            scales=opts["quick_scales"],
            spacing_px=4.0,
            max_points=opts["quick_points"],
            iterations=opts["quick_iterations"],
        ),
        "T1": fine.refine_from(pm, obs, truth_grid, opts["delta"], opts, **final_kw),
        "T2": fine.refine_from(pm, obs, truth_grid, opts["delta"], opts, walls=True, **final_kw),
    }


def seen_through(plan: Any, truth: np.ndarray, rooms: list[str], behind_m: float, window_m: float):
    """An OccupancyGrid (0.05 m) of the house ``truth · plan``: ``rooms`` seen whole (free inside,
    a one-cell occupied ring open at doors), the other rooms seen ``behind_m`` deep from the open
    doors into them, and ``window_m`` of free space outside gaps in the outer walls (every fourth
    metre of them)."""
    res = 0.05
    house = plan.transformed(truth, units="m")
    frame = RasterFrame.around(house.bounds, res, margin=0.6 + window_m)
    lab = rasterise_plan(house, frame, labels=True)
    pad = np.pad(lab, 1)
    ring = np.zeros(lab.shape, bool)
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        ring |= pad[1 + dr : 1 + dr + lab.shape[0], 1 + dc : 1 + dc + lab.shape[1]] != lab

    def line(d: Any) -> np.ndarray:
        m = np.zeros(lab.shape, np.uint8)
        a, b = frame.to_pixel(np.array([d.a, d.b])) - 0.5
        cv2.line(m, tuple(np.round(a).astype(int)), tuple(np.round(b).astype(int)), 1, 3)
        return m.astype(bool)

    doors = np.zeros(lab.shape, bool)
    behind = np.zeros(lab.shape, bool)
    for d in house.doors:
        doors |= line(d)
        if behind_m > 0 and sum(r in rooms for r in d.rooms) == 1:
            behind |= ndimage.distance_transform_edt(~line(d)) * res <= behind_m
    ids = [r.id for r in house.rooms]
    seen = ndimage.binary_dilation(np.isin(lab, [ids.index(r) + 1 for r in rooms]), iterations=1)
    occ = (lab > 0) & ring & ~doors & seen
    free = (lab > 0) & ~((lab > 0) & ring & ~doors) & (seen | behind)
    if window_m > 0:
        outside = ~ndimage.binary_fill_holes(free | occ)
        ys, xs = np.nonzero(occ & ndimage.binary_dilation(outside))
        gap = ((xs // 20 + ys // 20) % 4) == 0
        win = np.zeros(lab.shape, bool)
        win[ys[gap], xs[gap]] = True
        occ &= ~win
        free |= win | (ndimage.binary_dilation(win, iterations=int(window_m / res)) & outside)
    return OccupancyGrid.from_masks(free, occ, res, (frame.origin[0], frame.origin[1], 0.0))


def synthetic(tracer: Tracer) -> None:
    """The ``--synthetic`` rows (see the module docstring)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_registration import EXPLORED, synthetic_plan, truth_matrix

    plan = synthetic_plan()
    print(
        "| flip, rotation | behind doors (m) | windows (m) | ok | answer scale | screen from truth | final from truth |"
    )
    print("|---|---:|---:|:-:|---:|---:|---:|")
    for flipped, rot_deg in ((False, 0.0), (True, 90.0), (False, 30.0), (True, -60.0)):
        truth = truth_matrix(flipped, rot_deg)
        for behind_m, window_m in ((0.0, 0.0), (1.0, 0.0), (2.0, 0.0), (0.0, 1.0), (0.0, 2.0)):
            tracer.clear()
            reg = register(plan, seen_through(plan, truth, EXPLORED, behind_m, window_m), method="mfr")
            if "obs" not in tracer.ctx:
                print(f"| {int(flipped)}, {rot_deg:g} | {behind_m:g} | {window_m:g} | no final fit |")
                continue
            t = from_truth(tracer.ctx, np.linalg.inv(tracer.ctx["obs"].to_map) @ truth)
            ref = br.scale_of(truth)
            print(
                f"| {int(flipped)}, {rot_deg:g} | {behind_m:g} | {window_m:g} | {'yes' if reg.ok else 'no'} "
                f"| {100 * (br.scale_of(reg.matrix) / ref - 1):+.2f} % | {100 * (br.scale_of(t['Tscr'].matrix) / ref - 1):+.2f} % "
                f"| {100 * (br.scale_of(t['T1'].matrix) / ref - 1):+.2f} % |",
                flush=True,
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="maps whose name contains this")
    ap.add_argument("--trace", action="store_true", help="print every stage's placements")
    ap.add_argument("--synthetic", action="store_true", help="the synthetic openings check instead")
    args = ap.parse_args()
    data = Path(os.environ.get("FRSLAM_SHARED_DATA", "/work/shared/data"))
    tracer = Tracer()
    if args.synthetic:
        synthetic(tracer)
        return
    print(
        "| map | ok | scr | pol | fin | d1 (m) | ans | Tscr | T1 | T2 | h1 / h2 | rms h1 truth/ans | rms h2 truth/ans |"
    )
    print("|---|:-:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for _, name, plan, path, plan_pts, map_pts in br.halmstad_cases(data):
        if args.only and args.only not in name:
            continue
        truth, _ = br.fit_similarity(plan_pts, map_pts)
        tracer.clear()
        reg = register(plan, OccupancyGrid.from_image(path, 0.05), method="mfr")
        ctx = tracer.ctx
        if "obs" not in ctx:
            print(f"| {name} | no final fit: {reg.reason[:60]} |")
            continue
        truth_grid = np.linalg.inv(ctx["obs"].to_map) @ truth

        def err(m: np.ndarray, ref: float = br.scale_of(truth_grid)) -> str:
            return f"{100.0 * (br.scale_of(m) / ref - 1.0):+.1f}"

        screens = [ev for ev in tracer.events if ev[0] == "screen"]
        best_screen = max((p for ev in screens for p in ev[1]), key=lambda p: p[1])[0]
        pol = err(ctx["screened"].matrix)
        t = from_truth(ctx, truth_grid)
        hs = []
        for m in br.halves(map_pts):
            own, _ = br.fit_similarity(plan_pts[m], map_pts[m])
            hs.append(
                (
                    100.0 * (br.scale_of(own) / br.scale_of(truth) - 1.0),
                    br.rms_at(truth, plan_pts[m], map_pts[m]),
                    br.rms_at(reg.matrix, plan_pts[m], map_pts[m]),
                )
            )
        print(
            f"| {name} | {'yes' if reg.ok else 'no'} | {err(best_screen)} | {pol} | {err(ctx['final'].matrix)} "
            f"| {ctx['final'].delta:+.3f} | {100.0 * (br.scale_of(reg.matrix) / br.scale_of(truth) - 1.0):+.1f} "
            f"| {err(t['Tscr'].matrix)} | {err(t['T1'].matrix)} | {err(t['T2'].matrix)} "
            f"| {hs[0][0]:+.1f} / {hs[1][0]:+.1f} | {hs[0][1]:.2f} / {hs[0][2]:.2f} | {hs[1][1]:.2f} / {hs[1][2]:.2f} |",
            flush=True,
        )
        if args.trace:
            for stage, placed in tracer.events:
                print(f"    {stage}: " + ", ".join(f"{err(m)} ({k:.3f})" for m, k in placed))


if __name__ == "__main__":
    main()
