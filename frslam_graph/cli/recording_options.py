"""The reader options shared by ``inspect``, ``run`` and ``compare``, and opening a recording
with them so that a bad value is one line naming the CLI option and the choices the file offers.

The readers (:mod:`frslam_graph.datasets`) raise :class:`~frslam_graph.errors.OptionError` naming
their own argument (``scan_topic``); here it becomes the option a CLI user typed (``--scan-topic``).
"""

from __future__ import annotations

import inspect
import math
import shlex
from pathlib import Path
from typing import Annotated, Any

import typer

from frslam_graph.errors import OptionError, RecordingError

ScanTopic = Annotated[
    str | None, typer.Option("--scan-topic", help="Bag: scan topic (default: auto-detected).")
]
OdomTopic = Annotated[
    str | None, typer.Option("--odom-topic", help="Bag: odometry topic (default: auto-detected; '' = none).")
]
Laser = Annotated[str | None, typer.Option("--laser", help="CARMEN: front, rear or all (default front).")]
Odom = Annotated[
    str | None,
    typer.Option(
        "--odom",
        help="CARMEN: 'auto' (default: interpolated when the laser lines copy a stale pose and the "
        "stamps never go backwards, else 'laser'), the 'laser' lines' poses, interpolated 'odom', 'none'.",
    ),
]
PlaneTol = Annotated[
    float | None, typer.Option("--plane-tol", help="Point clouds: half thickness of the slice kept, m.")
]

#: the CLI option of each reader argument
FLAGS = {
    "scan_topic": "--scan-topic",
    "odom_topic": "--odom-topic",
    "laser": "--laser",
    "odom": "--odom",
    "plane_tol": "--plane-tol",
}
#: how the CLI names each reader's kind of recording
KINDS = {"CarmenLog": "CARMEN log", "RosBag": "ROS bag", "PointCloudFolder": "point-cloud folder"}
#: choices listed in a message at most
MAX_CHOICES = 20


def _quoted(value: object, limit: int = 80) -> str:
    text = shlex.quote(str(value))
    return text if len(text) <= limit else text[: limit - 3] + "..."


def option_error(exc: OptionError) -> RecordingError:
    """``exc`` said with the CLI option: ``file: --laser rear: no RLASER/... records (choices: front)``."""
    flag = FLAGS.get(exc.option, exc.option)
    named = flag if exc.value is None else f"{flag} {_quoted(exc.value)}"
    choices = [_quoted(c) if c and "'" not in c else c for c in exc.choices[:MAX_CHOICES]]
    more = f", ... ({len(exc.choices)} in all)" if len(exc.choices) > MAX_CHOICES else ""
    listed = f" (choices: {', '.join(choices)}{more})" if choices else ""
    return RecordingError(f"{named}: {exc.problem}{listed}", source=exc.source)


def open_recording_with(path: Path, **options: Any):
    """Open ``path`` with the reader options given (None = not given), naming CLI options in errors.

    An option the recording's reader does not take (``--laser`` on a bag) is one line naming it and
    the options that reader takes."""
    from frslam_graph.datasets import open_recording, reader_for

    opts = {k: v for k, v in options.items() if v is not None}
    tol = opts.get("plane_tol")
    if tol is not None and not 0.0 < tol < math.inf:
        raise RecordingError(
            f"--plane-tol {tol:g}: expected a positive finite thickness in metres", source=path
        )
    reader = reader_for(path) if path.exists() else None
    if reader is not None:
        accepted = inspect.signature(reader.__init__).parameters
        wrong = [k for k in opts if k not in accepted]
        if wrong:
            own = ", ".join(flag for k, flag in FLAGS.items() if k in accepted) or "none"
            kind = KINDS.get(reader.__name__, reader.__name__)
            raise RecordingError(
                f"{FLAGS.get(wrong[0], wrong[0])} does not apply to a {kind} (its options: {own})",
                source=path,
            )
    try:
        return open_recording(path, **opts)
    except OptionError as exc:
        raise option_error(exc) from None
