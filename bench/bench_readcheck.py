"""What the read path's checks cost: checked loading against the same load without checks.

    python bench/bench_readcheck.py [--runs 2] [--frames 1500] [--repeats 5] [--table]

For a store of synthetic energyscapes on the default 200 x 90 grid, in both image profiles
('ertis': sparse frames, lz4 without shuffle; 'raw': a noise floor, lz4 with bitshuffle), loaded
as float16 (train) and float32 (eval), it measures in CPU time (best of interleaved repeats: the
machine may be shared):

* load, unchecked: the loader's slab reads straight from zarr, as before the checks existed;
* load, checked: ``FrameBank.from_store`` (what eval and train use). The difference of these two
  carries the machine's noise (page faults of a fresh bank, other processes' cache traffic) and
  cannot resolve a few milliseconds; the next columns measure the checks themselves:
* open check: ``open_store(check=True)``, the structural checks at open (once per command);
* chunk headers: every chunk's header against its size, for all the chunks the loader reads;
* copy / check + copy: the decoded slabs copied into a bank, plain, and as ``Run.read(out=...)``
  does it: a chunk's worth at a time, checked (images in [0, 1]; velocity and time finite, time
  spacing against the frame rate, commands within the rig's limits), then copied from the cache;
* checks / load: chunk headers plus (check + copy - copy), as a share of the unchecked load
  (goal: < 5 %).

``--table`` also runs the corruption suite (tests/test_corruption.py, ~40 s) and prints its
kinds x commands table.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_windows import synthetic_run  # bench/ is the script's folder, first on sys.path
from sonarset.format.arrays import frame_interval_problems, value_problems
from sonarset.store.integrity import ChunkChecker
from sonarset.format.plausibility import command_problems
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.store.store import create_store, open_store
from sonarset.windows import FrameBank


def load_unchecked(store, dtype) -> np.ndarray:
    """The loader as it was before the checks: the same slabs, straight from zarr."""
    names = store.runs()
    runs = [store.run(n) for n in names]
    sizes = [r.n_frames for r in runs]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    images = np.empty((int(offsets[-1]), *store.grid.shape), dtype=dtype)
    velocity = np.empty((int(offsets[-1]), 2), dtype=np.float32)
    for j, run in enumerate(runs):
        lo, hi = int(offsets[j]), int(offsets[j + 1])
        arr = run.array("images")
        step = arr.chunks[0] * 16
        for s in range(0, hi - lo, step):
            e = min(hi - lo, s + step)
            images[lo + s:lo + e] = arr[s:e]
        velocity[lo:hi] = run.array("velocity")[:]
        run.array("time")[:]
    return images


def header_time(path: str, repeats: int) -> float:
    """CPU seconds of the chunk-header checks of everything the loader reads (arrays open)."""
    store = open_store(path)
    checkers = [ChunkChecker(store.run(n).array(k)) for n in store.runs() for k in ("images", "velocity", "time")]
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        for c in checkers:
            assert not c.first_problem()
        times.append(time.process_time() - t0)
    return min(times)


def value_check_time(path: str, dtype, repeats: int) -> tuple[float, float]:
    """(CPU seconds to copy the decoded slabs into a bank, CPU seconds to check and copy them as
    ``Run.read(out=...)`` does: a chunk's worth at a time, checked, then copied from the cache).
    The same decoded data, so the difference is what the value checks add; the small arrays'
    checks (velocity, time, commands) are added to the second."""
    store = open_store(path)
    runs = [store.run(n) for n in store.runs()]
    slabs = []
    for r in runs:
        arr = r.array("images")
        step = arr.chunks[0] * 16
        slabs += [arr[s:min(arr.shape[0], s + step)] for s in range(0, arr.shape[0], step)]
    small = [(r.array("velocity")[:], r.array("time")[:]) for r in runs]
    bank = np.empty((sum(len(b) for b in slabs), *store.grid.shape), dtype)
    bank[:] = 0  # touch every page once, so that neither timing pays the page faults
    chunk = runs[0].array("images").chunks[0]
    rig, rate = store.rig, store.attrs.frame_rate_hz

    def copy() -> None:
        lo = 0
        for b in slabs:
            bank[lo:lo + len(b)] = b
            lo += len(b)

    def check_and_copy() -> None:
        lo = 0
        for b in slabs:
            for i in range(0, len(b), chunk):
                piece = b[i:i + chunk]
                assert not value_problems("images", piece, i)
                bank[lo + i:lo + i + len(piece)] = piece
            lo += len(b)
        for v, t in small:
            assert not value_problems("velocity", v) and not value_problems("time", t)
            assert not command_problems(v, rig) and not frame_interval_problems(t, rate)

    plain, checked = [], []
    for _ in range(repeats):
        for fn, times in ((copy, plain), (check_and_copy, checked)):
            t0 = time.process_time()
            fn()
            times.append(time.process_time() - t0)
    return min(plain), min(checked)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--table", action="store_true", help="also print the corruption suite's table")
    args = ap.parse_args()
    grid = SensorGrid.default()
    print(f"# bench_readcheck  {platform.node()}  {platform.processor() or platform.machine()}  "
          f"{os.cpu_count()} cores  python {platform.python_version()}")
    print(f"# grid {grid.shape}, {args.runs} runs x {args.frames} frames, float16 on disk; CPU time, "
          f"best of {args.repeats} interleaved repeats")
    print("| images | loaded as | load, unchecked | load, checked | open check | chunk headers | copy | "
          "check + copy | checks / load |")
    print("|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for profile in ("ertis", "raw"):
            sparse = profile == "ertis"
            path = os.path.join(tmp, f"{profile}.zarr")
            store = create_store(path, grid, processing=Processing.named(profile))
            for j in range(args.runs):
                store.write_run(f"run_{j:03d}", **synthetic_run(args.frames, grid, j, sparse))
            for dtype in (np.float16, np.float32):  # train keeps float16, eval converts to float32
                load_unchecked(open_store(path), dtype)  # warm the page cache
                plain, checked, opened = [], [], []
                for _ in range(args.repeats):  # interleaved, so that drifts hit both alike
                    t0 = time.process_time()
                    load_unchecked(open_store(path), dtype)
                    plain.append(time.process_time() - t0)
                    t0 = time.process_time()
                    s = open_store(path, check=True)
                    opened.append(time.process_time() - t0)
                    t0 = time.process_time()
                    FrameBank.from_store(s, image_dtype=dtype)
                    checked.append(time.process_time() - t0)
                base, chk = min(plain), min(checked)
                headers = header_time(path, args.repeats)
                copy, check_copy = value_check_time(path, dtype, args.repeats)
                cost = headers + max(0.0, check_copy - copy)
                print(f"| {profile} | {np.dtype(dtype).name} | {base * 1e3:.0f} ms | {chk * 1e3:.0f} ms | "
                      f"{min(opened) * 1e3:.0f} ms | {headers * 1e3:.1f} ms | {copy * 1e3:.1f} ms | "
                      f"{check_copy * 1e3:.1f} ms | **{cost / base:.1%}** |")
    if args.table:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
        from tests.test_corruption import GRID, KINDS, check_kind, table
        from sonarset.sim import generate

        with tempfile.TemporaryDirectory() as tmp:
            base = Path(tmp) / "base.zarr"
            generate(base, runs=1, test_runs=1, minutes=0.5, seed=3, workers=1, grid=GRID)
            res = {}
            for i, kind in enumerate(KINDS):
                got = check_kind(kind, base, Path(tmp) / f"k{i}")
                res[kind.name] = {c: s if p is None else f"BAD: {p}" for c, (s, p) in got.items()}
            print()
            print(table(res))


if __name__ == "__main__":
    main()
