"""IPA plan images with their rooms filled in colour, as listing plans draw them (issue 21).

Each plan's rooms (read from the plain image) are filled with a light colour, a mid-tone colour
(random hue, HSV saturation 60-140 and 80-200 of 255, value 215-255 and 150-230) or one beige, and the
image is read again: rooms and area against the plain image's. Prints one line per plan and fill.

    FRSLAM_SHARED_DATA=../shared/data .venv/bin/python tools/dev_plan_colours.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _paths import SHARED_DATA  # noqa: E402
from bench_plan_images import labels_of  # noqa: E402

from frslam_graph.floorplan import plan_image  # noqa: E402

PLANS = ("office_d", "lab_intel", "office_b", "NLB", "lab_f_scan")


def _hsv(rng: np.random.Generator, sat: tuple[int, int], val: tuple[int, int]) -> np.ndarray:
    hsv = np.uint8([[[rng.integers(0, 180), rng.integers(*sat), rng.integers(*val)]]])
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]


def main() -> int:
    folder = SHARED_DATA / "floorplans" / "ipa"
    if not folder.is_dir():
        print(f"{folder}: not found (set FRSLAM_SHARED_DATA)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as d:
        for name in PLANS:
            grey = cv2.imread(str(folder / f"{name}.png"), cv2.IMREAD_GRAYSCALE)
            base = plan_image.load_image_plan_detailed(folder / f"{name}.png").plan
            rooms = labels_of(base, grey.shape, 1.0, grey.shape[0])
            rng = np.random.default_rng(1)
            for fill in ("light", "beige", "mid-tone"):
                img = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
                for k in range(1, int(rooms.max()) + 1):
                    if fill == "beige":
                        colour = np.array([210, 230, 245])
                    elif fill == "light":
                        colour = _hsv(rng, (60, 140), (215, 256))
                    else:
                        colour = _hsv(rng, (80, 200), (150, 230))
                    img[(rooms == k) & (grey > 250)] = colour
                path = Path(d) / f"{name}_{fill}.png"
                cv2.imwrite(str(path), img)
                try:
                    plan = plan_image.load_image_plan_detailed(path).plan
                    out = f"{len(plan.rooms)} rooms, area x{plan.area / base.area:.2f}"
                except Exception as exc:  # a reading that fails is the result
                    out = f"refused: {exc}"
                print(f"{name} {fill}: plain {len(base.rooms)} rooms -> {out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
