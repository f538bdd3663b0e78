"""Simulation and generation throughput.

    python bench/bench_generate.py            # quick: 2 runs x 1500 frames
    python bench/bench_generate.py --full     # plus the paper-scale dataset: 11 runs x 7500 frames,
                                              # default (ertis) images, then raw ones as the reference

Prints frames/s of the simulator alone (one process, no storage) for the default ``ertis`` images and
for ``raw`` delay-and-sum images (the reference in the same run), of simulate+write with 1 and 2
worker processes (the ratio is the parallel scaling), the wall time of the full default
configuration, and peak memory of the parent and of the largest worker.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import tempfile
import time

from sonarset.format.attrs import Processing, SensorGrid
from sonarset.sim import GenerationSpec, generate, plan_runs, simulate_blocks
from sonarset.sim.sonar import beam_table, range_psf_table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1500, help="frames per run in the quick measurements")
    ap.add_argument("--full", action="store_true", help="also generate the full 11 x 7500-frame dataset")
    args = ap.parse_args()
    grid = SensorGrid.default()
    print(f"# bench_generate  {platform.node()}  {os.cpu_count()} cores  python {platform.python_version()}")
    beam_table(), range_psf_table()  # one-time tables, not part of the per-frame rate
    minutes = args.frames * 0.2 / 60

    rate = {}
    for name in ("raw", "ertis"):
        processing = Processing.named(name)
        warm = GenerationSpec(runs=1, test_runs=0, minutes=0.2, seed=1, processing=processing)
        list(simulate_blocks(plan_runs(warm)[0], grid))  # compile, tabulate
        plan = plan_runs(GenerationSpec(runs=1, test_runs=0, minutes=minutes, seed=0, processing=processing))[0]
        t0 = time.perf_counter()
        n = sum(len(b["time"]) for _, b in simulate_blocks(plan, grid))
        rate[name] = n / (time.perf_counter() - t0)
        print(f"simulate only, 1 process, {name:5s} {rate[name]:8,.0f} frames/s  ({1000 / rate[name]:.2f} ms/frame)")
    sim = rate["ertis"]
    print(f"ertis processing costs {rate['raw'] / sim:.2f}x the raw images")

    with tempfile.TemporaryDirectory() as tmp:
        rates = {}
        for workers in (1, 2):
            t0 = time.perf_counter()
            generate(os.path.join(tmp, f"w{workers}.zarr"), runs=2, test_runs=0, minutes=minutes, seed=0, workers=workers)
            rates[workers] = 2 * args.frames / (time.perf_counter() - t0)
            print(f"simulate+write, {workers} worker(s)  {rates[workers]:8,.0f} frames/s")
        print(f"write overhead (1 worker): {sim / rates[1]:.2f}x the simulation alone; "
              f"2 workers / 1 worker = {rates[2] / rates[1]:.2f}x")
        if args.full:
            frames = 11 * 7500
            for name in ("ertis", "raw"):  # the default, and format 1.0's images as the reference
                t0 = time.perf_counter()
                generate(os.path.join(tmp, f"full-{name}.zarr"), workers=os.cpu_count(), processing=name)
                dt = time.perf_counter() - t0
                size = sum(os.path.getsize(os.path.join(d, f))
                           for d, _, fs in os.walk(os.path.join(tmp, f"full-{name}.zarr")) for f in fs)
                print(f"full default (11 runs x 7500 frames, {os.cpu_count()} workers), {name:5s}: {dt:.1f} s, "
                      f"{frames / dt:,.0f} frames/s, {size / 2**30:.2f} GiB on disk")
    self_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    child_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(f"# peak RSS: parent {self_mb:.0f} MiB, largest worker {child_mb:.0f} MiB "
          "(bounded: a worker holds one 64-frame block, never a whole run)")


if __name__ == "__main__":
    main()
