"""``frslam config dump [--all] [--out FILE]``: the default configuration as commented YAML."""

from __future__ import annotations

from pathlib import Path

import typer

from frslam_graph.cli.app import config_app, console


@config_app.command("dump")
def dump(
    every: bool = typer.Option(False, "--all", help="Every key (default: the dozen keys commonly changed)."),
    out: Path | None = typer.Option(
        None, "--out", "-o", help="YAML file to write (default: standard output)."
    ),
) -> None:
    """Print or write the default configuration as YAML, each key's meaning and unit above it."""
    from frslam_graph.atomic import Outputs, write_text
    from frslam_graph.config import BASIC_KEYS, FRSlamConfig

    text = FRSlamConfig().to_yaml(None if every else BASIC_KEYS)
    if out is None:
        typer.echo(text, nl=False)
        return
    outputs = Outputs()
    outputs.file(out, (".yaml", ".yml"))
    outputs.write(out, lambda p: write_text(p, text))
    console.print(f"wrote {out}", highlight=False, soft_wrap=True, markup=False)
