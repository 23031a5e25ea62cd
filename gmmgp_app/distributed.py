"""Running independent pieces of work (GP blocks, map tiles) on an Executor.

Everything goes through a :class:`concurrent.futures.Executor`, so the same code
runs in-process (:class:`SerialExecutor`), on local processes
(:class:`concurrent.futures.ProcessPoolExecutor`) or on a Dask cluster
(``distributed.Client(...).get_executor()``)::

    from gmmgp_app.distributed import open_executor
    with open_executor(workers=2) as ex:                 # Dask LocalCluster, 2 workers
        tmap = build_tiled_map(scan, cfg, executor=ex)
    with open_executor(scheduler="tcp://10.0.0.5:8786") as ex:   # an existing cluster
        ...

Tiny pieces of work are *batched*: a task carries several items whose estimated
cost adds up to at least ``min_task_seconds`` (10 ms by default), because a Dask
task costs about a millisecond of scheduling and serialisation.
"""

from __future__ import annotations

import contextlib
import math
from concurrent.futures import FIRST_COMPLETED, Executor, Future, as_completed, wait
from typing import Callable, Iterator, Optional, Sequence

import numpy as np

__all__ = [
    "DistributedError",
    "SerialExecutor",
    "open_executor",
    "batch_by_cost",
    "map_batched",
    "imap_unordered",
    "gp_block_seconds",
]

#: Rough sustained rate of the dense GP block work (kernel build + Cholesky), flop/s.
#: Only used to group blocks into tasks of about ``min_task_seconds``.
_FLOPS = 2e9
#: Fixed per-block cost (Python overhead of one ``fit_block`` call), s.
_BLOCK_OVERHEAD = 5e-5


class DistributedError(ValueError):
    """Bad executor settings (workers, scheduler address, batching)."""


class SerialExecutor(Executor):
    """An Executor that runs each task at ``submit`` time in the calling thread.

    The default: no processes, no pickling, results bitwise identical to a plain
    loop. Exceptions are stored in the returned future, as other executors do.
    """

    #: Tasks run on this machine: they may read and write the caller's files.
    shared_filesystem = True

    def submit(self, fn, /, *args, **kwargs) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - delivered through the future
            fut.set_exception(exc)
        return fut


@contextlib.contextmanager
def open_executor(workers: Optional[int] = None, scheduler: Optional[str] = None,
                  kind: str = "dask", numba_threads: Optional[int] = None
                  ) -> Iterator[Executor]:
    """An executor for the mapper, closed (with its cluster) on exit.

    Parameters
    ----------
    workers : int, optional
        Number of local worker processes. ``None`` or 0 with no ``scheduler``
        gives a :class:`SerialExecutor`.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://HOST:PORT"``); ``workers``
        is then ignored (the cluster has its own).
    kind : {"dask", "processes"}
        Local workers through a Dask ``LocalCluster`` (one thread per worker) or
        a :class:`concurrent.futures.ProcessPoolExecutor`.
    numba_threads : int, optional
        Threads of each local worker's numba kernels (``NUMBA_NUM_THREADS`` in the
        worker's environment). Default: the machine's cores shared out,
        ``max(1, cores // workers)``, so that workers do not oversubscribe the cores
        (each worker's BLAS has one thread already). Not applied to a ``scheduler``'s
        workers.

    Yields
    ------
    concurrent.futures.Executor
        Local workers' executors carry ``shared_filesystem = True`` (tasks may read
        and write the caller's files: :func:`gmmgp_app.tiling.tasks.map_tiles_to_store`
        has them save tile maps into the tile store themselves); a ``scheduler``'s do
        not say so.
    """
    if kind not in ("dask", "processes"):
        raise DistributedError(f"Expected kind 'dask' or 'processes', found {kind!r}.")
    if workers is not None and (not isinstance(workers, (int, np.integer)) or workers < 0):
        raise DistributedError(f"Expected workers to be an integer >= 0, found {workers!r}; "
                               "use e.g. --workers 2.")
    if scheduler is not None:
        if not isinstance(scheduler, str) or "://" not in scheduler:
            raise DistributedError(f"Expected a scheduler address like 'tcp://HOST:8786', "
                                   f"found {scheduler!r}.")
        from distributed import Client

        client = Client(scheduler)
        try:
            yield client.get_executor()
        finally:
            client.close()
        return
    if not workers:
        yield SerialExecutor()
        return
    import os

    if numba_threads is None:
        numba_threads = max(1, (os.cpu_count() or 1) // int(workers))
    if not (isinstance(numba_threads, (int, np.integer)) and numba_threads >= 1):
        raise DistributedError(f"Expected numba_threads to be an integer >= 1, found "
                               f"{numba_threads!r}.")
    if kind == "processes":
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        # spawned, not forked: the parent's numba parallel kernels start GNU OpenMP
        # threads, and a child forked from such a process aborts ("fork() called from a
        # process already using GNU OpenMP")
        with ProcessPoolExecutor(max_workers=int(workers), initializer=_single_thread_blas,
                                 initargs=(int(numba_threads),),
                                 mp_context=multiprocessing.get_context("spawn")) as ex:
            ex.shared_filesystem = True
            yield ex
        return
    from distributed import Client, LocalCluster

    # one thread per worker: the work is numpy/numba bound and holds the GIL in places
    # (the nanny gives each worker one BLAS/OpenMP thread; numba's pool is its own)
    cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                           dashboard_address=":0",
                           env={"NUMBA_NUM_THREADS": str(int(numba_threads))})
    client = Client(cluster)
    try:
        ex = client.get_executor()
        ex.shared_filesystem = True
        yield ex
    finally:
        client.close()
        cluster.close()


def _single_thread_blas(numba_threads: Optional[int] = None):
    """Worker initialiser: one BLAS thread per worker process (as Dask's nanny does);
    several multithreaded BLAS pools on few cores slow a Cholesky down 100x. With
    ``numba_threads``, numba's thread count too (read when numba is first imported:
    a spawned worker has not imported it yet)."""
    import os

    if numba_threads is not None:
        os.environ["NUMBA_NUM_THREADS"] = str(int(numba_threads))
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - threadpoolctl ships with scikit-learn
        pass


def gp_block_seconds(n_points) -> np.ndarray:
    """Estimated seconds to fit blocks of ``n_points`` (B,) GP points each.

    A block of n points has a 4n x 4n covariance: about ``(4n)^3 / 3`` flops for
    the Cholesky factor and ``~30 (4n)^2`` for the joint kernel.
    """
    n4 = 4.0 * np.asarray(n_points, dtype=np.float64)
    return (n4 ** 3 / 3.0 + 30.0 * n4 ** 2) / _FLOPS + _BLOCK_OVERHEAD


def batch_by_cost(costs, min_task_seconds: float = 0.01,
                  max_batches: Optional[int] = None) -> list[np.ndarray]:
    """Group consecutive items into batches of at least ``min_task_seconds`` each.

    Parameters
    ----------
    costs : (B,) array_like
        Estimated seconds per item (>= 0).
    min_task_seconds : float
        A batch is closed once its summed cost reaches this; the last batch may
        be lighter (it is merged into the previous one when it would be below half).
    max_batches : int, optional
        Upper bound on the number of batches (larger batches beyond it).

    Returns
    -------
    list of (b_i,) int64 index arrays, in order, covering ``range(B)`` exactly once.
    """
    c = np.asarray(costs, dtype=np.float64).reshape(-1)
    if not (min_task_seconds >= 0 and math.isfinite(min_task_seconds)):
        raise DistributedError(f"Expected min_task_seconds >= 0, found {min_task_seconds!r}.")
    if np.any(~np.isfinite(c)) or np.any(c < 0):
        raise DistributedError("Expected finite, non-negative item costs, found "
                               f"{int(np.count_nonzero(~(np.isfinite(c) & (c >= 0))))} bad "
                               "values.")
    if len(c) == 0:
        return []
    target = float(min_task_seconds)
    if max_batches is not None and max_batches > 0:
        target = max(target, float(c.sum()) / max_batches)
    out, start, acc = [], 0, 0.0
    for i, ci in enumerate(c):
        acc += ci
        if acc >= target:
            out.append(np.arange(start, i + 1))
            start, acc = i + 1, 0.0
    if start < len(c):
        if out and acc < 0.5 * target:
            out[-1] = np.arange(out[-1][0], len(c))
        else:
            out.append(np.arange(start, len(c)))
    return out


def map_batched(executor: Optional[Executor], fn: Callable, batches: Sequence,
                sizes: Optional[Sequence[int]] = None,
                progress: Optional[Callable[[int, int], None]] = None) -> list:
    """Run ``fn(batch)`` for every batch on ``executor``; results in batch order.

    Parameters
    ----------
    executor : Executor or None
        ``None`` runs serially in this thread.
    fn : callable
        Must be picklable (a module-level function) for process or Dask executors.
    batches : sequence
        Arguments, one per task.
    sizes : sequence of int, optional
        Items per batch, for the progress count (default 1 per batch).
    progress : callable(done, total), optional
        Called once at the start (done = 0) and after each finished task, in
        completion order, with the number of *items* done so far: one progress
        bar across all tasks of a run.

    Returns
    -------
    list of ``fn(batch)``, in the order of ``batches``.
    """
    sizes = [1] * len(batches) if sizes is None else [int(s) for s in sizes]
    total = int(sum(sizes))
    if progress is not None:
        progress(0, total)
    if executor is None:
        executor = SerialExecutor()
    futs = {executor.submit(fn, b): i for i, b in enumerate(batches)}
    results: list = [None] * len(batches)
    done = 0
    for fut in as_completed(futs):
        i = futs[fut]
        results[i] = fut.result()
        done += sizes[i]
        if progress is not None:
            progress(done, total)
    return results


def imap_unordered(executor: Optional[Executor], fn: Callable, tasks: Sequence,
                   window: int = 4) -> Iterator[tuple]:
    """``(i, fn(tasks[i]))`` for every task, in completion order, with at most ``window``
    tasks submitted and not yet handed back.

    What a tiled build needs: finished tile maps are consumed (saved, dropped) as they
    come, so at most ``window`` wait in memory, and a worker that finishes starts the
    next tile at once (submitting in waves of ``window`` left workers idle at the end
    of every wave while the wave's largest tile finished). ``None`` or a
    :class:`SerialExecutor` runs each task at submission: one result in memory at a
    time.
    """
    if not (isinstance(window, (int, np.integer)) and window >= 1):
        raise DistributedError(f"Expected window to be an integer >= 1, found {window!r}.")
    if executor is None:
        executor = SerialExecutor()
    if isinstance(executor, SerialExecutor):
        window = 1
    pending: dict = {}
    nxt = 0
    while nxt < len(tasks) or pending:
        while nxt < len(tasks) and len(pending) < window:
            pending[executor.submit(fn, tasks[nxt])] = nxt
            nxt += 1
        finished, _ = wait(list(pending), return_when=FIRST_COMPLETED)
        for fut in sorted(finished, key=pending.get):
            i = pending.pop(fut)
            yield i, fut.result()
