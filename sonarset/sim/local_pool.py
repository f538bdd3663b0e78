"""Run generation tasks in a local process pool (``generate`` without a ``scheduler``).

One task per run, exactly the function a Dask cluster runs (``runs.write_run``), in a
``sonarset.pool.WorkerPool`` (no worker outlives this process); progress comes back through a queue
the workers inherit, and only this process writes the root's consolidated metadata.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import threading

from sonarset.perf import keep_freed_memory
from sonarset.pool import WorkerPool
from sonarset.sim.runs import RunPlan, RunTarget, write_run


def run_locally(target: RunTarget, plans: list[RunPlan], workers: int | None, progress, store) -> None:
    """Simulate ``plans`` into the store ``target`` with up to ``workers`` processes (default: all
    cores); ``store`` (open for writing) is consolidated as runs complete."""
    total = {p.name: p.n_frames for p in plans}
    cores = workers or os.cpu_count() or 1
    workers = max(1, min(cores, len(plans)))
    if workers == 1:
        # one run on several cores (the demo's fresh run): two blocks at a time, as a pool's last run
        spare = threading.Event()
        if cores > 1:
            spare.set()
        for plan in plans:
            write_run(target, plan, _Direct(progress, total), spare)
            store.consolidate()
        return
    _run_pool(target, plans, workers, total, progress, store)


def _run_pool(target: RunTarget, todo: list[RunPlan], workers: int, total: dict, progress, store) -> None:
    """One task per run in a process pool; progress arrives through a queue the workers inherit."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    spare = ctx.Event()  # set once fewer runs remain than workers: a core is free
    try:
        _drive(WorkerPool(workers, _init_worker, (queue, spare)), target, todo, workers, total, progress, store,
               queue, spare)
    finally:
        # Freed now, not at exit: a semaphore still alive then is reported as leaked.
        queue.close()
        queue = spare = None


def _drive(pool: WorkerPool, target, todo, workers, total, progress, store, queue, spare) -> None:
    with pool:
        pending = {pool.submit(_write_run_in_worker, target, p) for p in todo}
        done = {p.name: 0 for p in todo}
        while pending:
            if len(pending) < workers:
                spare.set()
            finished, pending = cf.wait(pending, timeout=0.2)
            while not queue.empty():
                name, n = queue.get()
                done[name] += n
                if progress:
                    progress(name, done[name], total[name])
            for f in finished:
                f.result()  # re-raise a worker's error here
            if finished:
                # Only this process writes root metadata; zarr writes it atomically.
                store.consolidate()


_QUEUE = _SPARE = None


def _init_worker(queue, spare) -> None:
    global _QUEUE, _SPARE
    _QUEUE, _SPARE = queue, spare
    keep_freed_memory()


def _write_run_in_worker(target: RunTarget, plan: RunPlan) -> str:
    return write_run(target, plan, _QUEUE, _SPARE)


class _Direct:
    """Queue stand-in for the single-process path: reports progress straight away."""

    def __init__(self, progress, total):
        self.progress, self.total, self.done = progress, total, {}

    def put(self, item) -> None:
        name, n = item
        self.done[name] = self.done.get(name, 0) + n
        if self.progress:
            self.progress(name, self.done[name], self.total[name])
