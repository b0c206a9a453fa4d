"""Reading raster images (plans, maps, segmentations) safely: size from the header, then decode.

A PNG, JPEG or PNM (PGM/PPM/PBM) header states the image size; it is read *before* decoding, so
a huge image (more than :data:`MAX_SIDE` pixels on a side or :data:`MAX_PIXELS` pixels in all)
is refused with one line instead of exhausting memory. Other formats are refused too: their
size cannot be checked first. Errors are raised as the caller's :class:`FrslamError` subclass,
naming the file. The decoder's own messages (libpng's ``libpng error: ...`` on a damaged PNG)
are kept off standard error while it runs: the caller's error says it, once.
"""

from __future__ import annotations

import os
import stat
import struct
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from frslam_graph.errors import FrslamError

MAX_SIDE = 20_000  # pixels on either side
MAX_PIXELS = 100_000_000  # width × height
FORMATS = "PNG, JPEG or PGM/PPM"

_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def image_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) in pixels from a PNG, JPEG or PNM header; None for another or a broken
    header. Reads only the header (a few bytes; a JPEG's segments up to its frame header)."""
    with open(path, "rb") as f:
        head = f.read(32)
        if head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR":
            w, h = struct.unpack(">II", head[16:24])
            return int(w), int(h)
        if head.startswith(b"\xff\xd8"):
            return _jpeg_size(f)
        if len(head) > 2 and head[0:1] == b"P" and head[1:2] in b"123456":
            f.seek(0)
            return _pnm_size(f.read(1024))
    return None


def _jpeg_size(f) -> tuple[int, int] | None:
    f.seek(2)
    while True:
        marker = f.read(2)
        if len(marker) < 2 or marker[0] != 0xFF:
            return None
        kind = marker[1]
        if kind in (0xD8, 0x01) or 0xD0 <= kind <= 0xD7:  # markers without a length
            continue
        raw = f.read(2)
        if len(raw) < 2:
            return None
        length = struct.unpack(">H", raw)[0]
        if kind in _JPEG_SOF:
            body = f.read(5)
            if len(body) < 5:
                return None
            h, w = struct.unpack(">HH", body[1:5])
            return int(w), int(h)
        if length < 2:
            return None
        f.seek(length - 2, 1)


def _pnm_size(head: bytes) -> tuple[int, int] | None:
    tokens: list[bytes] = []
    for line in head.split(b"\n"):
        tokens += line.split(b"#", 1)[0].split()
        if len(tokens) >= 3:
            break
    try:
        return int(tokens[1]), int(tokens[2])
    except (IndexError, ValueError):
        return None


def read_image(path: str | Path, error: type[FrslamError], expected: str) -> np.ndarray:
    """Decode an image file as stored (grey, colour BGR(A), 8 or 16 bit) after checking it
    exists, is not empty, is PNG / JPEG / PNM and is at most MAX_SIDE × MAX_SIDE and
    MAX_PIXELS pixels. Raises ``error`` naming the file; ``expected`` says what it should be."""
    path = Path(path)
    src = str(path)
    if not path.exists():
        raise error(f"file not found (expected {expected})", source=src)
    if path.is_dir():
        raise error(f"expected {expected}, got a directory", source=src)
    st = path.stat()
    if not stat.S_ISREG(st.st_mode):  # /dev/zero, a FIFO: no header to trust, maybe no end
        raise error(f"not a regular file (expected {expected})", source=src)
    if st.st_size == 0:
        raise error(f"empty file (expected {expected})", source=src)
    size = image_size(path)
    if size is None:
        raise error(f"not a readable image (expected {expected} as {FORMATS})", source=src)
    w, h = size
    if w <= 0 or h <= 0 or w > MAX_SIDE or h > MAX_SIDE or w * h > MAX_PIXELS:
        raise error(
            f"image is {w}x{h} px; the limit is {MAX_SIDE} px a side and {MAX_PIXELS // 1_000_000} Mpx",
            source=src,
        )
    with _stderr_silenced():
        img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise error(f"not a readable image (expected {expected}; the file is damaged)", source=src)
    return img


@contextmanager
def _stderr_silenced() -> Iterator[None]:
    """File descriptor 2 points at /dev/null while the block runs (C libraries that print, such
    as libpng, bypass Python's ``sys.stderr``); nothing changes when there is no fd 2."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def grey_levels(img: np.ndarray) -> np.ndarray:
    """Float grey levels 0..255 as ROS map_server reads an image: colour channels averaged,
    alpha ignored, 16-bit scaled to 8-bit."""
    if img.ndim == 3:
        img = img[:, :, :3].mean(axis=2) if img.shape[2] >= 3 else img[:, :, 0]
    if img.dtype == np.uint16:
        img = img / 257.0
    return np.asarray(img, dtype=np.float64)
