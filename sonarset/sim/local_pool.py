"""Run generation tasks in a local process pool (``generate`` without a ``scheduler``).

One task per run, exactly the function a Dask cluster runs (``runs.write_run``); progress comes
back through a managed queue, and only this process writes the root's consolidated metadata.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import threading

from sonarset.perf import keep_freed_memory
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
    ctx = mp.get_context("spawn")  # no fork: zarr's event loop thread must not be copied
    # One BLAS/OpenMP thread per worker: the workers already fill the cores.
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS if k not in os.environ})
    try:
        _run_pool(ctx, target, plans, workers, total, progress, store)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _run_pool(ctx, target: RunTarget, todo: list[RunPlan], workers: int, total: dict, progress, store) -> None:
    """One task per run in a process pool; progress arrives through a managed queue."""
    with ctx.Manager() as manager:
        queue = manager.Queue()
        spare = manager.Event()  # set once fewer runs remain than workers: a core is free
        with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=keep_freed_memory) as pool:
            pending = {pool.submit(write_run, target, p, queue, spare) for p in todo}
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


class _Direct:
    """Queue stand-in for the single-process path: reports progress straight away."""

    def __init__(self, progress, total):
        self.progress, self.total, self.done = progress, total, {}

    def put(self, item) -> None:
        name, n = item
        self.done[name] = self.done.get(name, 0) + n
        if self.progress:
            self.progress(name, self.done[name], self.total[name])
