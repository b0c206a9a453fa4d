"""tools/bench_slam.py: the same figures with Dask workers as sequentially; the tables' format."""

from __future__ import annotations

import bz2
import json
import math
import sys

import numpy as np
import pytest
from conftest import load_tool


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_slam")


def excerpts(test_data, tmp_path):
    """Two small logs: the Intel head excerpt and its first 30 laser lines (with their ODOM lines)."""
    head = test_data / "intel_head.clf.bz2"
    lines, lasers = [], 0
    for line in bz2.open(head, "rt", encoding="latin-1"):
        lines.append(line)
        lasers += line.startswith("FLASER")
        if lasers == 30:
            break
    short = tmp_path / "intel_short.clf"
    short.write_text("".join(lines), encoding="latin-1")
    return {"head": (head, None), "short": (short, None)}


TIMING = {
    "wall_s",
    "xrt",
    "latency_ms",
    "latency_cpu_ms",
    "peak_rss_mb",
    "peak_rss_backend_mb",
    "peak_rss_worker_mb",
    "peak_forked_private_mb",
    "peak_tree_mb",
}


def test_workers_give_the_sequential_results(bench, test_data, tmp_path):
    logs = excerpts(test_data, tmp_path)
    runs = {}
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        done = bench.run_tasks(bench.make_tasks(logs, out, baseline=True), workers)
        runs[workers] = (out, bench.collect(done))
    (out1, res1), (out2, res2) = runs[1], runs[2]
    assert set(res1) == set(res2) == {"head", "short"}
    for name in ("head", "short"):
        for kind in ("frslam", "kiss"):
            a, b = res1[name][kind], res2[name][kind]
            assert "error" not in a and "error" not in b, (a, b)
            assert {k: v for k, v in a.items() if k not in TIMING} == {
                k: v for k, v in b.items() if k not in TIMING
            }
        assert res1[name]["frslam"]["scans"] == {"head": 64, "short": 30}[name]
        assert res1[name]["frslam"]["peak_rss_mb"] > 50  # the run's process, not the task runner's
        np.testing.assert_array_equal(
            np.loadtxt(out1 / name / "trajectory.tum"), np.loadtxt(out2 / name / "trajectory.tum")
        )
        m1, m2 = (json.loads((o / name / "metrics.json").read_text()) for o in (out1, out2))
        for k in TIMING | {"wall_time_s", "realtime_factor", "odometry_stats"}:
            m1.pop(k, None), m2.pop(k, None)
        for m in (m1, m2):  # the loop closer's wall and CPU seconds are timings too
            for k in ("seconds", "cpu_seconds"):
                m.get("loop_closure", {}).pop(k, None)
        assert m1 == m2


REL = {
    "trans_mean": 0.0341,
    "trans_std": 0.0312,
    "trans_max": 0.4567,
    "rot_mean": 0.591,
    "rot_std": 1.234,
    "rot_max": 12.345,
    "matched": 2984,
    "total": 2984,
}
RUN = {
    "scans": 13631,
    "duration_s": 2691.0,
    "wall_s": 100.0,
    "xrt": 26.91,
    "latency_ms": {"median": 1.234, "p99": 12.34, "max": 456.7},
    "latency_cpu_ms": {"median": 1.1, "p99": 9.87, "max": 123.4},
    "endpoints_on_wall": None,
    "closures": 42,
    "peak_rss_mb": 512.4,
    "relations": REL,
}
BASE = {"wall_s": 25.0, "xrt": 107.6, "relations": {**REL, "trans_mean": 0.5, "trans_std": 0.25}}


def test_table_rows_from_fixed_numbers(bench):
    row = bench.main_row("intel", RUN, BASE)
    assert row == [
        "intel",
        "13631",
        "0.0341 ± 0.0312, 0.457",
        "0.591 ± 1.234, 12.35",
        "2984 / 2984",
        "n/a",
        "26.9",
        "1.23 / 12.3 / 457",
        "1.10 / 9.9 / 123",
        "512",
        "42",
        "0.5000 ± 0.2500",
        "107.6",
        "4.00",
    ]
    assert len(row) == len(bench.MAIN_HEAD)
    with_wall = bench.main_row("intel", {**RUN, "endpoints_on_wall": 0.8766}, None)
    assert with_wall[5] == "87.7 %" and with_wall[-3:] == ["—", "—", "—"]
    sim = {k: v for k, v in RUN.items() if k != "relations"} | {"ate_rmse": 0.01234, "duration_s": 7200.0}
    assert bench.main_row("sim", sim, None)[2:5] == ["ATE RMSE 0.0123 (simulated, 2.00 h)", "—", "—"]
    none = {**REL, "matched": 0, "total": 10, "trans_mean": math.nan}
    assert bench.main_row("x", {**RUN, "relations": none}, None)[2:5] == ["n/a", "n/a", "0 / 10"]
    assert bench.main_row("x", {"error": "exit 1: boom"}, None)[1] == "failed: exit 1: boom"


def test_markdown_tables(bench):
    text = bench.tables({"intel": {"frslam": RUN, "kiss": {**BASE, "wheel_relations": REL}}})
    lines = text.splitlines()
    assert lines[0] == "| " + " | ".join(bench.MAIN_HEAD) + " |"
    assert lines[1] == "|" + "---|" * len(bench.MAIN_HEAD)
    assert lines[2].startswith("| intel | 13631 | 0.0341 ± 0.0312, 0.457 |")
    assert lines[2].count(" | ") == len(bench.MAIN_HEAD) - 1
    ref = [x for x in lines if x.startswith("| intel | 0.0229")]
    assert ref == [
        "| intel | 0.0229 ± 0.0239 m / 0.453 ± 1.335° | 0.031 ± 0.026 m / 1.3 ± 4.7° | 0.0341 ± 0.0312 m / 0.591 ± 1.234° |"
    ]
    assert bench.markdown(["a"], [["x|y"]]).splitlines()[2] == "| x\\|y |"


def test_a_config_file_reaches_every_frslam_run_and_a_bad_one_is_refused(bench, test_data, tmp_path, capsys):
    logs = {"short": excerpts(test_data, tmp_path)["short"]}
    cfg = tmp_path / "dense.yaml"
    cfg.write_text("odometry: {keyframe_max_interval_s: 1.0}\n")  # a keyframe a second, standing still too
    tasks = bench.make_tasks(logs, tmp_path / "out", baseline=True, config=cfg)
    assert [t["config"] for t in tasks] == [str(cfg), None]  # the KISS-ICP baseline has none
    dense = bench.child_frslam(tasks[0])
    default = bench.child_frslam({**tasks[0], "config": None, "out": str(tmp_path / "default")})
    assert dense["scans"] == default["scans"] == 30
    assert dense["keyframes"] > default["keyframes"]
    bad = tmp_path / "bad.yaml"
    bad.write_text("odometry: {keyframe_distanc: 0.02}\n")
    with pytest.raises(SystemExit) as exc:
        bench.main(["--config", str(bad), "--logs", "aces"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--config" in err[0] and "keyframe_distanc" in err[0]


def _hold(ready, go, mb: int) -> None:
    """A forked child: ``mb`` MB of its own, then wait."""
    own = np.ones(mb << 20, np.uint8)
    ready.send(1)
    go.wait()
    del own


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and fork")
def test_memory_sampler_counts_a_forked_childs_own_pages(bench):
    """A forked child's RSS counts the pages it shares with its parent (``RUSAGE_CHILDREN``'s
    peak, the figure bench_slam gave as the odometry worker's, was the final alignment's forked
    half: ~ the backend's size); the sampler gives the odometry worker (the first child seen)
    its peak RSS, the other children the pages they add (private memory)."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    parent = np.ones(64 << 20, np.uint8)  # the backend's pages, shared with its forked children
    go = ctx.Event()
    ends = [ctx.Pipe(duplex=False) for _ in range(2)]
    sampler = bench.MemorySampler()
    kids = []
    try:
        for (receive, send), mb in zip(ends, (0, 32), strict=True):
            kids.append(ctx.Process(target=_hold, args=(send, go, mb), daemon=True))
            kids[-1].start()
            receive.recv()
            sampler.sample()  # the first child is seen first, as the odometry worker is
        worker, forked = (sampler.children[str(k.pid)] for k in kids)
        assert list(sampler.children) == [str(k.pid) for k in kids]
        assert forked["hwm"] >= 64 + 30  # its RSS: the parent's pages and its own
        assert 30 <= forked["private"] < 64  # its own only
        assert sampler.forked_private_mb() == forked["private"]
        assert sampler.worker_mb() == worker["hwm"] >= 64
        # the parent's pages once: not the children's RSS
        assert sampler.tree_mb < bench.process_memory()["rss"] + worker["private"] + forked["private"] + 8
    finally:
        go.set()
        for k in kids:
            k.join(timeout=10)
    del parent


def test_memory_cell_gives_backend_worker_and_forked(bench):
    cell = bench.MAIN_HEAD.index("peak memory backend + worker + forked (MB)")
    run = {**RUN, "peak_rss_backend_mb": 448.2, "peak_rss_worker_mb": 118.6, "peak_forked_private_mb": 95.9}
    assert bench.main_row("intel", run, None)[cell] == "448 + 119 + 96"
    old = {**RUN, "peak_rss_backend_mb": 448.2, "peak_rss_worker_mb": 346.0}  # before session 8
    assert bench.main_row("intel", old, None)[cell] == "448 + 346"
