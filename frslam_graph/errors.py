"""Exceptions raised by frslam for bad input.

Every error names *where* (file, line or field) and *what was expected*, so a user can fix
the input without reading a traceback from inside numpy, OpenCV or GTSAM. All derive from
:class:`FrslamError`; the CLI turns them into a one-line message and exit code 2.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path


class FrslamError(Exception):
    """Base class of all frslam input errors.

    ``FrslamError(message, source=path, where="rooms[3].polygon")`` renders as
    ``"plan.json: rooms[3].polygon: message"``.
    """

    def __init__(self, message: str, source: str | Path | None = None, where: str | None = None):
        self.message = message
        self.source = str(source) if source is not None else None
        self.where = where
        parts = [p for p in (self.source, where) if p]
        super().__init__(": ".join([*parts, message]))

    def __reduce__(self):  # keep message / source / where across processes (pickle)
        return (type(self), (self.message, self.source, self.where))


class FloorPlanError(FrslamError, ValueError):
    """A floor plan file or object is malformed (JSON, R2V, room segmentation, HouseExpo)."""


class MapError(FrslamError, ValueError):
    """An occupancy map (map_server YAML + image) is malformed or unreadable."""


class RecordingError(FrslamError, ValueError):
    """A recording (CARMEN log, ROS bag, point-cloud folder, simulator output) is unreadable."""


class OptionError(RecordingError):
    """A reader option does not fit the recording (a topic it lacks, a laser it has no records
    of), or one it needs was not given (several scan topics).

    ``option`` names the reader's argument (``scan_topic``), ``value`` what was given (None: not
    given), ``choices`` the values this file offers and ``problem`` what is wrong without the
    option's name, so the CLI can say it with its own option (``--scan-topic``).
    """

    def __init__(
        self,
        message: str,
        source: str | Path | None = None,
        *,
        option: str,
        value: str | None = None,
        choices: tuple[str, ...] | list[str] = (),
        problem: str | None = None,
    ):
        super().__init__(message, source)
        self.option = option
        self.value = value
        self.choices = tuple(choices)
        self.problem = problem or message

    def __reduce__(self):
        fields = dict(option=self.option, value=self.value, choices=self.choices, problem=self.problem)
        return (partial(type(self), **fields), (self.message, self.source))


class ConfigError(FrslamError, ValueError):
    """A configuration value is out of range or of the wrong type."""


class TrajectoryError(FrslamError, ValueError):
    """A trajectory / ground-truth / relations file is malformed."""


class OutputError(FrslamError):
    """An output cannot be written: its folder is not writable, the path is a folder, the
    extension is not one the writer supports, the disk is full."""


class Interrupted(BaseException):
    """SIGINT / SIGTERM arrived (raised by the CLI's signal handler, like KeyboardInterrupt).

    ``outputs`` lists the outputs complete when it arrived (set on its way out of a command)."""

    def __init__(self, signum: int):
        self.signum = signum
        self.outputs: list[str] = []
        super().__init__(signum)
