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


# ---------------------------------------------------------------- small text inputs (JSON / YAML)
@pytest.mark.parametrize("name", ["log.clf.gz", "log.clf.bz2"])
def test_compressed_logs_are_read_ahead_in_a_thread_with_the_same_bytes(tmp_path, name, monkeypatch):
    """open_binary decompresses in a thread (ReadAhead), in pieces: the same lines as the plain
    stream, and closing the file part-way stops the thread."""
    import threading

    monkeypatch.setattr(limits, "READ_AHEAD_BYTES", 1000)  # many pieces, lines across them
    text = b"".join(b"FLASER %d %s\n" % (i, b"1.5 " * (i % 97)) for i in range(3000))
    opener = gzip.open if name.endswith(".gz") else bz2.open
    with opener(tmp_path / name, "wb") as f:
        f.write(text)
    with limits.open_binary(tmp_path / name) as f:
        lines = list(limits.bounded_lines(f, tmp_path / name, RecordingError))
    assert b"".join(lines) == text and len(lines) == 3000
    f = limits.open_binary(tmp_path / name)
    assert isinstance(f.raw, limits.ReadAhead)
    assert f.readline() == b"FLASER 0 \n"
    f.close()
    assert not any(t.name == "frslam-read-ahead" for t in threading.enumerate())


def test_json_with_a_key_given_twice_is_refused(tmp_path):
    """The last value silently won ({"rooms": [], "rooms": [...]} read the second)."""
    from frslam_graph.errors import FloorPlanError
    from frslam_graph.floorplan import FloorPlan

    path = tmp_path / "dup.json"
    room = '{"id": "a", "polygon": [[0, 0], [4, 0], [4, 3], [0, 3]]}'
    path.write_text(f'{{"rooms": [], "rooms": [{room}]}}')
    with pytest.raises(FloorPlanError, match=r"dup\.json: malformed JSON: duplicate key 'rooms'"):
        FloorPlan.load(path)


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_nesting_too_deep_is_an_error_not_a_recursion_traceback(tmp_path, suffix):
    from frslam_graph.config import FRSlamConfig
    from frslam_graph.errors import ConfigError, MapError
    from frslam_graph.occupancy import OccupancyGrid

    deep = "[" * 100_000 + "]" * 100_000
    cfg = tmp_path / f"c{suffix}"
    cfg.write_text(f'{{"odometry": {deep}}}' if suffix == ".json" else f"odometry: {deep}\n")
    with pytest.raises(ConfigError, match="nested too deeply"):
        FRSlamConfig.load(cfg)
    if suffix == ".yaml":
        m = tmp_path / "m.yaml"
        m.write_text(f"origin: {deep}\n")
        with pytest.raises(MapError, match=r"m\.yaml: malformed YAML: nested too deeply"):
            OccupancyGrid.load(m)


def test_a_device_or_binary_file_as_a_config_or_plan(tmp_path, capsys):
    """/dev/zero read forever (0 bytes by stat, endless by read); a binary config was a
    UnicodeDecodeError traceback."""
    zero = tmp_path / "z.yaml"
    zero.symlink_to("/dev/zero")
    binary = tmp_path / "b.yaml"
    binary.write_bytes(bytes(range(128, 256)) * 20)
    plan = tmp_path / "z.json"
    plan.symlink_to("/dev/zero")
    for argv, name, what in [
        (["config", "dump", "--out", str(tmp_path / "x.yaml")], None, None),
        (["plan", "show", str(plan), "--out", str(tmp_path / "p.png")], "z.json", "not a regular file"),
    ]:
        code = main(argv)
        err = capsys.readouterr().err
        if name is not None:
            assert code == 2 and name in err and what in err and len(err.strip().splitlines()) == 1, err
    from frslam_graph.config import FRSlamConfig
    from frslam_graph.errors import ConfigError

    with pytest.raises(ConfigError, match="not a regular file"):
        FRSlamConfig.load(zero)
    with pytest.raises(ConfigError, match=r"b\.yaml: cannot read as UTF-8 text"):
        FRSlamConfig.load(binary)
