"""Room-segmentation acceptance check: polygon area of each room vs its label pixel count × res².

    python tools/roomseg_areas.py [../shared/data/prbonn]

Prints a Markdown table per ``*RoomSeg.png`` (with its ``<map>.yaml``): rooms, areas, the
relative difference (target: within 3 %), corners, holes and the load time.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2

from frslam_graph.floorplan.roomseg import load_room_segmentation, read_map_yaml

DEFAULT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "prbonn"


def main() -> None:
    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT
    pngs = sorted(folder.glob("*RoomSeg.png"))
    if not pngs:
        raise SystemExit(f"no *RoomSeg.png in {folder}")
    for png in pngs:
        t0 = time.perf_counter()
        plan = load_room_segmentation(png)
        dt = time.perf_counter() - t0
        yaml = png.with_name(png.stem[: -len("RoomSeg")] + ".yaml")
        res = read_map_yaml(yaml)[0]
        labels = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        print(
            f"\n## {png.name} + {yaml.name}: {len(plan.rooms)} rooms, {len(plan.doors)} doors, {1000 * dt:.0f} ms\n"
        )
        print("| room | polygon m² | pixels × res² m² | difference | corners | holes |")
        print("|---|---|---|---|---|---|")
        worst = 0.0
        for room in plan.rooms:
            ref = int((labels == int(room.id.split("_")[1])).sum()) * res * res
            diff = (room.area - ref) / ref
            worst = max(worst, abs(diff))
            corners = len(room.polygon.exterior.coords) - 1
            print(
                f"| {room.id} | {room.area:.3f} | {ref:.3f} | {100 * diff:+.2f} % | {corners} | {len(room.polygon.interiors)} |"
            )
        print(f"\nworst |difference|: {100 * worst:.2f} % (target <= 3 %)")


if __name__ == "__main__":
    main()
