"""The README reads: no paragraph over 120 words, every file it links exists, and the names its
library snippets call exist in the package (a rename that forgets the README fails here)."""

from __future__ import annotations

import re
from pathlib import Path

import frslam_graph as fr
from frslam_graph.slam import FRSlam

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text(encoding="utf-8")


def paragraphs(text: str) -> list[str]:
    """Prose paragraphs and list items (code blocks and tables left out)."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    out = []
    for block in re.split(r"\n\s*\n", text):
        if block.lstrip().startswith(("|", "#")):
            continue
        out += [item for item in re.split(r"\n(?=\s*(?:\d+\.|-) )", block) if item.strip()]
    return out


def test_paragraphs_are_short():
    long = [(len(p.split()), p[:60]) for p in paragraphs(README) if len(p.split()) > 120]
    assert not long, long


def test_paragraph_splitter_sees_a_long_paragraph():
    assert [len(p.split()) for p in paragraphs("a " * 130 + "\n\n| t | " + "b " * 200)] == [130]


def test_linked_files_exist():
    links = re.findall(r"\]\(([^)#:]+)\)", README)
    assert links, "the README links docs/design.md"
    assert all((REPO / link).exists() for link in links), links


def test_library_names_exist():
    for name in re.findall(r"\bfr\.([A-Za-z_]+)", README):
        assert hasattr(fr, name), f"fr.{name}"
    for name in re.findall(r"\bslam\.([A-Za-z_]+)\(", README):
        assert hasattr(FRSlam, name), f"slam.{name}"
