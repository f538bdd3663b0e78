"""Time and file size of ``sonarset view`` for a whole run, with one model, against recording the
run alone (the reference in the same run).

    python bench/bench_view.py [--minutes 25] [--model flow]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sonarset import open_store  # noqa: E402
from sonarset.models.view import record_run  # noqa: E402
from sonarset.sim import generate  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=25.0)
    ap.add_argument("--model", default="flow")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        generate(work / "sim.zarr", runs=0, test_runs=1, minutes=args.minutes, seed=1)
        store = open_store(work / "sim.zarr")
        n = store.run("test_000").n_frames
        print(f"{time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores; a {args.minutes:g}-minute run, {n} frames of "
              f"{store.grid.describe()}")
        print("| recording | s | frames/s | file MiB | peak RSS MiB (process so far) |")
        print("|---|---|---|---|---|")
        for label, models in (("the run alone", []), (f"with {args.model}, horizon 1", [args.model])):
            t0 = time.perf_counter()
            path = record_run(store, "test_000", work / "v.rrd", models=models)
            dt = time.perf_counter() - t0
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            print(f"| {label} | {dt:.1f} | {n / dt:,.0f} | {path.stat().st_size / 2**20:.0f} | {peak:.0f} |")


if __name__ == "__main__":
    main()
