"""What a non-editable install (``pip install .``, a wheel) ships: every package of the source.

``pyproject.toml`` lists the packages by hand (``frslam_graph.factors`` and ``frslam_graph.datasets``
live in top-level folders). An editable install imports any subfolder of ``frslam_graph/`` whether it
is listed or not, so a package missing from the list passes every other test and breaks only a
wheel: ``frslam`` then fails on import (it did: ``backend``, ``localisation``, ``loop_closure``,
``odometry`` and ``plan_updates`` were not listed). Read statically, nothing built.
"""

from __future__ import annotations

import tomllib

from tests.test_imports import REPO, ROOT, package_dirs


def _setuptools() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]


def source_packages() -> set[str]:
    """Dotted names of every folder holding an ``__init__.py``: ``frslam_graph/`` and the folders
    pyproject maps into it (:func:`tests.test_imports.package_dirs`)."""
    found = set()
    for package, folder in package_dirs().items():
        for init in folder.rglob("__init__.py"):
            rel = init.parent.relative_to(folder).parts
            if not any(p in (".venv", "__pycache__") for p in rel):
                found.add(".".join([package, *rel]))
    return found


def test_every_source_package_is_in_the_wheel():
    listed = set(_setuptools()["packages"])
    missing = sorted(source_packages() - listed)
    assert not missing, (
        f"pyproject.toml [tool.setuptools] packages lacks {missing}: a wheel would not ship them"
    )


def test_every_listed_package_exists():
    assert not sorted(set(_setuptools()["packages"]) - source_packages())


def test_the_bundled_data_is_package_data():
    """``frslam demo`` and the examples read ``frslam_graph/data``: its files must match a
    package-data pattern of ``frslam_graph`` (a pattern ``data/*`` alone misses subfolders)."""
    patterns = _setuptools()["package-data"][ROOT]
    data = REPO / ROOT / "data"
    files = {p for p in data.rglob("*") if p.is_file() and "__pycache__" not in p.parts}
    shipped = {p for pattern in patterns for p in (REPO / ROOT).glob(pattern) if p.is_file()}
    assert files
    assert not sorted(str(f.relative_to(REPO)) for f in files - shipped)
