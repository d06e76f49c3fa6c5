"""Dask clusters for the work that scales out (``rigctl encode --scheduler``, ``rigctl analyze --scheduler``): one
home for connecting to a scheduler or starting a local cluster, shared by encoding and analysis (which may not import
each other). Dask itself is imported only when a cluster is asked for (the optional ``rigctl[dask]`` extra).
"""

from __future__ import annotations

import os
from contextlib import contextmanager

__all__ = ["dask_client", "connected"]


def dask_client(scheduler, workers=None):
    """A ``dask.distributed.Client`` for ``scheduler`` (an address, or ``"local"``: a local cluster of ``workers``
    single-threaded processes, default one per core) and the cluster it started (None for an address).

    Raises
    ------
    ImportError
        Dask's distributed scheduler is not installed (``pip install 'rigctl[dask]'``).
    """
    from dask.distributed import Client, LocalCluster

    if scheduler == "local":
        cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        return Client(cluster), cluster
    return Client(scheduler), None


@contextmanager
def connected(scheduler, workers=None):
    """Context: a Dask client for ``scheduler`` (an address or ``"local"``: connected here, closed on exit with the
    local cluster), ``scheduler`` itself if it is already a client (left open), or None if ``scheduler`` is None."""
    if scheduler is None or not isinstance(scheduler, str):
        yield scheduler
        return
    client, cluster = dask_client(scheduler, workers)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
