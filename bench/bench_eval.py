"""Evaluation throughput: persistence + naive + flow on 1000 windows x horizons 1, 3, 5, 10.

    python bench/bench_eval.py [--store STORE]   # default: simulate one 25-minute test run first

Prints the wall time of the whole evaluation (statistics included, figures excluded) with the
torch ``grid_sample`` warps, and the same evaluation with the SciPy ``map_coordinates`` warps as
the reference, in the same run. Goal: <= 30 s on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

from sonarset import RobotRig, open_store
from sonarset.models.baselines import AcousticFlow, NaiveShift, Persistence
from sonarset.models.eval.evaluate import evaluate
from sonarset.sim import generate


def run(store, backend: str) -> tuple[float, dict]:
    grid, rig = store.grid, store.rig or RobotRig()
    preds = {"persistence": Persistence(grid), "naive": NaiveShift(grid, rig, backend=backend),
             "flow": AcousticFlow(grid, rig, backend=backend)}
    t0 = time.perf_counter()
    res = evaluate(store, [], predictors=preds, samples=1000, horizons=(1, 3, 5, 10))
    return time.perf_counter() - t0, res.seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", help="an existing store with a 'test' split")
    args = ap.parse_args()
    print(f"# bench_eval  {platform.node()}  {os.cpu_count()} cores  python {platform.python_version()}")
    with tempfile.TemporaryDirectory() as tmp:
        path = args.store
        if path is None:
            path = os.path.join(tmp, "test.zarr")
            t0 = time.perf_counter()
            generate(path, runs=0, test_runs=1, minutes=25, seed=0, workers=1)
            print(f"(simulated one 7500-frame test run in {time.perf_counter() - t0:.1f} s)")
        store = open_store(path)
        for backend in ("torch", "scipy"):
            total, per = run(store, backend)
            detail = ", ".join(f"{k} {v:.1f} s" for k, v in per.items())
            print(f"{backend:6s} warps: {total:5.1f} s for 1000 windows x 4 horizons x 3 methods ({detail})")


if __name__ == "__main__":
    main()
