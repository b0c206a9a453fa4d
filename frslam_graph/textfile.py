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


def read_text(path: str | Path, error: type[FrslamError], expected: str) -> str:
    """The file's text; ``error`` when it is missing, a folder, not UTF-8 text, or empty."""
    path = Path(path)
    if not path.exists():
        raise error(f"file not found (expected {expected})", source=path)
    if path.is_dir():
        raise error(f"expected {expected}, got a directory", source=path)
    check_file_size(path, limits.MAX_PLAN_BYTES, error, "file")
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
    """Parsed YAML of the file (safe loader, no aliases, no duplicate keys); malformed YAML names
    the line."""
    text = read_text(path, error, expected)
    try:
        return load_yaml(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else None
        raise error(f"malformed YAML ({yaml_problem(exc)})", source=path, where=where) from None


def yaml_problem(exc: yaml.YAMLError) -> str:
    """What PyYAML found wrong, on one line, without the quoted context (cut to 200 characters)."""
    problem = " ".join((getattr(exc, "problem", None) or str(exc)).split())
    return problem if len(problem) <= 200 else problem[:197] + "..."
