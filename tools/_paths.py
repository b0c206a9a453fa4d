"""Where the tools find the repository and the shared data: ``$FRSLAM_SHARED_DATA`` when set,
else ``../shared/data`` beside the repository (as the tests do, ``tests/conftest.py``)."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("FRSLAM_SHARED_DATA", REPO.parent / "shared" / "data"))
#: the shared real logs: name -> (recording, Kümmerle et al. relations), under SHARED_DATA
LOGS = {
    "aces": ("carmen/aces.clf.bz2", "carmen/aces.relations"),
    "intel": ("carmen/intel.clf.bz2", "carmen/intel.relations"),
    "fr079": ("carmen/fr079.clf.bz2", "carmen/fr079.relations"),
    "intel.bag": ("bags/intel.bag", "carmen/intel.relations"),
}
