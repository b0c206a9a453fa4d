"""Bounded reading of text logs: decompression bombs and endless lines end fast with a clear error."""

from __future__ import annotations

import bz2
import gzip
import resource
from pathlib import Path

import pytest
from frslam_graph.datasets import open_recording

from frslam_graph import limits
from frslam_graph.cli import main
from frslam_graph.errors import RecordingError

GIB = 1 << 30


def _rss_kib() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def _bomb(path, unit: bytes, total: int) -> None:
    """``total`` bytes of ``unit`` repeated, compressed by the file name's suffix, written in pieces."""
    piece = unit * ((1 << 20) // len(unit))
    opener = gzip.open if path.name.endswith(".gz") else bz2.open
    with opener(path, "wb") as f:
        for _ in range(total // len(piece)):
            f.write(piece)


@pytest.mark.parametrize("name", ["bomb.clf.bz2", "bomb.clf.gz"])
@pytest.mark.parametrize("unit", [b"\n", b"A"], ids=["newlines", "one-line"])
def test_a_decompression_bomb_ends_with_an_error_naming_the_file(tmp_path, name, unit):
    path = tmp_path / name
    _bomb(path, unit, 8 << 20)  # 8 MiB: over every limit, quick to write
    before = _rss_kib()
    with pytest.raises(RecordingError) as err:
        open_recording(path)
    message = str(err.value)
    assert name in message and "line" in message
    assert "MAX_EXPANSION" in message or "MAX_LINE_BYTES" in message
    assert (_rss_kib() - before) * 1024 < GIB // 4


def test_a_long_line_in_a_plain_log_is_refused(tmp_path):
    path = tmp_path / "long.clf"
    path.write_bytes(b"FLASER " + b"1 " * limits.MAX_LINE_BYTES + b"\n")
    with pytest.raises(RecordingError, match=r"long\.clf: line 1: line longer than 1,048,576 bytes"):
        open_recording(path)


def test_too_many_lines_are_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(limits, "MAX_LINES", 1000)
    path = tmp_path / "many.clf"
    path.write_bytes(b"# comment\n" * 1001)
    with pytest.raises(RecordingError, match=r"many\.clf: line 1001: more than 1,000 lines"):
        open_recording(path)


def test_inspect_of_a_bomb_exits_2_with_one_line(tmp_path, capsys):
    path = tmp_path / "bomb.clf.bz2"
    _bomb(path, b"\n", 8 << 20)
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "bomb.clf.bz2" in err and "decompression bomb" in err
    assert "Traceback" not in err and len(err.splitlines()) == 1


@pytest.mark.filterwarnings("ignore::frslam_graph.datasets.RecordingWarning")
def test_a_real_compressed_log_is_within_the_limits():
    rec = open_recording(Path(__file__).parent / "data" / "intel_head.clf.bz2")
    assert len(rec) > 0 and len(list(rec)) == len(rec)
