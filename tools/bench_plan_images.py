"""Rooms of real plan images against their ground truth, at several pixel densities (issue 21).

Each IPA plan image with a ``*_gt_segmentation.png`` (``floorplans/ipa/``) is resampled to each
``--scales`` factor (OpenCV area interpolation below 1, linear above: a plan exported or scanned
at another pixel density), read by ``FloorPlan.load`` as a user's file would be, and its rooms
are drawn back at the original size. A ground-truth room (the segmentation's regions grown over
the plan's free space, ``FloorPlan.from_image(..., segmentation="auto")``) is *matched* when one
room read from the image overlaps it with IoU >= 0.5. The table gives per plan the rooms read and
the matched share at each scale, and the mean matched share per scale; the same with a fixed
``--door-width`` (px at the original density, scaled with the image: what a user who knows the
plan's door width gets) in the same run, as the reference.

    FRSLAM_SHARED_DATA=../shared/data .venv/bin/python tools/bench_plan_images.py
    .venv/bin/python tools/bench_plan_images.py --scales 0.5 1 2 --door-width 30
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _paths import SHARED_DATA  # noqa: E402

from frslam_graph.floorplan import FloorPlan  # noqa: E402
from frslam_graph.raster import RasterFrame, rasterise_plan  # noqa: E402

MATCH_IOU = 0.5


def labels_of(plan: FloorPlan, shape: tuple[int, int], scale: float, height: float) -> np.ndarray:
    """The plan's rooms, read from an image ``height`` px high (``scale`` times ``shape``), drawn
    at ``shape``: label k + 1 for room k, 0 elsewhere (a pixel is a room's when its centre is)."""
    # the plan frame: x = column, y = height - row; a raster frame's row 0 is its lowest y
    frame = RasterFrame(scale, (0.0, height - shape[0] * scale), shape)
    return np.flipud(rasterise_plan(plan, frame, labels=True))


def matched_share(truth: np.ndarray, found: np.ndarray) -> float:
    """Share of the ground-truth rooms (labels > 0 of ``truth``) that one room of ``found``
    overlaps with IoU >= :data:`MATCH_IOU`."""
    ids = np.unique(truth)
    ids = ids[ids > 0]
    if len(ids) == 0:
        return float("nan")
    n = int(found.max()) + 1
    sizes = np.bincount(found.ravel(), minlength=n)
    hits = 0
    for i in ids:
        m = truth == i
        inter = np.bincount(found[m], minlength=n)
        inter[0] = 0
        j = int(inter.argmax())
        if j > 0 and inter[j] / (m.sum() + sizes[j] - inter[j]) >= MATCH_IOU:
            hits += 1
    return hits / len(ids)


def rows(folder: Path, scales: list[float], door_width: float | None, tmp: Path) -> list[dict]:
    out = []
    for seg in sorted(folder.glob("*_gt_segmentation.png")):
        path = folder / seg.name.replace("_gt_segmentation", "")
        truth_plan = FloorPlan.from_image(path, segmentation="auto")
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        truth = labels_of(truth_plan, grey.shape, 1.0, grey.shape[0])
        row = {"plan": path.name, "truth": len(truth_plan.rooms), "rooms": [], "matched": []}
        for s in scales:
            img = (
                grey
                if s == 1
                else cv2.resize(
                    grey, None, fx=s, fy=s, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
                )
            )
            p = tmp / f"{path.stem}_{s:g}.png"
            cv2.imwrite(str(p), img)
            opts = {} if door_width is None else {"door_width": door_width * s}
            try:
                plan = FloorPlan.load(p, **opts)
            except Exception as exc:  # a reading that fails matches nothing
                print(f"{p.name}: {exc}", file=sys.stderr)
                row["rooms"].append(0)
                row["matched"].append(0.0)
                continue
            row["rooms"].append(len(plan.rooms))
            row["matched"].append(matched_share(truth, labels_of(plan, grey.shape, s, img.shape[0])))
        out.append(row)
    return out


def table(title: str, result: list[dict], scales: list[float]) -> str:
    head = "| plan | truth | " + " | ".join(f"x{s:g}: rooms, matched" for s in scales) + " |"
    lines = [f"#### {title}", "", head, "|---|---:|" + "---:|" * len(scales)]
    for r in result:
        cells = " | ".join(f"{n}, {m:.2f}" for n, m in zip(r["rooms"], r["matched"], strict=True))
        lines.append(f"| {r['plan']} | {r['truth']} | {cells} |")
    means = [np.mean([r["matched"][i] for r in result]) for i in range(len(scales))]
    lines.append("| **mean matched** | | " + " | ".join(f"**{m:.3f}**" for m in means) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scales", type=float, nargs="+", default=[0.5, 0.75, 1.0, 1.5, 2.0, 3.0])
    ap.add_argument(
        "--door-width",
        type=float,
        default=30.0,
        help="px at the original density; the reference rows (0: none)",
    )
    args = ap.parse_args(argv)
    if any(not 0.1 <= s <= 8 for s in args.scales):
        print("--scales: expected factors between 0.1 and 8", file=sys.stderr)
        return 2
    folder = SHARED_DATA / "floorplans" / "ipa"
    if not folder.is_dir():
        print(f"{folder}: not found (set FRSLAM_SHARED_DATA)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        print("### Plan images against their ground-truth rooms, at several pixel densities\n")
        print(table("default door width (the sweep)", rows(folder, args.scales, None, tmp), args.scales))
        if args.door_width > 0:
            ref = rows(folder, args.scales, args.door_width, tmp)
            print()
            print(
                table(
                    f"fixed door width {args.door_width:g} px at x1 (scaled with the image)", ref, args.scales
                )
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
