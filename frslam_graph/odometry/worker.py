"""Scan odometry in a second process, one stage ahead of the backend (offline runs).

The front end (:class:`~frslam_graph.odometry.scan_odometry.ScanOdometry`: KISS-ICP fused with wheel odometry)
depends on nothing downstream: the graph, loop closure and floor-plan priors never feed back into
it. Offline, :func:`frslam_graph.offline.process` therefore runs it in a
forked worker on the second core while the caller's process runs the backend on the results of
earlier scans, a classic two-stage pipeline. The worker gets scans (stamp, points in base_link,
wheel pose in odom) in chunks and returns one :class:`~frslam_graph.odometry.scan_odometry.OdometryResult` per
scan, in order; the results are bit-identical to running the
same ScanOdometry in-process. Frames and units are those of :mod:`frslam_graph.odometry.scan_odometry`.

The stateless part of the odometry (:meth:`ScanOdometry.prepare
<frslam_graph.odometry.scan_odometry.ScanOdometry.prepare>`: valid points, voxelisation, scan geometry) goes to
whichever stage is the lighter one: given a ``prepare`` function, :meth:`OdometryWorker.run`
applies it in the caller to the next chunk while the caller's own work per scan is below the
worker's (a light backend), and leaves it to the worker otherwise (loop closure and floor-plan
priors), by moving averages of both stages' times. Either way the worker's results are the same
(prepare is deterministic and stateless); only the speed depends on the split.

An input error raised by the odometry in the worker (e.g. a non-finite stamp) is re-raised in the
caller after the results of the scans before it, exactly where the in-process run would raise.
The worker is started with ``fork`` (Linux), so nothing is pickled at start-up and it costs
milliseconds; :func:`available` tells whether this process can start one.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from frslam_graph.config import OdometryConfig
from frslam_graph.errors import FrslamError
from frslam_graph.odometry.scan_odometry import OdometryResult, OdometryStats, PreparedScan, ScanOdometry

#: one scan for the worker: stamp (s), points (M, 2) in base_link or their PreparedScan, wheel
#: pose (x, y, theta) in odom or None
ScanInput = tuple[float, np.ndarray, Any]


def available(config: OdometryConfig) -> bool:
    """Whether a worker can run here: Linux ``fork``, two or more cores, not inside a daemonic
    process (which may not have children), and KISS-ICP single-threaded (``num_threads`` 1: a
    forked child must not inherit a TBB thread pool)."""
    return (
        sys.platform.startswith("linux")
        and "fork" in mp.get_all_start_methods()
        and (os.cpu_count() or 1) >= 2
        and not mp.current_process().daemon
        and config.num_threads == 1
    )


def _exit_when_orphaned(parent: int, poll_s: float) -> None:
    """Worker thread: end the worker process once its caller is gone, whatever the worker is
    blocked in. A caller killed while it wrote a chunk leaves part of a message in the inbox
    pipe, whose write end the forked worker holds too: its read then waited forever (a worker
    found still asleep 6 minutes after ``frslam run`` was killed); a full outbox blocks too."""
    while os.getppid() == parent:
        time.sleep(poll_s)
    os._exit(0)


def _serve(config: OdometryConfig, inbox, outbox, parent: int, poll_s: float = 1.0) -> None:
    """Worker loop: chunks of ScanInput in, lists of results out; None ends it.

    Ctrl-C is the caller's to handle (it stops the worker); a worker whose caller died without
    stopping it (killed) is ended by :func:`_exit_when_orphaned`, whatever it is blocked in.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_when_orphaned, args=(parent, poll_s), daemon=True).start()
    odometry = ScanOdometry(config)
    while True:
        chunk = inbox.get()
        if chunk is None:
            outbox.put(("done", odometry.stats))
            return
        results: list[tuple[OdometryResult, float, float, float]] = []
        try:
            for stamp, points, odom in chunk:
                t0, c0 = time.perf_counter(), time.thread_time()
                if not isinstance(points, PreparedScan):  # what process() would do first
                    points = odometry.prepare(points)
                t1 = time.perf_counter()
                res = odometry.process(stamp, points, odom)
                results.append((res, time.perf_counter() - t0, t1 - t0, time.thread_time() - c0))
        except FrslamError as exc:  # bad input: the caller raises it after the earlier results
            outbox.put(("results", results))
            outbox.put(("error", exc))
            return
        except Exception:  # a bug: report it rather than leave the caller waiting
            outbox.put(("results", results))
            outbox.put(("crash", traceback.format_exc()))
            return
        outbox.put(("results", results))


class OdometryWorker:
    """A ScanOdometry in a forked process (see module docstring); use as a context manager.

    ``run(items, prepare)`` yields ``(item, result, seconds, cpu_seconds)`` for each ``item`` of
    ``items`` (a ScanInput followed by anything the caller wants back with it), in order, keeping
    at most ``chunk * window`` scans in flight; ``seconds`` is the wall time the odometry took on
    it and ``cpu_seconds`` its thread's CPU time (its prepare included, wherever it ran). ``stats`` holds the worker's
    :class:`OdometryStats` once ``run`` is exhausted; ``prepared_here`` / ``prepared_there``
    count the scans whose prepare ran in the caller / in the worker.

    The window lets the worker run ahead through the backend's bursts (a closure's LM batch and
    the iSAM2 updates after it, a stretch of loop-closure matching): with 64 scans in flight it
    waited for the backend, with 256 it hardly does. A pipeline simulation on the scans' CPU
    times (FR079 / ACES / Intel, odometry CPU 20.1 / 19.8 / 34.6 s): the run's two stages end
    after 21.7 / 21.7 / 35.8 s of CPU time with 64 in flight, 21.0 / 19.9 / 35.2 with 256 (as
    with any larger window). A scan in flight holds its points and result: ~10 kB.
    """

    def __init__(self, config: OdometryConfig, chunk: int = 16, window: int = 16, poll_s: float = 1.0):
        if chunk < 1 or window < 1:
            raise ValueError("chunk and window must be >= 1")
        self.chunk, self.window, self.poll_s = chunk, window, poll_s
        self.stats: OdometryStats | None = None
        self.prepared_here = self.prepared_there = 0
        # moving averages (s per scan) of each stage's own work: the worker's odometry without
        # prepare, and the caller's time between taking one result and asking for the next
        self._odometry_s = self._caller_s = None
        ctx = mp.get_context("fork")
        self._inbox, self._outbox = ctx.Queue(), ctx.Queue()
        self._proc = ctx.Process(
            target=_serve,
            args=(config, self._inbox, self._outbox, os.getpid(), poll_s),
            name="frslam-odometry",
            daemon=True,
        )
        self._proc.start()

    def __enter__(self) -> OdometryWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the worker (also after an error in the caller) and release its queues."""
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join(timeout=5.0)
        for q in (self._inbox, self._outbox):
            q.cancel_join_thread()
            q.close()

    def _receive(self) -> Any:
        """The next payload ("results" or "done"); a worker's input error or failure is raised."""
        while True:
            try:
                kind, payload = self._outbox.get(timeout=self.poll_s)
                break
            except queue.Empty:
                if not self._proc.is_alive():
                    raise RuntimeError(
                        f"the odometry worker process exited unexpectedly (exit code {self._proc.exitcode})"
                    ) from None
        if kind == "error":
            raise payload
        if kind == "crash":
            raise RuntimeError(f"the odometry worker failed:\n{payload}")
        return payload

    def _prepare_here(self) -> bool:
        """Prepare the next chunk in the caller unless the caller's own work per scan (the
        backend) is at least the worker's (its odometry without prepare): with b the backend's and
        w the odometry's seconds per scan and p prepare's, the pipeline takes max(b + p, w) per
        scan with prepare here and max(b, w + p) there, and the latter is smaller iff b >= w."""
        if self._odometry_s is None or self._caller_s is None:
            return True
        return self._caller_s < self._odometry_s

    def run(
        self, items: Iterable[tuple[Any, ...]], prepare: Callable[[np.ndarray], Any] | None = None
    ) -> Iterator[tuple[tuple[Any, ...], OdometryResult, float, float]]:
        """See the class docstring. ``prepare``: the odometry's stateless preparation of an item's
        points (``ScanOdometry.prepare``), run in this process while the worker is the slower
        stage; None = always in the worker."""
        source = iter(items)
        # (item, prepare wall s, prepare CPU s) sent, not yielded
        waiting: deque[tuple[tuple[Any, ...], float, float]] = deque()
        in_flight, exhausted = 0, False
        while True:
            while not exhausted and in_flight < self.window:
                chunk = []
                here = prepare is not None and self._prepare_here()
                for item in source:
                    stamp, points, odom = item[:3]
                    prepare_s = prepare_cpu = 0.0
                    if here:
                        t0, c0 = time.perf_counter(), time.thread_time()
                        points = prepare(points)
                        prepare_s, prepare_cpu = time.perf_counter() - t0, time.thread_time() - c0
                    waiting.append((item, prepare_s, prepare_cpu))
                    chunk.append((stamp, points, odom))
                    if len(chunk) == self.chunk:
                        break
                if here:
                    self.prepared_here += len(chunk)
                else:
                    self.prepared_there += len(chunk)
                if chunk:
                    self._inbox.put(chunk)
                    in_flight += 1
                if len(chunk) < self.chunk:
                    exhausted = True
                    self._inbox.put(None)
            if in_flight == 0:
                break
            results = self._receive()
            in_flight -= 1
            for result, seconds, worker_prepare_s, cpu_s in results:
                item, prepare_s, prepare_cpu = waiting.popleft()
                self._odometry_s = _average(self._odometry_s, seconds - worker_prepare_s)
                t0 = time.perf_counter()
                yield item, result, seconds + prepare_s, cpu_s + prepare_cpu
                self._caller_s = _average(self._caller_s, time.perf_counter() - t0)
        self.stats = self._receive()  # or the error that ended the last chunk after its results


def _average(mean: float | None, x: float, weight: float = 1.0 / 64.0) -> float:
    """Exponential moving average (about the last 64 scans)."""
    return x if mean is None else mean + weight * (x - mean)


__all__ = ["OdometryWorker", "ScanInput", "available"]
