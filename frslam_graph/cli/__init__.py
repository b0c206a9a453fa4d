"""``frslam`` command line: ``frslam --help``.

Each command lives in its own module; importing the module registers it on ``app``.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys

from frslam_graph.cli.app import app, err_console
from frslam_graph.errors import FrslamError

# One module per command group; each adds its commands to ``app`` when imported.
COMMAND_MODULES = (
    "plan",
    "map",
    "demo",
    "run",
    "inspect",
    "evaluate",
    "simulate",
    "register",
    "navigate",
)

for _name in COMMAND_MODULES:
    # a listed module that is absent is skipped (tests/test_cli.py checks every command exists);
    # an import error inside a present module is raised
    if importlib.util.find_spec(f"frslam_graph.cli.{_name}") is not None:
        importlib.import_module(f"frslam_graph.cli.{_name}")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``frslam`` script: runs the app, reporting input errors in one line."""
    try:
        app(args=argv, standalone_mode=False)
    except FrslamError as exc:
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        return 2
    except SystemExit as exc:  # typer/click exit codes
        return int(exc.code or 0)
    except Exception as exc:  # click usage errors
        import click

        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            return exc.exit_code
        if isinstance(exc, click.exceptions.Abort):
            err_console.print("aborted")
            return 1
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main())
