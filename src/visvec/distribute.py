"""Many independent tasks (Monte Carlo runs, simulated frames, recordings) on this
machine's cores or on a Dask cluster.

:class:`TaskPool` runs one function over a list of inputs and yields each result with
its index as it finishes; :meth:`TaskPool.map` gathers them in task order, so that a
study's output does not depend on where or in which order its tasks ran (each task
carries its own seed). Where they run:

- ``scheduler="tcp://HOST:PORT"``: a running Dask scheduler and its workers (lab
  servers, an SSH cluster, a batch system: see the docs' "Studies on a cluster"). The
  workers must have this version of visvec installed; they are asked before any task
  is sent.
- ``workers=N`` without a scheduler: a local Dask cluster of N single-threaded worker
  processes (N = the cores by default), when Dask is installed (``pip install
  "visvec[dask]"``); otherwise N processes of the standard library's pool, or this
  process alone when N = 1.

Dask reruns the tasks of a worker that dies on the others. Ctrl-C stops the pool; the
results already gathered stay with the caller.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from functools import partial
from importlib import import_module, metadata
from typing import Any

import visvec
from visvec.errors import SourceError

CONNECT_TIMEOUT_S = 10.0


def one_thread(fn: Callable, x: Any) -> Any:
    """fn(x) with the linear algebra libraries on one thread, as Dask's workers run: a
    sum split over threads is added in another order, and a study's numbers would
    differ in their last digits between a serial run and a distributed one
    (threadpoolctl, installed with the [dask] extra)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return fn(x)
    with threadpool_limits(1):
        return fn(x)


def have_dask() -> bool:
    """Whether Dask's distributed scheduler is installed (the [dask] extra)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


class TaskPool:
    """Where a study's tasks run (module docstring); a context manager."""

    def __init__(self, scheduler: str | None = None, workers: int | None = None,
                 local_dask: bool = True):  # fmt: skip
        """``local_dask`` False: without a scheduler, local processes even where Dask is
        installed (a short job, which a local cluster's 2 s start would outlast)."""
        self.scheduler = scheduler
        self.local_dask = local_dask
        self.workers = workers or os.cpu_count() or 1
        self._client = None
        self._cluster = None
        self._pool: ProcessPoolExecutor | None = None
        if scheduler is not None and not have_dask():
            raise SourceError(
                f"Dask scheduler {scheduler}: Dask is not installed here; "
                'pip install "visvec[dask]"'
            )

    @property
    def where(self) -> str:
        """Where the tasks run, in words."""
        if self.scheduler is not None:
            n = len(self._client.scheduler_info()["workers"]) if self._client else 0
            return f"Dask scheduler {self.scheduler} ({n} workers)"
        if self._client is not None:
            return f"a local Dask cluster of {self.workers} workers"
        if self._pool is not None:
            return f"{self.workers} processes"
        return "this process"

    def __enter__(self) -> TaskPool:
        # the workers started here do not take Ctrl-C themselves: a terminal sends it to
        # every process of the group, and each worker printed its own traceback; this
        # process ends the run (an ignored signal stays ignored in a child, through
        # fork and exec)
        import signal

        try:
            before = signal.signal(signal.SIGINT, signal.SIG_IGN)
        except ValueError:  # not the main thread: nothing to set
            before = None
        try:
            return self._start()
        finally:
            if before is not None:
                signal.signal(signal.SIGINT, before)

    def _start(self) -> TaskPool:
        if self.scheduler is not None:
            self._connect()
        elif self.local_dask and have_dask() and self.workers > 1:
            import dask
            from distributed import Client, LocalCluster

            # the workers' environment: one thread per numerical library (as the tasks
            # run: one_thread), but not Dask's default MALLOC_TRIM_THRESHOLD_, whose
            # eager trimming costs these tasks 5 %; and the workers' own bookkeeping
            # (stack sampling every 10 ms, system and memory polls) less often, as it
            # takes the cores the tasks need (benchmarks/dask_scale.py)
            env = {k: 1 for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
            quiet = {
                "distributed.nanny.pre-spawn-environ": env,
                "distributed.worker.profile.enabled": False,
                "distributed.admin.system-monitor.interval": "2s",
                "distributed.worker.memory.monitor-interval": "1s",
            }
            with dask.config.set(quiet):
                self._cluster = LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True,
                    host="127.0.0.1", dashboard_address="127.0.0.1:0", silence_logs=40,
                )  # fmt: skip
            self._client = Client(self._cluster)
        elif self.workers > 1:
            self._pool = ProcessPoolExecutor(self.workers)
        return self

    def _connect(self) -> None:
        from distributed import Client

        try:
            self._client = Client(self.scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as exc:
            raise SourceError(
                f"Dask scheduler {self.scheduler}: no answer within "
                f"{CONNECT_TIMEOUT_S:g} s ({exc}): is it running, and is the address "
                "tcp://HOST:PORT as `dask scheduler` printed it?"
            ) from None
        # the installed visvec's version on every worker, asked of the standard library
        # (a worker without visvec answers with the error)
        versions = self._client.run(metadata.version, "visvec", on_error="return")
        versions = {w: (None if isinstance(v, Exception) else v) for w, v in versions.items()}
        if not versions:
            self.close()
            raise SourceError(f"Dask scheduler {self.scheduler}: it has no workers")
        wrong = {w: v for w, v in versions.items() if v != visvec.__version__}
        if wrong:
            self.close()
            names = ", ".join(f"{w} has {'no visvec' if v is None else 'visvec ' + v}"
                              for w, v in sorted(wrong.items()))  # fmt: skip
            raise SourceError(
                f"Dask scheduler {self.scheduler}: its workers must run visvec "
                f"{visvec.__version__}, as here: {names}"
            )

    def warm(self, module: str) -> None:
        """Import ``module`` on every worker now (a study's first tasks would pay it)."""
        if self._client is not None:
            self._client.run(import_module, module)
        elif self._pool is not None:
            list(self._pool.map(import_module, [module] * self.workers))

    def __exit__(self, *exc) -> None:
        self.close(abort=exc[0] is not None and issubclass(exc[0], KeyboardInterrupt))

    def close(self, abort: bool = False) -> None:
        """Stop the workers; with ``abort`` (Ctrl-C), the local processes at once,
        whatever task they are in (they do not take Ctrl-C themselves)."""
        if abort and self._pool is not None:
            for proc in list(getattr(self._pool, "_processes", {}).values()):
                proc.terminate()
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def run(self, fn: Callable, items: Sequence) -> Iterator[tuple[int, Any]]:
        """(index, fn(items[index])) for every item, as each finishes (each on one
        thread: :func:`one_thread`)."""
        fn = partial(one_thread, fn)
        if self._client is not None:
            from distributed import as_completed

            futures = self._client.map(fn, list(items), pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            try:
                for fut in as_completed(futures):
                    yield index[fut.key], fut.result()
            finally:
                self._client.cancel(futures)
        elif self._pool is not None:
            pending = {self._pool.submit(fn, x): i for i, x in enumerate(items)}
            try:
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        yield pending.pop(fut), fut.result()
            finally:
                for fut in pending:
                    fut.cancel()
        else:
            for i, x in enumerate(items):
                yield i, fn(x)

    def map(self, fn: Callable, items: Sequence, done: Callable[[int, Any], None] | None = None
            ) -> list:  # fmt: skip
        """fn over every item, the results in the items' order; ``done(index, result)``
        is called as each finishes (progress, keeping partial results)."""
        out: list = [None] * len(items)
        for i, r in self.run(fn, items):
            out[i] = r
            if done is not None:
                done(i, r)
        return out
