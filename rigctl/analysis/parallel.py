"""Run the repetitions of an analysis on all cores, or on a Dask cluster.

Each repetition of a Table 1 task (a new random draw, its folds, one PCA per fold and variant) is independent of the
others, so :func:`map_repeats` runs them side by side: in threads of this process (NumPy's BLAS releases the GIL;
BLAS is limited to one thread per repetition meanwhile, so the cores are not oversubscribed), or as tasks on a Dask
cluster (``scheduler`` = an address such as ``tcp://host:8786``, or ``"local"`` for a local cluster of processes),
with the feature matrices sent to every worker once. Results come back in repetition order, so the outcome does not
depend on where or how many at a time they ran.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import ParamSpec, TypeVar

from rigctl.core.cluster import connected, dask_client

__all__ = ["dask_client", "connected", "map_repeats", "map_threads", "one_blas_thread"]

_P = ParamSpec("_P")
_R = TypeVar("_R")


def one_blas_thread(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """``fn`` run with BLAS limited to one thread (threadpoolctl), for an analysis whose matrices are small (tens of
    trials by at most a few hundred features, PCs and classes): there BLAS's threads spend more CPU waiting for each
    other than computing (measured on 2 cores: ``rigctl analyze --task realtime`` on 50 scans, 4.6 CPU-s with
    OpenBLAS's default threads, 2.6 with one, the same output). The repetitions of :func:`map_repeats` run so too."""

    @functools.wraps(fn)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper


def map_repeats(fn, repeats, shared, *, n_jobs=None, scheduler=None, workers=None, on_done=None):
    """``[fn(r, **shared) for r in range(repeats)]``, computed in parallel.

    Parameters
    ----------
    fn : callable
        A module-level function ``fn(repeat, **shared)`` (pickled to Dask workers).
    repeats : int
    shared : dict
        Keyword arguments common to every repetition (the feature matrices: sent to each Dask worker once).
    n_jobs : int, optional
        Repetitions at a time in this process (default: one per core; 1 = sequential, BLAS on every core).
    scheduler : str or dask.distributed.Client, optional
        Dask scheduler address, ``"local"``, or a connected client (left open); when given, ``n_jobs`` is ignored.
    workers : int, optional
        Worker processes of ``scheduler="local"``.
    on_done : callable, optional
        Called with no argument after each finished repetition (progress bars).

    Returns
    -------
    list
        The repetitions' results, in repetition order.
    """
    tick = on_done or (lambda: None)
    if scheduler is not None:
        from dask.distributed import as_completed

        with connected(scheduler, workers) as client:
            # one future for the whole dict, under a fresh key (a dict scattered as is would be keyed by its field
            # names, shared with - and released by - the previous task's data)
            shared_f = client.scatter([shared], broadcast=True, hash=False)[0]
            futures = [client.submit(_call, fn, r, shared_f, pure=False) for r in range(repeats)]
            for _ in as_completed(futures):
                tick()
            return client.gather(futures)
    n_jobs = min(repeats, n_jobs or os.cpu_count() or 1)
    if n_jobs <= 1:
        out = []
        for r in range(repeats):
            out.append(fn(r, **shared))
            tick()
        return out
    from joblib import Parallel, delayed
    from threadpoolctl import threadpool_limits

    out = []
    with threadpool_limits(1):
        for res in Parallel(n_jobs=n_jobs, prefer="threads", return_as="generator")(
                delayed(fn)(r, **shared) for r in range(repeats)):
            out.append(res)
            tick()
    return out


def map_threads(fn, items, *, n_jobs=None):
    """``[fn(item) for item in items]`` on ``n_jobs`` threads of this process (default one per core), each with one
    BLAS thread, in order: the once-per-run steps of Table 1 (each variant's zero padding and trained cells' Gram
    matrix), which ran one at a time between the repetitions with BLAS on both cores (OpenBLAS's second thread spins
    more than it works on these sizes). ``n_jobs=1``: one at a time, BLAS as configured."""
    items = list(items)
    n_jobs = min(len(items), n_jobs or os.cpu_count() or 1)
    if n_jobs <= 1:
        return [fn(item) for item in items]
    from concurrent.futures import ThreadPoolExecutor

    from threadpoolctl import threadpool_limits

    with threadpool_limits(1), ThreadPoolExecutor(n_jobs) as pool:
        return list(pool.map(fn, items))


def _call(fn, r, shared):
    return fn(r, **shared)
