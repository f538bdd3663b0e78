"""Frames per second of export-bag and import-bag, on the default 200 x 90 grid.

    python bench/bench_bag.py [--minutes 2] [--repeats 3]

A simulated run is exported to MCAP (export_bag) and imported back (import_bag); the reference in
the same run is the floor any importer pays: rosbags iterating the same file's messages without
decoding them, and with decoding them (its deserializer, what import_bag's reader calls).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sonarset import open_store  # noqa: E402
from sonarset.ingest.bag import export_bag, import_bag  # noqa: E402
from sonarset.sim import generate  # noqa: E402


def best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    from rosbags.highlevel import AnyReader

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        generate(work / "sim.zarr", runs=1, test_runs=0, minutes=args.minutes, seed=1, workers=1)
        store = open_store(work / "sim.zarr")
        n = store.run("run_000").n_frames
        bag = work / "run.mcap"

        def export():
            bag.unlink(missing_ok=True)
            export_bag(store, bag)

        def import_():
            shutil.rmtree(work / "back.zarr", ignore_errors=True)
            import_bag(bag, work / "back.zarr")

        def iterate(decode: bool):
            def go():
                with AnyReader([bag]) as reader:
                    conns = [c for c in reader.connections if c.topic == "/sonar/image"]
                    for conn, _, raw in reader.messages(connections=conns):
                        if decode:
                            reader.deserialize(raw, conn.msgtype)
            return go

        t_export = best(export, args.repeats)
        t_import = best(import_, args.repeats)
        t_iter = best(iterate(False), args.repeats)
        t_decode = best(iterate(True), args.repeats)
        print(f"{time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores; {n} frames of {store.grid.describe()}, "
              f"MCAP {bag.stat().st_size / 2**20:.1f} MiB, best of {args.repeats}")
        print("| step | s | frames/s | vs reading the images' messages |")
        print("|---|---|---|---|")
        for name, t in (("rosbags: iterate the image messages", t_iter), ("rosbags: iterate + deserialize", t_decode),
                        ("import_bag (checked, written to a new store)", t_import),
                        ("export_bag (images, commands, odometry, tf)", t_export)):
            print(f"| {name} | {t:.2f} | {n / t:,.0f} | {t / t_iter:.1f}x |")


if __name__ == "__main__":
    main()
