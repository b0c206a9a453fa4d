"""Dev diagnosis (session 13): the Halmstad maps registered with the one-sided final fit and with
the current answer (``two``); per map the one-sided fit's wall offset ``d1``, the two-sided fit's
``d2`` (m) and both answers' scale / point errors.

    FRSLAM_SHARED_DATA=/work/shared/data python tools/dev_halmstad_sides.py [--only E5_04]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_real as br  # noqa: E402
from _fit_capture import CAPTURE, MODE  # noqa: E402  (installs the capturing final fit)

from frslam_graph.occupancy import OccupancyGrid  # noqa: E402
from frslam_graph.registration import register  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only")
    args = ap.parse_args()
    data = Path(os.environ.get("FRSLAM_SHARED_DATA", "/work/shared/data"))
    for _, name, plan, path, plan_pts, map_pts in br.halmstad_cases(data):
        if args.only and args.only not in name:
            continue
        grid = OccupancyGrid.from_image(path, 0.05)
        truth, res = br.fit_similarity(plan_pts, map_pts)
        line = f"{name:8s}"
        for ans in ("one", "two"):
            MODE["answer"] = ans
            CAPTURE.clear()
            reg = register(plan, grid)
            row = br.point_rows(reg, truth, plan_pts, map_pts, res)
            one = CAPTURE.get("one")
            if ans == "one":
                line += f" ok={int(row['ok'])} d1={one.delta if one else float('nan'):+.3f}"
                line += f" rms1={one.rms if one else float('nan'):.3f}"
            two = CAPTURE.get("two")
            if ans == "two" and two is not None:
                line += f" d2={two.delta:+.3f}"
            line += f" | {ans}: sc {100 * row['scale_err']:+.1f}% asp {100 * row['aspect_err']:+.1f}% pts {row['err_ratio']:.2f}"
        line += f" | {reg.reason[:80] if not reg.ok else ''}"
        print(line, flush=True)


if __name__ == "__main__":
    main()
