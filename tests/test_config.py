"""The configuration: defaults unchanged, every field described, a readable dump, typo hints."""

from __future__ import annotations

import json
from pathlib import Path

from frslam_graph.config import FRSlamConfig

DATA = Path(__file__).parent / "data"


def test_defaults_are_those_recorded_before_the_descriptions():
    """tests/data/config_defaults.json is FRSlamConfig().model_dump() of the code before the
    fields got their descriptions (commit eb968a9): describing a field must not change it."""
    recorded = json.loads((DATA / "config_defaults.json").read_text())
    assert FRSlamConfig().model_dump() == recorded


def test_every_field_has_a_description():
    missing = [name for name, _field in _all_fields() if not _field.description]
    assert not missing, f"fields without a description: {missing}"


def _all_fields():
    for section, field in FRSlamConfig.model_fields.items():
        yield section, field
        for name, inner in field.annotation.model_fields.items():
            yield f"{section}.{name}", inner
