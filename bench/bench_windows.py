"""Window loading throughput: SonarSet store -> batches, against references in the same run.

    python bench/bench_windows.py [--runs 2] [--frames 7500] [--batch 64]

Prints, for the default 200 x 90 grid:
  * write: frames/s into a local store (reference writer, float16, Blosc zstd);
  * load: frames/s decoding the store into the in-memory FrameBank (one pass, each chunk once);
  * gather: windows/s of shuffled batches from the bank (the training path), next to
  * numpy: windows/s of the same gather on a plain in-memory NumPy array (the reference);
  * torch: windows/s through SonarWindowDataset + make_loader (float32 tensors);
  * lazy zarr: windows/s reading every window straight from zarr, no cache (why we cache).
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import tempfile
import time

import numpy as np

from sonarset.format.attrs import SensorGrid
from sonarset.store.store import create_store, open_store
from sonarset.windows import N_IN, FrameBank, WindowIndex, iter_batches


def synthetic_run(T: int, grid: SensorGrid, seed: int, sparse: bool = False) -> dict[str, np.ndarray]:
    """Energyscape-like frames: a few bright drifting blobs, on a low noise floor (raw images) or,
    ``sparse``, on black (ertis images)."""
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


def rate(n: int, seconds: float) -> str:
    return f"{n / seconds:12,.0f}/s"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--frames", type=int, default=7500)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--horizon", type=int, default=1)
    args = ap.parse_args()
    grid = SensorGrid.default()
    print(f"# bench_windows  {platform.node()}  {platform.processor() or platform.machine()}  "
          f"{os.cpu_count()} cores  python {platform.python_version()}")
    print(f"# grid {grid.shape}, {args.runs} runs x {args.frames} frames, float16, batch {args.batch}, H={args.horizon}")
    data = [synthetic_run(args.frames, grid, s) for s in range(args.runs)]
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.zarr")
        t0 = time.perf_counter()
        store = create_store(path, grid)
        for j, d in enumerate(data):
            store.write_run(f"run_{j:03d}", **d)
        t_write = time.perf_counter() - t0
        n_frames = args.runs * args.frames
        size = store.nbytes_stored()
        print(f"write      {rate(n_frames, t_write)} frames   ({size / 2**20:.0f} MiB on disk, "
              f"{n_frames * grid.shape[0] * grid.shape[1] * 2 / size:.1f}x compression)")

        store = open_store(path)
        t0 = time.perf_counter()
        bank = FrameBank.from_store(store)
        t_load = time.perf_counter() - t0
        print(f"load       {rate(n_frames, t_load)} frames   ({bank.nbytes / 2**20:.0f} MiB in memory, {t_load:.2f} s)")

        index = WindowIndex.build(bank, N_IN, args.horizon)
        n = len(index)
        t0 = time.perf_counter()
        got = sum(len(b) for b in iter_batches(bank, index, args.batch, seed=0))
        t_gather = time.perf_counter() - t0
        assert got == n
        print(f"gather     {rate(n, t_gather)} windows (shuffled batches from the bank; one epoch = {n} windows)")
        print(f"  +load    {rate(n, t_gather + t_load)} windows (first epoch including the store decode)")

        # Reference: the same windows gathered from a plain NumPy array, no sonarset code.
        frames = np.concatenate([d["images"] for d in data])
        vel = np.concatenate([d["velocity"] for d in data])
        order = np.random.default_rng(0).permutation(index.starts)
        span = np.arange(index.span)
        t0 = time.perf_counter()
        for lo in range(0, n, args.batch):
            rows = order[lo:lo + args.batch, None] + span
            _ = frames[rows], vel[rows]
        t_ref = time.perf_counter() - t0
        print(f"numpy      {rate(n, t_ref)} windows (reference; sonarset gather / numpy = {t_ref / t_gather:.2f})")

        try:
            from sonarset.torchdata import SonarWindowDataset, make_loader

            ds = SonarWindowDataset(bank, index)
            t0 = time.perf_counter()
            got = sum(b["frames"].shape[0] for b in make_loader(ds, args.batch, seed=0))
            t_torch = time.perf_counter() - t0
            print(f"torch      {rate(got, t_torch)} windows (DataLoader, float32 tensors)")
        except ImportError:
            print("torch      not installed")

        run = store.run("run_000")
        m = 300
        starts = np.random.default_rng(1).integers(0, run.n_frames - 4, m)
        t0 = time.perf_counter()
        for s in starts:
            _ = run.images[int(s):int(s) + 4], run.velocity[int(s):int(s) + 4]
        t_lazy = time.perf_counter() - t0
        print(f"lazy zarr  {rate(m, t_lazy)} windows (no cache: every window decodes its chunks again)")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"# peak RSS {peak:.0f} MiB")


if __name__ == "__main__":
    main()
