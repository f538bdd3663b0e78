"""Scale-out figures: Dask generation with 1 and 2 workers; remote-style reads against local ones.

    python bench/bench_scaling.py [--runs 4] [--frames 1500]

Generation: the same runs through a Dask LocalCluster of 1 and of 2 single-threaded worker
processes (the ratio is the scaling; the local process pool is the reference in the same run).
Reads: the same store from its local path and over HTTP from a server on loopback (the stand-in
for object storage here), loading the whole training split into memory and reading window by
window through the lazy path, with the chunk cache and without it.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

import numpy as np

from sonarset.sim import generate
from sonarset.store.store import open_store
from sonarset.testing import serve_directory
from sonarset.windows import FrameBank


def lazy_windows(location: str, n: int, **kw) -> float:
    """Windows per second reading 4 frames per window straight from the store."""
    run = open_store(location, **kw).run(open_store(location).runs()[0])
    starts = np.random.default_rng(0).integers(0, run.n_frames - 4, size=n)
    t0 = time.perf_counter()
    for k in starts:
        run.images[int(k):int(k) + 4]
    return n / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--frames", type=int, default=1500, help="frames per run")
    args = ap.parse_args()
    print(f"# bench_scaling  {platform.node()}  {os.cpu_count()} cores  python {platform.python_version()}")
    minutes = args.frames * 0.2 / 60
    frames = args.runs * args.frames
    with tempfile.TemporaryDirectory() as tmp:
        rates = {}
        for name, kw in (("local processes, 2", dict(workers=2)),
                         ("dask LocalCluster, 1 worker", dict(workers=1, scheduler="local")),
                         ("dask LocalCluster, 2 workers", dict(workers=2, scheduler="local"))):
            t0 = time.perf_counter()
            generate(os.path.join(tmp, f"{len(rates)}.zarr"), runs=args.runs, test_runs=0, minutes=minutes, seed=0, **kw)
            rates[name] = frames / (time.perf_counter() - t0)
            print(f"generate {args.runs} x {args.frames} frames, {name:30s} {rates[name]:8,.0f} frames/s (incl. start-up)")
        print(f"dask 2 workers / 1 worker = {rates['dask LocalCluster, 2 workers'] / rates['dask LocalCluster, 1 worker']:.2f}x; "
              f"dask 2 workers / local pool of 2 = {rates['dask LocalCluster, 2 workers'] / rates['local processes, 2']:.2f}x")

        local = os.path.join(tmp, "0.zarr")
        with serve_directory(tmp) as (base, served):
            url = f"{base}/0.zarr"
            t0 = time.perf_counter()
            FrameBank.from_store(open_store(local))
            t_local = time.perf_counter() - t0
            served.requests = 0
            t0 = time.perf_counter()
            FrameBank.from_store(open_store(url))
            t_http = time.perf_counter() - t0
            print(f"load {frames} frames into memory: local {frames / t_local:8,.0f} frames/s, "
                  f"http {frames / t_http:8,.0f} frames/s ({served.requests} requests); "
                  f"remote/local time = {t_http / t_local:.2f}x")
            n = 2000
            w_local = lazy_windows(local, n)
            served.requests = 0
            w_cached = lazy_windows(url, n)
            req_cached = served.requests
            served.requests = 0
            w_raw = lazy_windows(url, n // 10, cache_bytes=0)
            req_raw = served.requests * 10
            print(f"lazy window reads (4 frames each): local {w_local:6,.0f} windows/s; "
                  f"http with chunk cache {w_cached:6,.0f} windows/s ({req_cached} requests for {n} windows); "
                  f"http without cache {w_raw:6,.0f} windows/s (~{req_raw} requests for {n})")
            print(f"remote/local time per window: with cache {w_local / w_cached:.2f}x, without {w_local / w_raw:.2f}x")


if __name__ == "__main__":
    main()
