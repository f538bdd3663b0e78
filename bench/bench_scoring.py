"""The cost of scoring one predicted image: echo detection and CC + NRMSD, against plain references.

    python bench/bench_scoring.py [--minutes 2] [--rounds 5]

Frames come from a freshly simulated run on the default grid (the demo's images). Echo detection
is timed on its sparse path (candidates >= level compared with their windows, plateaus grouped on a
graph of touching maxima) and on a maximum filter over the whole batch, the plain reference,
which it must equal; CC and NRMSD from one pass against the two textbook formulas. The shares of
candidate pixels at which the sparse path stops paying come from smoothed random images of rising
density. Each figure is the best of ``--rounds`` rounds in which the variants take turns.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

import sonarset.scoring.echoes as echoes
from sonarset.scoring.echoes import EchoMatching, find_echoes
from sonarset.scoring.metrics import cc_and_nrmsd
from sonarset.format.attrs import SensorGrid


def textbook_cc_nrmsd(p: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = p.reshape(len(p), -1).astype(np.float64)
    m = m.reshape(len(m), -1).astype(np.float64)
    pc, mc = p - p.mean(1, keepdims=True), m - m.mean(1, keepdims=True)
    cc = (pc * mc).sum(1) / np.sqrt((pc * pc).sum(1) * (mc * mc).sum(1))
    return cc, np.linalg.norm(p - m, axis=1) / np.linalg.norm(m, axis=1)


def per_image_ms(fn, batches: list, n_images: int, rounds: int) -> float:
    best = np.inf
    for _ in range(rounds):
        t = time.perf_counter()
        for b in batches:
            fn(b)
        best = min(best, time.perf_counter() - t)
    return 1e3 * best / n_images


DEFAULT_SHARE = echoes._SPARSE_SHARE


def detection(x: np.ndarray, grid: SensorGrid, sparse: bool):
    echoes._SPARSE_SHARE = 1.0 if sparse else 0.0
    try:
        return find_echoes(x, grid)
    finally:
        echoes._SPARSE_SHARE = DEFAULT_SHARE


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    from sonarset.models.demo import simulate_fresh_run
    from sonarset.windows import FrameBank

    print(f"machine: {platform.processor() or platform.machine()}, {platform.python_version()}")
    with tempfile.TemporaryDirectory() as tmp:
        store = simulate_fresh_run(Path(tmp) / "run.zarr", minutes=args.minutes, seed=7)
        grid = store.grid
        images = FrameBank.from_store(store, split="test", image_dtype=np.float32).images
    level = EchoMatching().level
    batches = [images[lo:lo + 64] for lo in range(0, len(images) - 64, 64)]
    n = sum(map(len, batches))
    print(f"{n} frames of {grid.n_range} x {grid.n_azimuth}, "
          f"{100 * (images >= level).mean():.1f}% of pixels >= {level:g}")

    a, b = detection(images[:512], grid, True), detection(images[:512], grid, False)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.range_m, b.range_m), "the paths disagree"
    t_sparse = per_image_ms(lambda x: detection(x, grid, True), batches, n, args.rounds)
    t_filter = per_image_ms(lambda x: detection(x, grid, False), batches, n, args.rounds)
    print(f"echo detection: sparse {t_sparse:.3f} ms/image, maximum filter {t_filter:.3f} "
          f"(reference/sparse {t_filter / t_sparse:.1f}x)")

    pairs = [(b[:-1], b[1:]) for b in batches]
    got, want = cc_and_nrmsd(*pairs[0]), textbook_cc_nrmsd(*pairs[0])
    err = max(np.nanmax(np.abs(got[0] - want[0])), np.nanmax(np.abs(got[1] - want[1])))
    t_one = per_image_ms(lambda pm: cc_and_nrmsd(*pm), pairs, n - len(pairs), args.rounds)
    t_ref = per_image_ms(lambda pm: textbook_cc_nrmsd(*pm), pairs, n - len(pairs), args.rounds)
    print(f"CC + NRMSD: one pass {t_one:.3f} ms/image, textbook {t_ref:.3f} (ratio {t_ref / t_one:.1f}x), "
          f"max abs difference {err:.1e}")

    rng = np.random.default_rng(0)
    smooth = ndimage.gaussian_filter(rng.random((64, *grid.shape)).astype(np.float32), (0, 3, 2))
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min())
    print("share of candidates | sparse ms/image | filter ms/image")
    for q in (0.98, 0.95, 0.9, 0.8, 0.7, 0.6):
        x = np.clip(smooth - np.quantile(smooth, q) + level, 0, 1).astype(np.float32)
        s = per_image_ms(lambda y: detection(y, grid, True), [x], len(x), args.rounds)
        f = per_image_ms(lambda y: detection(y, grid, False), [x], len(x), args.rounds)
        print(f"{100 * (x >= level).mean():5.1f}% | {s:.3f} | {f:.3f}")


if __name__ == "__main__":
    main()
