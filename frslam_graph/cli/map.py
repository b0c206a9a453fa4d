"""``frslam map show MAP.yaml --out map.png``: render an occupancy map (metres, map frame)."""

from __future__ import annotations

from pathlib import Path

import typer

from frslam_graph.cli.app import console, map_app


@map_app.command("show")
def show(
    map_yaml: Path = typer.Argument(
        ..., help="ROS map_server YAML (image + resolution + origin), or an image with --resolution."
    ),
    out: Path = typer.Option(Path("map.png"), "--out", "-o", help="PNG to write."),
    resolution: float | None = typer.Option(
        None, "--resolution", help="Metres per pixel of a map image without a YAML (not for a YAML map)."
    ),
) -> None:
    """Render a map_server occupancy map to PNG with metric axes, and print its summary."""
    from frslam_graph.atomic import FIGURE_SUFFIXES, Outputs
    from frslam_graph.cli.option_errors import named_options
    from frslam_graph.occupancy import OccupancyGrid
    from frslam_graph.viz import save_grid_png

    outputs = Outputs()
    outputs.file(out, FIGURE_SUFFIXES)
    with named_options({"resolution": ("--resolution", resolution)} if resolution is not None else {}):
        grid = OccupancyGrid.load(map_yaml, resolution=resolution)
    outputs.write(out, lambda p: save_grid_png(grid, p, title=map_yaml.name))
    free = int(grid.free_mask().sum())
    occ = int(grid.occupied_mask().sum())
    area = free * grid.resolution**2
    console.print(
        f"{map_yaml}: {grid.height}×{grid.width} cells at {grid.resolution} m, origin {grid.origin}; "
        f"free {free} cells ({area:.1f} m²), occupied {occ}, unknown {grid.height * grid.width - free - occ}"
    )
    console.print(f"wrote {out}")
