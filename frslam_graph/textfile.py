"""Reading small text inputs (JSON plans, map_server YAML) with errors that name file and line.

One place for the checks every loader needs: the file exists and is a file, decodes as UTF-8,
is not empty, and parses; each failure raises the caller's :class:`FrslamError` subclass with
the file, the line (where the parser gives one) and what was expected.
"""

from __future__ import annotations

import json
import stat
from pathlib import Path
from typing import Any

import yaml

from frslam_graph import limits
from frslam_graph.errors import FrslamError
from frslam_graph.limits import check_file_size, short_repr


class StrictYamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses aliases (``*name``: a few lines of them expand to
    gigabytes, the "billion laughs") and a key given twice in one mapping."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, "aliases (*name) are not accepted; write the value out", event.start_mark
            )
        return super().compose_node(parent, index)

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: set[Any] = set()
            for key_node, _ in node.value:
                if isinstance(key_node, yaml.ScalarNode):
                    key = self.construct_object(key_node)
                    if key in seen:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {short_repr(key)}", key_node.start_mark
                        )
                    seen.add(key)
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str) -> Any:
    """``yaml.safe_load`` without aliases or duplicate keys (:class:`StrictYamlLoader`);
    raises ``yaml.YAMLError``."""
    return yaml.load(text, Loader=StrictYamlLoader)  # noqa: S506 - a SafeLoader subclass


def read_text(path: str | Path, error: type[FrslamError], expected: str, allow_empty: bool = False) -> str:
    """The file's text; ``error`` when it is missing, a folder, not a regular file, over
    ``MAX_PLAN_BYTES``, not UTF-8 text, or (unless ``allow_empty``) empty."""
    path = Path(path)
    if not path.exists():
        raise error(f"file not found (expected {expected})", source=path)
    if path.is_dir():
        raise error(f"expected {expected}, got a directory", source=path)
    check_file_size(path, limits.MAX_PLAN_BYTES, error, "file")
    try:
        if not stat.S_ISREG(path.stat().st_mode):  # /dev/zero, a FIFO: endless or blocking
            raise error(f"not a regular file (expected {expected})", source=path)
        with open(path, "rb") as f:  # bounded: the size checked above may not be the size read
            data = f.read(limits.MAX_PLAN_BYTES + 1)
        if len(data) > limits.MAX_PLAN_BYTES:
            raise error(
                f"file over the limit of {limits.MAX_PLAN_BYTES:,} bytes (frslam_graph.limits)", source=path
            )
        text = data.decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read as UTF-8 text ({short_repr(str(exc), 120)[1:-1]})", source=path) from None
    if not text.strip() and not allow_empty:
        raise error(f"file is empty (expected {expected})", source=path)
    return text


class DuplicateKeyError(ValueError):
    """A JSON object gives one key twice (raised while parsing)."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise DuplicateKeyError(f"duplicate key {short_repr(key)}")
        out[key] = value
    return out


def load_json(text: str) -> Any:
    """``json.loads`` refusing a key given twice in one object (``DuplicateKeyError``; the last
    value silently won before) and nesting deeper than Python's recursion limit
    (``RecursionError``)."""
    return json.loads(text, object_pairs_hook=_unique_keys)


def read_json(path: str | Path, error: type[FrslamError], expected: str) -> Any:
    """Parsed JSON of the file; malformed JSON names the line and column; a duplicate key or
    nesting too deep to parse is an error too."""
    text = read_text(path, error, expected)
    try:
        return load_json(text)
    except json.JSONDecodeError as exc:
        raise error(
            f"malformed JSON: {exc.msg}", source=path, where=f"line {exc.lineno} column {exc.colno}"
        ) from None
    except DuplicateKeyError as exc:
        raise error(f"malformed JSON: {exc} (each key once)", source=path) from None
    except RecursionError:
        raise error(f"malformed JSON: nested too deeply (expected {expected})", source=path) from None


def read_yaml(path: str | Path, error: type[FrslamError], expected: str) -> Any:
    """Parsed YAML of the file (safe loader, no aliases, no duplicate keys); malformed YAML names
    the line."""
    text = read_text(path, error, expected)
    try:
        return load_yaml(text)
    except RecursionError:
        raise error(f"malformed YAML: nested too deeply (expected {expected})", source=path) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else None
        raise error(f"malformed YAML ({yaml_problem(exc)})", source=path, where=where) from None


def yaml_problem(exc: yaml.YAMLError) -> str:
    """What PyYAML found wrong, on one line, without the quoted context (cut to 200 characters)."""
    problem = " ".join((getattr(exc, "problem", None) or str(exc)).split())
    return problem if len(problem) <= 200 else problem[:197] + "..."
