"""What the read path's checks cost: checked loading against the same load without checks.

    python bench/bench_readcheck.py [--runs 2] [--frames 1500] [--repeats 5] [--table]

For a store of synthetic energyscapes on the default 200 x 90 grid, in both image profiles
('ertis': sparse frames, lz4 without shuffle; 'raw': a noise floor, lz4 with bitshuffle), loaded
as float16 (train) and float32 (eval), it measures in CPU time (best of interleaved repeats: the
machine may be shared):

* load, unchecked: the loader's slab reads straight from zarr, as before the checks existed;
* load, checked: ``FrameBank.from_store`` (what eval and train use), and its difference;
* open check: ``open_store(check=True)``, the structural checks at open (once per command);
* chunk headers / value checks: the checks alone, on open arrays and decoded data: every chunk's
  header against its size, and every value the loader reads (images in [0, 1], velocity and time
  finite, time spacing against the frame rate, commands within the rig's limits);
* checks / load: their sum as a share of the unchecked load (goal: < 5 %). The end-to-end
  difference carries the machine's noise; this share does not.

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

from sonarset.arrays import frame_interval_problem, value_problem
from sonarset.integrity import ChunkChecker
from sonarset.plausibility import command_problems
from sonarset.schema import Processing, SensorGrid
from sonarset.store import create_store, open_store
from sonarset.windows import FrameBank


def synthetic_run(T: int, grid: SensorGrid, seed: int, sparse: bool) -> dict[str, np.ndarray]:
    """Energyscape-like frames: a few bright drifting blobs, on black (ertis) or on a noise floor (raw)."""
    rng = np.random.default_rng(seed)
    R, A = grid.shape
    r, a = np.meshgrid(np.arange(R), np.arange(A), indexing="ij")
    images = np.empty((T, R, A), np.float16)
    centres = rng.uniform([0, 0], [R, A], size=(6, 2))
    for k in range(T):
        img = np.zeros((R, A)) if sparse else rng.uniform(0, 0.25, (R, A))
        for cr, ca in centres + k * np.array([-0.3, 0.05]):
            blob = 0.9 * np.exp(-((r - cr % R) ** 2 / 2.0 + (a - ca % A) ** 2 / 3.0))
            img = np.maximum(img, np.where(blob > 0.05, blob, 0.0) if sparse else blob)
        images[k] = img
    velocity = np.c_[rng.uniform(-0.3, 0.3, T), rng.uniform(-1, 1, T)].astype(np.float32)
    return {"images": images, "velocity": velocity, "time": np.arange(T) * 0.2}


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


def parts(store, repeats: int) -> dict[str, float]:
    """CPU seconds of each check alone (best of ``repeats``): the chunk headers (arrays already
    open), and the value checks of everything the loader reads (data already decoded)."""
    runs = [store.run(n) for n in store.runs()]
    checkers = [ChunkChecker(r.array(k)) for r in runs for k in ("images", "velocity", "time")]
    blocks = []
    for r in runs:
        arr = r.array("images")
        step = arr.chunks[0] * 16
        blocks += [("images", arr[s:min(arr.shape[0], s + step)]) for s in range(0, arr.shape[0], step)]
    small = [(r.array("velocity")[:], r.array("time")[:]) for r in runs]

    def values() -> None:
        for key, b in blocks:
            assert value_problem(key, b) is None
        for v, t in small:
            assert value_problem("velocity", v) is None and value_problem("time", t) is None
            assert not command_problems(v, store.rig) and frame_interval_problem(t, store.attrs.frame_rate_hz) is None

    def headers() -> None:
        for c in checkers:
            assert c.first_problem() is None

    return {"chunk headers": best(headers, repeats), "values": best(values, repeats)}


def best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


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
    print("| images | loaded as | load, unchecked | load, checked | open check | chunk headers | value checks | checks / load |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for profile in ("ertis", "raw"):
            sparse = profile == "ertis"
            path = os.path.join(tmp, f"{profile}.zarr")
            store = create_store(path, grid, processing=Processing.named(profile))
            for j in range(args.runs):
                store.write_run(f"run_{j:03d}", **synthetic_run(args.frames, grid, j, sparse))
            for dtype in (np.float16, np.float32):  # train keeps float16, eval converts to float32
                load_unchecked(open_store(path), dtype)  # warm the page cache
                # CPU time, the best of interleaved repeats: this machine is shared, and another
                # process's load only ever adds wall time
                plain, checked, opened = [], [], []
                for _ in range(args.repeats):
                    s = open_store(path)
                    t0 = time.process_time()
                    load_unchecked(s, dtype)
                    plain.append(time.process_time() - t0)
                    t0 = time.process_time()
                    s = open_store(path, check=True)
                    opened.append(time.process_time() - t0)
                    t0 = time.process_time()
                    FrameBank.from_store(s, image_dtype=dtype)
                    checked.append(time.process_time() - t0)
                p = parts(open_store(path), args.repeats)
                base, chk = min(plain), min(checked)
                cost = p["chunk headers"] + p["values"]
                print(f"| {profile} | {np.dtype(dtype).name} | {base * 1e3:.0f} ms | {chk * 1e3:.0f} ms "
                      f"({(chk - base) / base:+.1%}) | {min(opened) * 1e3:.0f} ms | {p['chunk headers'] * 1e3:.1f} ms | "
                      f"{p['values'] * 1e3:.1f} ms | **{cost / base:.1%}** |")
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
