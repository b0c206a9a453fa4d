"""Run a benchmark's tasks in a plain loop or through Dask distributed (the tools' one sweep helper).

``Sweep(workers=1)`` runs every task in this process, one after another, in submission order.
``Sweep(workers=N)`` (N > 1) starts a ``dask.distributed.LocalCluster`` of N single-threaded worker
processes on this machine (no dashboard, no memory limit: a task that needs the memory gets it,
as with a process pool); ``Sweep(scheduler="tcp://host:8786")`` attaches to an existing Dask
cluster instead (its workers must have frslam installed; ``workers`` is then ignored). An
unreachable scheduler raises :class:`SweepError` with one line naming the address.

A task is ``fn(task)`` with a picklable task (a dict) and a picklable result. Functions of a tool
script are pickled by value (cloudpickle does it for ``__main__`` and for the tools the tests load
from a file), so a remote worker needs frslam, not this folder. Dask's worker processes start with
``OMP_NUM_THREADS`` and the other BLAS thread counts at 1; a task that uses OpenCV sets
``cv2.setNumThreads`` itself.

    with Sweep(workers=2) as sweep:                      # all at once, results in submission order
        rows = sweep.map(run_case, tasks, progress=lambda done, total: ...)

    with Sweep(workers, scheduler) as sweep:             # a bounded number in flight, as completed
        sweep.submit(house, first)
        for result in sweep.as_completed():
            if more: sweep.submit(house, nxt)            # included in the same iteration
"""

from __future__ import annotations

import logging
import warnings
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

__all__ = ["Sweep", "SweepError"]

Progress = Callable[[int, int], None]

#: seconds to wait for a ``--scheduler`` to answer (when ``Sweep`` is given no timeout of its own)
CONNECT_TIMEOUT_S = 10.0


class SweepError(RuntimeError):
    """The sweep cannot run (a scheduler address that does not answer, a bad worker count)."""


class Sweep:
    """Tasks in a plain loop (one worker, no scheduler) or on a Dask cluster; a context manager
    that closes the client, and the cluster it started, on the way out (also on an error)."""

    def __init__(
        self, workers: int = 1, scheduler: str | None = None, connect_timeout_s: float | None = None
    ) -> None:
        if scheduler is None and workers < 1:
            raise SweepError(f"--workers {workers}: expected 1 or more")
        self.workers = workers
        self.scheduler = scheduler
        self.connect_timeout_s = connect_timeout_s
        self.client: Any = None
        self._cluster: Any = None
        self._queue: deque[tuple[Callable[[Any], Any], Any]] = deque()  # the plain loop's
        self._done: Any = None  # dask's as_completed, fed by submit

    @property
    def distributed(self) -> bool:
        """True when the tasks run on a Dask cluster, False for the plain loop."""
        return self.scheduler is not None or self.workers > 1

    def __enter__(self) -> Sweep:
        if not self.distributed:
            return self
        from dask.distributed import Client, LocalCluster

        if self.scheduler is None:
            with warnings.catch_warnings():  # its HTTP server moves off a port another cluster holds
                warnings.filterwarnings("ignore", message="Port .* is already in use")
                self._cluster = LocalCluster(
                    n_workers=self.workers,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    memory_limit=0,
                    silence_logs=logging.ERROR,  # not "worker still alive after 4 s, killing" at close
                )
            try:
                self.client = Client(self._cluster)
                self.client.wait_for_workers(self.workers)  # so ``slots`` counts them all from the start
            except BaseException:
                self.__exit__()
                raise
            return self
        try:
            timeout = CONNECT_TIMEOUT_S if self.connect_timeout_s is None else self.connect_timeout_s
            self.client = Client(self.scheduler, timeout=f"{timeout}s")
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise SweepError(
                f"--scheduler {self.scheduler}: no Dask scheduler answers there ({why})"
            ) from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    @property
    def slots(self) -> int:
        """Tasks that can run at once: 1 for the plain loop, else the cluster's worker threads."""
        if self.client is None:
            return 1
        return max(1, sum(self.client.nthreads().values()))

    def map(self, fn: Callable[[Any], Any], tasks: list[Any], progress: Progress | None = None) -> list[Any]:
        """``[fn(t) for t in tasks]``, run by the workers; results in submission order whatever order
        they finish in. ``progress(done, total)`` is called after each task finishes."""
        total = len(tasks)
        if self.client is None:
            out = []
            for task in tasks:
                out.append(fn(task))
                if progress is not None:
                    progress(len(out), total)
            return out
        from dask.distributed import as_completed

        futures = [self.client.submit(fn, t, pure=False) for t in tasks]
        for done, _ in enumerate(as_completed(futures), start=1):
            if progress is not None:
                progress(done, total)
        return self.client.gather(futures)

    def submit(self, fn: Callable[[Any], Any], task: Any) -> None:
        """Queue ``fn(task)``; its result comes out of :meth:`as_completed`."""
        if self.client is None:
            self._queue.append((fn, task))
            return
        from dask.distributed import as_completed

        future = self.client.submit(fn, task, pure=False)
        if self._done is None:
            self._done = as_completed([future])
        else:
            self._done.add(future)

    def as_completed(self) -> Iterator[Any]:
        """Results of the submitted tasks as they finish (the plain loop: in submission order);
        tasks submitted while iterating are included. A task's exception is raised here."""
        if self.client is None:
            while self._queue:
                fn, task = self._queue.popleft()
                yield fn(task)
            return
        while self._done is not None and not self._done.is_empty():
            yield next(self._done).result()
