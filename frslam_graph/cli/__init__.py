"""``frslam`` command line: ``frslam --help``.

Each command lives in its own module; importing the module registers it on ``app``.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import signal
import sys
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

from rich.markup import escape

from frslam_graph.cli.app import app, err_console

try:  # typer >= 0.20 carries its own copy of click
    from typer._click.exceptions import UsageError as _UsageError
except ImportError:  # pragma: no cover - older typer on click itself
    from click.exceptions import UsageError as _UsageError
from frslam_graph.datasets.recording import RecordingWarning
from frslam_graph.errors import FrslamError, Interrupted

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
    "config",
)

for _name in COMMAND_MODULES:
    # a listed module that is absent is skipped (tests/test_cli.py checks every command exists);
    # an import error inside a present module is raised
    if importlib.util.find_spec(f"frslam_graph.cli.{_name}") is not None:
        importlib.import_module(f"frslam_graph.cli.{_name}")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A reader's warning (records skipped or repaired, naming the file and where) as one
    yellow line; any other warning as Python prints it."""
    if issubclass(category, RecordingWarning):
        err_console.print(f"[bold yellow]warning:[/] {escape(str(message))}", highlight=False, soft_wrap=True)
    else:
        _default_show(message, category, filename, lineno, file, line)


_default_show = warnings.showwarning


@contextmanager
def _signals_interrupt() -> Iterator[None]:
    """SIGINT and SIGTERM raise :class:`Interrupted` in this process while the block runs (a
    forked child, e.g. the odometry worker, dies of them as by default); handlers restored after.
    Outside the main thread (where Python cannot set handlers) nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    owner = os.getpid()

    def handler(signum: int, frame: object) -> None:
        if os.getpid() != owner:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        raise Interrupted(signum)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


#: an error line is cut to this many characters (a value quoted from a binary file, say)
MAX_MESSAGE_CHARS = 1000


def _one_line(text: str) -> str:
    """``text`` on one line: control characters (newlines, escapes of a binary file) shown as
    spaces, cut to :data:`MAX_MESSAGE_CHARS`."""
    text = "".join(" " if (ord(c) < 32 or 127 <= ord(c) < 160) else c for c in text)
    return text if len(text) <= MAX_MESSAGE_CHARS else text[: MAX_MESSAGE_CHARS - 3] + "..."


def _quiet_opencv() -> None:
    """OpenCV prints its own ``[ WARN:0@...]`` / ``[ERROR:0@...]`` lines on stderr (a damaged PNG)
    before the CLI's one line that names the file: only the CLI's stays. OpenCV 4 has its log level
    as ``cv2.setLogLevel``, OpenCV 5 as ``cv2.utils.logging.setLogLevel``."""
    os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
    import cv2

    logging = getattr(getattr(cv2, "utils", None), "logging", None)  # OpenCV 5
    if logging is not None:
        logging.setLogLevel(logging.LOG_LEVEL_SILENT)
    elif hasattr(cv2, "setLogLevel"):  # OpenCV 4 (pyproject admits >= 4.10): no cv2.utils.logging
        cv2.setLogLevel(0)  # LOG_LEVEL_SILENT


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``frslam`` script: runs the app, reporting input errors in one line.

    A usage error (unknown command or option, a value of the wrong type) is one line naming it
    and the command's ``--help``, exit code 2; a
    :class:`~frslam_graph.errors.FrslamError` (bad input file / field, an output that cannot be
    written) becomes one red line and exit code 2; SIGINT / SIGTERM stop the command with one line
    naming the outputs complete by then (unfinished ones are not left behind) and exit code 130 /
    143; any other exception is a bug and keeps its traceback.
    """
    _quiet_opencv()
    try:
        with warnings.catch_warnings(), _signals_interrupt():
            warnings.showwarning = _show_warning
            code = app(args=argv, standalone_mode=False)
    except _UsageError as exc:  # an unknown command / option, a value of the wrong type
        if not exc.format_message().strip():  # a group called without a command: its help was shown
            return exc.exit_code
        path, ctx = [], exc.ctx
        while ctx is not None and ctx.parent is not None:  # the commands below the program
            path.insert(0, ctx.info_name or "")
            ctx = ctx.parent
        err_console.print(
            f"[bold red]error:[/] {escape(_one_line(exc.format_message()))} "
            f"(see: {escape(' '.join(['frslam', *path, '--help']))})",
            highlight=False,
            soft_wrap=True,
        )
        return 2
    except FrslamError as exc:
        err_console.print(
            f"[bold red]error:[/] {escape(_one_line(str(exc)))}", highlight=False, soft_wrap=True
        )
        return 2
    except Interrupted as exc:
        name = signal.Signals(exc.signum).name
        left = ", ".join(exc.outputs) or "none"
        err_console.print(
            f"frslam: interrupted ({name}); outputs left: {escape(left)}", highlight=False, soft_wrap=True
        )
        return 128 + exc.signum
    except SystemExit as exc:
        code = exc.code
        return code if isinstance(code, int) else (0 if code is None else 1)
    return code if isinstance(code, int) else 0


if __name__ == "__main__":
    sys.exit(main())
