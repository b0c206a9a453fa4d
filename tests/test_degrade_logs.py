"""``tools/degrade_logs.py``'s variants on a small excerpt (``tests/data/aces_stand.clf.bz2``,
150 ACES scans): the seeded range-noise variants are other draws of the same 3 cm noise."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import load_tool
from frslam_graph.datasets import RecordingWarning, open_recording


@pytest.fixture(scope="module")
def scans(test_data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)
        return list(open_recording(test_data / "aces_stand.clf.bz2"))


def _ranges(variant: str, scans) -> np.ndarray:
    """The variant's ranges (m), the scans stacked (N, beams)."""
    transform, drops = load_tool("degrade_logs").VARIANTS[variant]
    assert not drops
    return np.stack([s.ranges for s in transform(scans)])


def test_noise3cm_seeds_are_other_draws_of_the_same_noise(scans):
    """``noise3cm`` is seed 0; ``noise3cm_s1`` / ``_s2`` are seeds 1 and 2: reproducible, each
    unlike the others, with the same 3 cm sigma on the valid beams (no-return beams untouched)."""
    raw = np.stack([s.ranges for s in scans])
    s0, s1, s2 = (_ranges(v, scans) for v in ("noise3cm", "noise3cm_s1", "noise3cm_s2"))
    np.testing.assert_array_equal(s1, _ranges("noise3cm_s1", scans))
    ok = np.isfinite(raw) & (raw > 0.0) & (raw < scans[0].max_range)
    assert ok.sum() > 10_000
    for a, b in ((s0, s1), (s0, s2), (s1, s2)):
        assert np.mean(a[ok] != b[ok]) > 0.99
    for s in (s0, s1, s2):
        np.testing.assert_array_equal(s[~ok], raw[~ok])
        assert abs(np.std(s[ok] - raw[ok]) - 0.03) < 0.002
