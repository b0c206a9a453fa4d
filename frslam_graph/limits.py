"""Resource limits on inputs, checked before the memory or time is spent.

A few hundred bytes can ask for gigabytes: a compressed log that expands a thousandfold, a YAML
alias bomb, a point-cloud header that claims a billion points, a grid at a tiny resolution. Each
reader checks its input against one of these documented limits and raises its
:class:`~frslam_graph.errors.FrslamError` subclass naming the file (and field) when it is over.

Limits (all far above the largest real input seen: the Intel / FR079 / ACES CARMEN logs are
8-16 MB of text in 14,000-41,000 lines of at most 2 kB, compressed 6-9 times by bz2):

- ``MAX_LINE_BYTES`` (1 MiB): one line of a text log.
- ``MAX_LINES`` (20 million): lines of a text log.
- ``MAX_EXPANSION`` (100) and ``EXPANSION_ALLOWANCE`` (1 MiB): a ``.gz`` / ``.bz2`` stream may
  decompress to at most ``EXPANSION_ALLOWANCE + MAX_EXPANSION * compressed size`` bytes.
- ``MAX_CLOUD_POINTS`` (20 million): points of one ``.pcd`` / ``.ply`` cloud.
- ``MAX_PLAN_BYTES`` (50 MB): a JSON / YAML floor plan, map YAML or config file.
- ``MAX_PLAN_WALLS`` (2,000): walls and doors (R2V lines) of one floor plan (the 1,024 R2V
  plans have at most 75 walls; 2,000 random crossing walls take ~8 s and 260 MB to build rooms
  from, 20,000 over 2 minutes and 1.6 GB).
- ``MAX_PLAN_ROOMS`` (1,000): rooms of one floor plan, any reader (a building has tens to hundreds;
  ``plan show`` draws 1,000 in about 15 s, 5,000 in 70 s).
- ``MAX_GRID_CELLS`` (100 million, 0.8 GB of hit / miss counts): an occupancy grid.
- ``MAX_REPR_CHARS`` (80): a value quoted in an error message.
"""

from __future__ import annotations

import bz2
import gzip
import io
import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from frslam_graph.errors import FrslamError

MAX_LINE_BYTES = 1 << 20
MAX_LINES = 20_000_000
MAX_EXPANSION = 100
EXPANSION_ALLOWANCE = 1 << 20
MAX_CLOUD_POINTS = 20_000_000
MAX_PLAN_BYTES = 50_000_000
MAX_PLAN_WALLS = 2_000
MAX_PLAN_ROOMS = 1_000
MAX_GRID_CELLS = 100_000_000
MAX_REPR_CHARS = 80


def short_repr(value: Any, limit: int = MAX_REPR_CHARS) -> str:
    """``repr(value)`` cut to ``limit`` characters (``...`` marks the cut).

    Containers are summarised before their repr is built, so a huge value costs no memory."""
    if isinstance(value, list | tuple | dict | set) and len(value) > limit:
        return f"<{type(value).__name__} of {len(value)} items>"
    if isinstance(value, str | bytes) and len(value) > 4 * limit:
        value = value[: 4 * limit]
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def check_file_size(path: Path, limit: int, error: type[FrslamError], what: str) -> None:
    """``error`` naming the file when it is larger than ``limit`` bytes."""
    try:
        size = path.stat().st_size
    except OSError:
        return  # the reader reports a missing / unreadable file itself
    if size > limit:
        raise error(
            f"{what} of {size:,} bytes is over the limit of {limit:,} bytes (frslam_graph.limits)",
            source=path,
        )


def open_binary(path: Path) -> IO[bytes]:
    """The file's bytes, decompressed when its name ends in ``.gz`` / ``.bz2`` (ahead of the
    reader, in a thread: :class:`ReadAhead`)."""
    name = path.name.lower()
    if name.endswith(".gz"):
        return io.BufferedReader(ReadAhead(gzip.open(path, "rb")))
    if name.endswith(".bz2"):
        return io.BufferedReader(ReadAhead(bz2.open(path, "rb")))
    return open(path, "rb")  # noqa: SIM115


#: bytes a :class:`ReadAhead` thread decompresses per piece, and pieces it keeps ready at most
READ_AHEAD_BYTES = 1 << 18
READ_AHEAD_PIECES = 4


class ReadAhead(io.RawIOBase):
    """A binary stream read in pieces by a thread, ahead of its reader: the bz2 / zlib
    decompressors release the GIL, so a log is decompressed on another core while the caller
    parses it (and, in an offline run, while the backend works on the scans: FR079's 2 s of bz2
    were the backend's, the busier of the run's two processes). The same bytes in the same
    order; an error of the stream (a truncated ``.bz2``) is raised where the bytes before it
    end. At most ``READ_AHEAD_PIECES`` pieces of ``READ_AHEAD_BYTES`` wait; closing stops the
    thread and closes the stream."""

    def __init__(self, stream: IO[bytes]) -> None:
        super().__init__()
        self._stream = stream
        self._pieces: queue.Queue[bytes | BaseException | None] = queue.Queue(READ_AHEAD_PIECES)
        self._piece = memoryview(b"")
        self._ended = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._fill, name="frslam-read-ahead", daemon=True)
        self._thread.start()

    def _fill(self) -> None:
        try:
            while not self._stop.is_set():
                # read1: whatever one decompression step gives, so every byte that decodes
                # before a damaged part reaches the reader (read(n) would drop its last piece)
                data = self._stream.read1(READ_AHEAD_BYTES)
                if not data:
                    break
                self._put(data)
            else:
                return
        except BaseException as exc:  # noqa: BLE001 - handed to the reader, raised there
            self._put(exc)
            return
        self._put(None)

    def _put(self, item: bytes | BaseException | None) -> None:
        while not self._stop.is_set():
            try:
                self._pieces.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        while not len(self._piece):
            if self._ended:
                return 0
            item = self._pieces.get()
            if item is None:
                self._ended = True
                return 0
            if isinstance(item, BaseException):
                self._ended = True
                raise item
            self._piece = memoryview(item)
        n = min(len(buffer), len(self._piece))
        buffer[:n] = self._piece[:n]
        self._piece = self._piece[n:]
        return n

    def close(self) -> None:
        if not self.closed:
            self._stop.set()
            self._thread.join()
            self._stream.close()
        super().close()


def bounded_lines(
    f: IO[bytes],
    path: Path,
    error: type[FrslamError],
    *,
    compressed_size: int | None = None,
    max_line_bytes: int | None = None,
    max_lines: int | None = None,
) -> Iterator[bytes]:
    """Lines of a binary stream, read in bounded pieces.

    ``error`` (naming the file and line) on a line longer than ``max_line_bytes``, more than
    ``max_lines`` lines, or, when ``compressed_size`` is given, more decompressed bytes than
    ``EXPANSION_ALLOWANCE + MAX_EXPANSION * compressed_size`` (a decompression bomb).
    """
    max_line_bytes = MAX_LINE_BYTES if max_line_bytes is None else max_line_bytes
    max_lines = MAX_LINES if max_lines is None else max_lines
    budget = None if compressed_size is None else EXPANSION_ALLOWANCE + MAX_EXPANSION * compressed_size
    total = 0
    lineno = 0
    while True:
        line = f.readline(max_line_bytes + 1)
        if not line:
            return
        lineno += 1
        if len(line) > max_line_bytes:
            raise error(
                f"line longer than {max_line_bytes:,} bytes (limit MAX_LINE_BYTES, frslam_graph.limits)",
                source=path,
                where=f"line {lineno}",
            )
        if lineno > max_lines:
            raise error(
                f"more than {max_lines:,} lines (limit MAX_LINES, frslam_graph.limits)",
                source=path,
                where=f"line {lineno}",
            )
        total += len(line)
        if budget is not None and total > budget:
            raise error(
                f"decompresses to more than {budget:,} bytes, {MAX_EXPANSION} times its size of "
                f"{compressed_size:,} bytes (a decompression bomb? limit MAX_EXPANSION, frslam_graph.limits)",
                source=path,
                where=f"line {lineno}",
            )
        yield line
