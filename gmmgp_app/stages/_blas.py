"""One BLAS thread for the stages' many small dense solves.

The local GPs factorise and solve thousands of small matrices (4n x 4n, n <= a few
hundred). A multithreaded OpenBLAS splits each of them across its threads, which
spin while they wait; on a loaded 2-core machine an 8 x 8 triangular solve then
took 14 ms instead of 0.02 ms, and ``gmmgp run`` on the 1.3M-point street spent
465 s instead of ~30 s extracting its surface (scripts/bench_peers.py, docs/speed.md).
Parallel work belongs to the executor (one single-threaded worker per core), not
to BLAS inside a block.
"""

from __future__ import annotations

import contextlib
import functools

_CONTROLLER = None


def one_blas_thread():
    """Context manager limiting BLAS (OpenBLAS, MKL, BLIS) to one thread, restoring it
    on exit; a no-op when threadpoolctl is not installed."""
    global _CONTROLLER
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - threadpoolctl is a declared dependency
        return contextlib.nullcontext()
    if _CONTROLLER is None:  # scanning the loaded libraries costs ~ms: once
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")


def single_threaded_blas(fn):
    """Decorator: run ``fn`` under :func:`one_blas_thread`."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return fn(*args, **kwargs)

    return wrapper
