"""The Dask cluster the fleet commands run on: a local one on this machine, or an existing one."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from estimator.errors import EstimatorError
from estimator.fleet.tasks import WORKER_ENV


@contextmanager
def dask_client(workers: int | None, scheduler: str | None, most: int | None = None) -> Iterator[Any]:
    """A client of the cluster at ``scheduler`` (``tcp://HOST:PORT``), or of a local cluster of
    ``workers`` processes (default: the cores, at most ``most``), one thread each, bound to 127.0.0.1,
    no dashboard; closed (the local cluster too) on leaving."""
    from dask.distributed import Client, LocalCluster

    for k, v in WORKER_ENV.items():   # inherited by the local cluster's worker processes
        os.environ.setdefault(k, v)
    if scheduler:
        client, cluster = Client(scheduler), None
    else:
        n = workers or os.cpu_count() or 1
        if not 1 <= n <= 256:
            raise EstimatorError(f"--workers {n} must be within 1..256")
        cluster = LocalCluster(n_workers=min(n, most) if most else n, threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address=None, silence_logs=40)
        client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
