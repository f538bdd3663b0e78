"""Run generation tasks on a Dask distributed cluster (``generate`` given a ``scheduler``).

One task per run, exactly the function the local process pool runs (``runs.write_run``): the task
simulates its run from the run's own seed and writes the run group to the target store, so the
store is the same bit for bit whatever the cluster. Progress comes back through a Dask ``Queue``.
"""

from __future__ import annotations

import os
import time
import uuid

from sonarset.errors import SonarSetError
from sonarset.sim.runs import RunPlan, RunTarget, write_run

CONNECT_TIMEOUT = "15s"  # how long to wait for a scheduler address to answer


def connect(scheduler, workers: int | None):
    """(client, cluster or None) for an address, ``"local"`` or an existing ``distributed.Client``."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise SonarSetError("a Dask scheduler needs Dask distributed: pip install 'sonarset[dask]'",
                           parameter="scheduler") from None
    if isinstance(scheduler, Client):
        return scheduler, None
    if scheduler == "local":
        # One single-threaded worker process per core: a run is one sequential simulation.
        cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        return Client(cluster), cluster
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT), None
    except (OSError, TimeoutError, ValueError) as exc:
        raise SonarSetError(f"cannot reach the Dask scheduler at {scheduler!r}: {exc}") from None


def run_on_dask(scheduler, target: RunTarget, plans: list[RunPlan], workers: int | None, progress, store) -> None:
    from distributed import Queue

    client, cluster = connect(scheduler, workers)
    try:
        tag = uuid.uuid4().hex[:8]
        queue = Queue(f"sonarset-progress-{tag}", client=client)
        futures = [client.submit(write_run, target, p, queue,
                                 key=f"sonarset-generate-{p.name}-{tag}", pure=False, retries=0) for p in plans]
        done = {p.name: 0 for p in plans}
        total = {p.name: p.n_frames for p in plans}

        def drain() -> None:
            for name, n in queue.get(batch=True):
                done[name] += n
                if progress:
                    progress(name, done[name], total[name])

        pending = list(futures)
        while pending:
            time.sleep(0.2)
            drain()
            for f in [f for f in pending if f.done()]:
                f.result()  # re-raise a task's error here
                store.consolidate()  # only this process writes the root's consolidated metadata
                pending.remove(f)
        drain()
    finally:
        if cluster is not None:
            client.close()
            cluster.close()
