"""Diagnostic (issue 21 d4): MFR on maps of the Intel log stopped part-way, against the
hand-annotated truth (``tests/data/intel_lab_plan_points.csv``).

Snapshots: FRSlam without a plan, serial, no final batch, the map (free-space weights, 0.05 m)
saved after each of ``--scans`` (skipped when ``DIR/snap_N.yaml`` exists); ``--final MAP.yaml``
adds a finished run's map. For each map: the share of the plan's room area (at the annotated
transform) that known cells cover, MFR's result (flip, rotation, scales, RMS at the annotated
points) and the gate's IoU x precision x recall at several structure tolerances (m), at MFR's
placement and at the annotated one; and the floor-plan judge's map checks at both (share of
occupied cells within 0.1 / 0.25 m of a plan wall, ``min_map_fit``; share of the plan's observed
interior walls the map has seen through at margin 0.2 / 0.4 m, ``max_walls_in_free_space``).

    .venv/bin/python tools/intel_partial_maps.py --dir /tmp/snaps --scans 1500 2000 3000 4000 5500 7000 \\
        --final run0/map.yaml
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from _paths import REPO as ROOT  # noqa: E402
from _paths import SHARED_DATA  # noqa: E402

sys.path.insert(0, str(ROOT / "tests"))
TOLERANCES = (0.15, 0.25, 0.35, 0.5)


def snapshots(recording: Path, scans: list[int], folder: Path) -> None:
    """Save the maps after each of ``scans`` into ``folder`` (only those missing)."""
    from frslam_graph.datasets import open_recording

    from frslam_graph.offline import process
    from frslam_graph.slam import FRSlam

    todo = {n for n in scans if not (folder / f"snap_{n}.yaml").exists()}
    if not todo:
        return
    folder.mkdir(parents=True, exist_ok=True)
    slam = FRSlam(floor_plan=None)

    def until_last():
        for i, scan in enumerate(open_recording(recording)):
            yield scan
            if i + 1 in todo:
                slam.occupancy_grid(0.05, free_space=True).save(folder / f"snap_{i + 1}.yaml")
                if i + 1 == max(todo):
                    return

    process(slam, until_last(), batch=False, parallel=False)


def main() -> None:
    import shapely
    from shapely.affinity import affine_transform
    from test_intel_plan_points import fit_similarity, intel_plan_points, residuals

    import frslam_graph as fr
    from frslam_graph.localisation.relocalisation import Relocaliser, RelocaliserParams
    from frslam_graph.plan_checks import occupied_points, walls_through_free_space
    from frslam_graph.registration import Registration, register
    from frslam_graph.registration.mfr import fine
    from frslam_graph.registration.mfr.map_side import observe_map
    from frslam_graph.registration.mfr.plan_side import prepare_plan

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data",
        type=Path,
        default=SHARED_DATA,
    )
    ap.add_argument("--dir", type=Path, required=True, help="folder of the snapshot maps")
    ap.add_argument("--scans", type=int, nargs="*", default=[])
    ap.add_argument("--final", type=Path, default=None, help="a finished run's map.yaml")
    args = ap.parse_args()
    snapshots(args.data / "carmen" / "intel.clf.bz2", args.scans, args.dir)
    _, plan_xy, map_xy = intel_plan_points(ROOT / "tests" / "data")
    truth = fit_similarity(plan_xy, map_xy, True)
    plan = fr.FloorPlan.load(args.data / "floorplans" / "ipa" / "lab_intel.png")
    pm = prepare_plan(plan, adjacency="doors")
    a = [truth[0, 0], truth[0, 1], truth[1, 0], truth[1, 1], truth[0, 2], truth[1, 2]]
    rooms = shapely.union_all([affine_transform(r.polygon, a) for r in plan.rooms])
    maps = [(str(n), args.dir / f"snap_{n}.yaml") for n in args.scans]
    maps += [("final", args.final)] if args.final is not None else []
    for name, path in maps:
        g = fr.OccupancyGrid.load(path)
        rr, cc = np.nonzero(g.free_mask() | g.occupied_mask())
        xy = g.cell_to_world(np.column_stack([cc + 0.5, rr + 0.5]))
        seen = shapely.contains_xy(rooms, xy[:, 0], xy[:, 1]).sum() * g.resolution**2 / rooms.area
        reg = register(plan, g)
        e = residuals(reg.matrix, plan_xy, map_xy)
        print(
            f"{name}: seen {seen:.0%}; ok={reg.ok} flip={reg.flipped} rot={reg.rotation_deg:.1f} deg "
            f"scale={reg.scale[0]:.4f}/{reg.scale[1]:.4f} m/px rooms={list(reg.rooms)} "
            f"rms@points {np.sqrt(np.mean(e**2)):.2f} m; {reg.reason}"
        )
        obs = observe_map(g, min_area_m2=2.0, coarse_px=80)
        delta = float(reg.details.get("delta_m") or 0.06)
        for who, m in (("MFR", reg.matrix), ("truth", truth)):
            gm = np.linalg.inv(obs.to_map) @ m
            iou, _ = fine.placed_rooms_iou(pm, obs, gm, 0.5)
            row = f"   {who}: IoU {iou:.2f}"
            for tol in TOLERANCES:
                p, r = fine.wall_precision_recall(pm, obs, gm, tol, 1000, delta=delta)
                row += f" | {tol} m: p {p:.2f} r {r:.2f} q {iou * p * r:.2f}"
            reloc = Relocaliser(Registration.from_matrix(m).apply(plan), RelocaliserParams())
            occ = occupied_points(g)
            fits = "/".join(f"{reloc.fit_points(occ, t):.2f}" for t in (0.1, 0.25))
            free = "/".join(f"{walls_through_free_space(reloc, g, t):.2f}" for t in (0.2, 0.4))
            print(row + f" || map fit {fits}, walls in free space {free}", flush=True)


if __name__ == "__main__":
    main()
