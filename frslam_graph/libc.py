"""Functions of the process's C library through ctypes (glibc's allocator and ``madvise``), for
the few places that tune memory; None where the platform or the library has none."""

from __future__ import annotations

import ctypes
import sys
from typing import Any


def libc_function(name: str, argtypes: list[Any], restype: Any) -> Any | None:
    """The C library's function ``name`` with its ctypes signature set, or None off Linux or when
    the library does not define it (another C library than glibc)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = getattr(ctypes.CDLL(None), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = argtypes, restype
    return fn
