"""Library errors said with the CLI option a user typed.

The library names its own fields (``simulation.beams``, ``door_width``, ``resolution``); a CLI
user set them through options (``--beams``, ``--door-width``, ``--resolution``). A command wraps
its work in :func:`named_options` with the fields it fills from options; an error about one of
them becomes ``--beams -5: Input should be greater than or equal to 2`` (the file, when the
error named one, in brackets at the end).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

from frslam_graph.errors import FrslamError
from frslam_graph.limits import short_repr


def option_text(flag: str, value: Any) -> str:
    """``--beams -5``, ``--rooms attic,cellar``: the option as typed (a value cut to 80 characters)."""
    if isinstance(value, list | tuple):
        value = ",".join(str(v) for v in value)
    if isinstance(value, float):
        value = f"{value:g}"
    text = str(value)
    return f"{flag} {text if len(text) <= 80 else short_repr(text)}"


def _field(exc: FrslamError) -> str | None:
    """The field an error is about: the last dotted part of its ``where`` (or of its source when
    the source is a field path, not a file)."""
    for name in (exc.where, exc.source):
        if name and "/" not in name and "\\" not in name:
            return name.rsplit(".", 1)[-1].split("[", 1)[0]
    return None


@contextmanager
def named_options(flags: Mapping[str, tuple[str, Any]]) -> Iterator[None]:
    """Re-raise a :class:`FrslamError` about a field in ``flags`` (field -> (option, value given))
    naming the option and its value instead of the field."""
    try:
        yield
    except FrslamError as exc:
        field = _field(exc)
        if field not in flags:
            raise
        flag, value = flags[field]
        file = exc.source if exc.where else None  # with a field in ``where`` the source is the file
        message = exc.message if file is None else f"{exc.message} ({file})"
        raise FrslamError(message, source=option_text(flag, value)) from None
