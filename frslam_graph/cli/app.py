"""The typer application object shared by the command modules, and its error handling.

Command modules (``frslam_graph.cli.<name>``) import ``app`` (or a sub-app) from here and add
their commands. Only the CLI prints; library code raises :class:`~frslam_graph.errors.FrslamError`,
which :func:`main` turns into one red line naming the file and the problem, and exit code 2.
"""

from __future__ import annotations

import typer
from rich.console import Console

app = typer.Typer(
    name="frslam",
    help="FR-SLAM: floor-plan registration + factor-graph 2D SLAM.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
plan_app = typer.Typer(help="Floor plans: show, convert.", no_args_is_help=True)
map_app = typer.Typer(help="Occupancy maps (ROS map_server YAML + image): show.", no_args_is_help=True)
config_app = typer.Typer(
    help="Configuration: dump the defaults with their descriptions.", no_args_is_help=True
)
app.add_typer(plan_app, name="plan")
app.add_typer(map_app, name="map")
app.add_typer(config_app, name="config")

console = Console()
err_console = Console(stderr=True)


def _version() -> str:
    """The installed package's version (its metadata), or "unknown" when run from a bare tree."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("frslam")
    except PackageNotFoundError:
        return "unknown"


def _print_version(value: bool) -> None:
    if value:
        console.print(f"frslam {_version()}", highlight=False)
        raise typer.Exit()


@app.callback()
def _root(
    show_version: bool = typer.Option(
        False, "--version", help="Print the version and exit.", callback=_print_version, is_eager=True
    ),
) -> None:
    """FR-SLAM: floor-plan registration + factor-graph 2D SLAM."""
