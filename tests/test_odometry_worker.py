"""Offline runs with the odometry in a worker process: same results, errors in order, no hang."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import time

import numpy as np
import pytest
from frslam_graph.datasets import Scan
from synthetic_world import ROOM_LOOP, drifting_odometry, room_world, route, scans_along

from frslam_graph.config import FRSlamConfig
from frslam_graph.errors import ConfigError, RecordingError
from frslam_graph.odometry import worker as odometry_worker
from frslam_graph.odometry.scan_odometry import PreparedScan, ScanOdometry
from frslam_graph.offline import process
from frslam_graph.slam import FRSlam

CFG = {"odometry": {"max_range": 10.0}}

needs_worker = pytest.mark.skipif(
    not odometry_worker.available(FRSlamConfig.from_dict(CFG).odometry),
    reason="the odometry worker needs Linux fork, two cores and a non-daemonic process",
)


@pytest.fixture(scope="module")
def faulty_recording() -> list[Scan]:
    """One lap of the synthetic room with all-NaN scans, a gap, a wheel jump and a stale stamp."""
    truth = route(ROOM_LOOP)
    ranges, amin, inc = scans_along(room_world(), truth)
    wheel = drifting_odometry(truth)
    angles = amin + inc * np.arange(len(ranges[0]))
    scans = []
    for i in range(len(truth)):
        r = np.full_like(ranges[i], np.nan) if 100 <= i < 105 else ranges[i]
        if 200 <= i < 203:
            continue
        odom = wheel[i] + (np.array([1.5, 0.0, 0.0]) if i >= 300 else 0.0)
        scans.append(Scan(float(truth[i, 0]), r, angles, tuple(odom), 10.0, (0.1, 0.0, 0.0)))
    scans.insert(400, Scan(float(truth[10, 0]), ranges[10], angles, tuple(wheel[10]), 10.0))
    return scans


@needs_worker
@pytest.mark.parametrize("loop_closure", [False, True])
def test_parallel_process_equals_the_sequential_one(faulty_recording, loop_closure):
    cfg = FRSlamConfig.from_dict({**CFG, "loop_closure": {"enabled": loop_closure}})
    seq = process(FRSlam(cfg), faulty_recording, parallel=False)
    par_slam = FRSlam(cfg)
    par = process(par_slam, faulty_recording)  # parallel by default where available
    assert par.parallel and not seq.parallel
    np.testing.assert_array_equal(par.trajectory, seq.trajectory)
    np.testing.assert_array_equal(par.odometry, seq.odometry)
    np.testing.assert_array_equal(par.keyframes, seq.keyframes)
    assert par.stats == seq.stats and par_slam.stats == seq.stats
    assert par.stats.empty_scans == 5 and par.stats.dropped_scans == 3 and par.stats.out_of_order == 1
    assert [(e.kind, e.stamp) for e in par.log if e.kind != "batch_optimised"] == [
        (e.kind, e.stamp) for e in seq.log if e.kind != "batch_optimised"
    ]
    assert len(par.latencies) == len(faulty_recording) and par.duration == seq.duration
    assert np.all(par.latencies > 0.0)  # odometry (worker) + backend time of each scan
    # the map from the keyframe scans (kept in this process) is the same
    seq_slam = FRSlam(cfg)
    process(seq_slam, faulty_recording, parallel=False)
    np.testing.assert_array_equal(par_slam.occupancy_grid(0.1).data, seq_slam.occupancy_grid(0.1).data)


@needs_worker
def test_input_error_in_the_worker_is_raised_in_order(faulty_recording):
    scans = list(faulty_recording[:150])
    bad = scans[120]
    scans[120] = Scan(float("nan"), bad.ranges, bad.angles, bad.odom, bad.max_range)
    for parallel in (False, True):
        slam = FRSlam(CFG)
        with pytest.raises(RecordingError, match="stamp must be a finite number") as err:
            process(slam, scans, parallel=parallel)
        assert err.value.where == "stamp"
        assert len(slam.trajectory()) == 120  # every scan before the bad one went through the backend


@needs_worker
def test_a_worker_that_dies_is_reported_not_waited_for(faulty_recording, monkeypatch):
    real = ScanOdometry.process

    def dies_at_scan_50(self, stamp, points, odom=None):
        if self.stats.scans == 50:
            os._exit(3)  # only ever reached in the forked worker
        return real(self, stamp, points, odom)

    monkeypatch.setattr(ScanOdometry, "process", dies_at_scan_50)
    with pytest.raises(RuntimeError, match="exit code 3"):
        process(FRSlam(CFG), faulty_recording[:200], parallel=True)


def _exited(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/status") as fh:
            return any(line.startswith("State:") and "Z" in line.split()[1] for line in fh)
    except FileNotFoundError:
        return True


@needs_worker
def test_a_worker_whose_caller_was_killed_exits_on_its_own(tmp_path):
    """No orphan left computing or waiting forever when the caller dies without stopping it."""
    script = tmp_path / "caller.py"
    script.write_text(
        "import os, sys\n"
        "from frslam_graph.config import OdometryConfig\n"
        "from frslam_graph.odometry.worker import OdometryWorker\n"
        "w = OdometryWorker(OdometryConfig(), poll_s=0.1)\n"
        "print(w._proc.pid, flush=True)\n"
        "os._exit(0)\n"
    )
    out = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=600
    )  # a guard against a hang only
    pid = int(out.stdout.split()[0])
    # a guard against waiting forever, not a timing assertion: the worker polls every 0.1 s, but a
    # machine loaded 10x over its cores has delayed it by tens of seconds
    deadline = time.monotonic() + 180.0
    while not _exited(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _exited(pid)


@needs_worker
def test_a_worker_left_with_half_a_chunk_exits_when_its_caller_dies(tmp_path):
    """A caller killed while it wrote a chunk leaves part of a message in the inbox pipe; the
    worker (which holds the pipe's write end too) waited for the rest forever: found asleep
    minutes after a killed ``frslam run`` (tools/bad_inputs.py --kill)."""
    script = tmp_path / "caller.py"
    script.write_text(
        "import os, struct, time\n"
        "from frslam_graph.config import OdometryConfig\n"
        "from frslam_graph.odometry.worker import OdometryWorker\n"
        "w = OdometryWorker(OdometryConfig(), poll_s=0.1)\n"
        "os.write(w._inbox._writer.fileno(), struct.pack('!i', 1000) + b'x')  # 1 of 1000 bytes\n"
        "time.sleep(0.5)\n"
        "print(w._proc.pid, flush=True)\n"
        "os._exit(0)\n"
    )
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600)
    pid = int(out.stdout.split()[0])
    deadline = time.monotonic() + 180.0  # a guard against waiting forever, not a timing assertion
    while not _exited(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    exited = _exited(pid)
    if not exited:
        os.kill(pid, 9)
    assert exited


@needs_worker
def test_after_a_parallel_run_no_more_scans_and_no_second_parallel_run(faulty_recording):
    slam = FRSlam(CFG)
    process(slam, faulty_recording[:30], batch=False, parallel=True)
    s = faulty_recording[30]
    with pytest.raises(ConfigError, match="worker process") as err:
        slam.add(s)
    assert err.value.where == "parallel"
    with pytest.raises(ConfigError, match="fresh FRSlam"):
        process(slam, faulty_recording[30:40], parallel=True)
    # sequential processing may continue a streaming instance
    streaming = FRSlam(CFG)
    process(streaming, faulty_recording[:30], batch=False, parallel=False)
    process(streaming, faulty_recording[30:60], parallel=None)  # not fresh: runs in-process
    assert len(streaming.trajectory()) == 60


def test_prepared_scan_is_stateless_and_lazy():
    odo = ScanOdometry(FRSlamConfig.from_dict({"odometry": {"scan_matching": False}}).odometry)
    ang = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    pts = np.column_stack((3 * np.cos(ang), 2 * np.sin(ang)))
    prep = odo.prepare(pts)
    assert isinstance(prep, PreparedScan) and prep.source is None and prep.geometry is None
    full = odo.prepare(pts, icp_inputs=True)
    assert full.source.shape[1] == 3 and full.geometry.n_normals > 10
    # without wheel odometry the scan must still be matched: process computes what it needs
    assert odo.process(0.0, prep) is not None
    res = odo.process(0.1, odo.prepare(pts + [0.05, 0.0]))
    assert res is not None and not res.fallback
    assert abs(res.pose[0] + 0.05) < 0.01  # the walls moved +5 cm: the robot moved -5 cm


def test_input_errors_survive_pickling():
    err = RecordingError("bad line", source="run.clf", where="line 7")
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is RecordingError and (back.message, back.source, back.where) == (
        "bad line",
        "run.clf",
        "line 7",
    )
    assert str(back) == str(err)


@needs_worker
@pytest.mark.parametrize("schedule", ["here", "there", "alternating"])
def test_prepare_placement_gives_the_same_results(faulty_recording, schedule, monkeypatch):
    """Whichever stage prepares each chunk (decided per chunk, see the next test), the results are
    those of the in-process odometry. The placement is forced, so nothing depends on timing."""
    cfg = FRSlamConfig.from_dict(CFG).odometry
    scans = faulty_recording[:250]
    here = ScanOdometry(cfg)
    prepare_calls = []

    def prepare(points):
        prepare_calls.append(1)
        return here.prepare(points)

    inputs = [(s.stamp, s.points, s.odom, k) for k, s in enumerate(scans)]
    expected = [here.process(s.stamp, s.points, s.odom) for s in scans]
    with odometry_worker.OdometryWorker(cfg, chunk=8) as worker:
        chunks = iter(range(10**6))
        place = {
            "here": lambda: True,
            "there": lambda: False,
            "alternating": lambda: next(chunks) % 2 == 0,
        }[schedule]
        monkeypatch.setattr(worker, "_prepare_here", place)
        got = []
        for item, res, seconds, cpu_seconds in worker.run(inputs, prepare):
            got.append((item[3], res))
            assert seconds > 0.0 and cpu_seconds > 0.0
    assert [k for k, _ in got] == list(range(len(scans)))
    for (_, a), b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a.pose, b.pose)
        np.testing.assert_array_equal(a.covariance, b.covariance)
        assert a.keyframe == b.keyframe
    assert (
        worker.prepared_here + worker.prepared_there
        == len(scans)
        == len(prepare_calls) + worker.prepared_there
    )
    if schedule == "here":
        assert worker.prepared_there == 0
    elif schedule == "there":
        assert worker.prepared_here == 0
    else:
        assert worker.prepared_here > 0 and worker.prepared_there > 0


@needs_worker
def test_the_worker_may_run_256_scans_ahead_of_its_caller(faulty_recording):
    """The caller hands the worker 16 chunks of 16 scans before it takes the first result: a
    backend busy for a while (a closure's LM batch, a stretch of matching) does not stop the
    odometry until it is 256 scans ahead (with 64, FR079's and ACES's workers waited: tools/README.md)."""
    cfg = FRSlamConfig.from_dict(CFG).odometry
    pulled = []

    def inputs():
        for k, s in enumerate(faulty_recording[:300]):
            pulled.append(k)
            yield s.stamp, s.points, s.odom, k

    with odometry_worker.OdometryWorker(cfg) as worker:
        run = worker.run(inputs())
        first = next(run)
        assert first[0][3] == 0 and len(pulled) == 256 == worker.chunk * worker.window
        assert [item[3] for item, *_ in run] == list(range(1, 300))


def test_prepare_goes_to_the_lighter_stage():
    """The rule, on given moving averages (seconds per scan): the caller prepares while its own
    work is below the worker's odometry, and before both are measured."""
    worker = odometry_worker.OdometryWorker.__new__(odometry_worker.OdometryWorker)
    worker._odometry_s = worker._caller_s = None
    assert worker._prepare_here()
    worker._odometry_s, worker._caller_s = 1e-3, 1e-4  # light backend
    assert worker._prepare_here()
    worker._odometry_s, worker._caller_s = 1e-3, 1e-2  # heavy backend
    assert not worker._prepare_here()


@pytest.mark.parametrize("parallel", [False, pytest.param(True, marks=needs_worker)])
def test_cpu_latency_counts_the_work_of_a_scan_not_the_waits(faulty_recording, monkeypatch, parallel):
    """``cpu_latencies`` are CPU seconds of the threads that did each scan's work: a backend
    stage that waits (here a 30 ms sleep on every 10th scan, as a busy machine would make it
    wait) shows in the wall latency and not in the CPU one."""
    slam = FRSlam(FRSlamConfig.from_dict({**CFG, "loop_closure": {"enabled": False}}))
    add = slam.add_odometry
    calls = iter(range(10**9))

    def waiting_add(*args, **kwargs):
        if next(calls) % 10 == 0:
            time.sleep(0.03)
        return add(*args, **kwargs)

    monkeypatch.setattr(slam, "add_odometry", waiting_add)
    res = process(slam, faulty_recording[:200], parallel=parallel)
    assert res.parallel is parallel
    assert res.cpu_latencies.shape == res.latencies.shape == (200,)
    assert np.all(res.cpu_latencies > 0.0)
    slept = np.arange(200) % 10 == 0
    assert np.all(res.latencies[slept] >= 0.03)
    assert np.all(res.cpu_latencies[slept] < res.latencies[slept] - 0.02)
