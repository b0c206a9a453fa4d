"""Reading small text inputs (JSON plans, map_server YAML) with errors that name file and line.

One place for the checks every loader needs: the file exists and is a file, decodes as UTF-8,
is not empty, and parses; each failure raises the caller's :class:`FrslamError` subclass with
the file, the line (where the parser gives one) and what was expected.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml

from frslam_graph.errors import FrslamError


def read_text(path: str | Path, error: type[FrslamError], expected: str) -> str:
    """The file's text; ``error`` when it is missing, a folder, not UTF-8 text, or empty."""
    path = Path(path)
    if not path.exists():
        raise error(f"file not found (expected {expected})", source=path)
    if path.is_dir():
        raise error(f"expected {expected}, got a directory", source=path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read as UTF-8 text ({exc})", source=path) from None
    if not text.strip():
        raise error(f"file is empty (expected {expected})", source=path)
    return text


def read_json(path: str | Path, error: type[FrslamError], expected: str) -> Any:
    """Parsed JSON of the file; malformed JSON names the line and column."""
    text = read_text(path, error, expected)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(
            f"malformed JSON: {exc.msg}", source=path, where=f"line {exc.lineno} column {exc.colno}"
        ) from None


def read_yaml(path: str | Path, error: type[FrslamError], expected: str) -> Any:
    """Parsed YAML of the file (safe loader); malformed YAML names the line."""
    text = read_text(path, error, expected)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else None
        raise error(
            f"malformed YAML ({getattr(exc, 'problem', None) or exc})", source=path, where=where
        ) from None
