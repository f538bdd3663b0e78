"""Calibration of the energyscape processing: what each setting does to the images and to the baselines.

    python bench/bench_processing.py                 # 5-minute test runs, 300 windows per setting
    python bench/bench_processing.py --minutes 25 --samples 1000

For each candidate setting, one lab test run (same seed, SNR 5 dB) is simulated and scored:
the share of exactly-black pixels, the median and 99th-percentile pixel, how much of the clean
scene survives (CC of a frame with its noise-free render, the noise ceiling), how a -80 dB burst
frame looks (share of bright pixels, its CC with the clean scene), and persistence / naive / flow
CC and NRMSD at one-shot, AR-3, AR-5 and AR-10 on the same windows. The `ertis` default is chosen
from this table (BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

import numpy as np

from sonarset import open_store
from sonarset.models.eval.evaluate import evaluate
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.sim import generate
from sonarset.sim.sonar import SonarModel
from sonarset.sim.families import load_world

ERTIS = Processing.ertis()
SETTINGS = {
    "raw (delay-and-sum, no post-processing)": Processing.raw(),
    "ertis (default)": ERTIS,
    # the toolbox's filterSize [101, 7] is a sigma in decimated samples x direction columns, 2 deg apart
    "toolbox smoothing 0.385 m x 14 deg": ERTIS.model_copy(update={"smoothing_range_m": 0.385,
                                                                   "smoothing_azimuth_deg": 14.0}),
    "smoothing 0.045 m x 2 deg": ERTIS.model_copy(update={"smoothing_range_m": 0.045}),
    "smoothing 0.09 m x 4 deg": ERTIS.model_copy(update={"smoothing_range_m": 0.09, "smoothing_azimuth_deg": 4.0}),
    "no smoothing": ERTIS.model_copy(update={"smoothing_range_m": 0.0, "smoothing_azimuth_deg": 0.0}),
    "azimuth-mean factor 1.0": ERTIS.model_copy(update={"azimuth_mean_factor": 1.0}),
    "azimuth-mean factor 2.0": ERTIS.model_copy(update={"azimuth_mean_factor": 2.0}),
    "das + ertis post-processing": ERTIS.model_copy(update={"beamformer": "das"}),
}


def burst_look(processing: Processing, grid: SensorGrid, poses: np.ndarray) -> tuple[float, float]:
    """(share of pixels > 0.5, CC with the noise-free scene) of -80 dB burst frames at ``poses``."""
    model, world = SonarModel(grid, processing=processing), load_world("lab", 2026)
    clean, _ = model.render_batch(world, poses, None)
    burst, _ = model.render_batch(world, poses, np.random.default_rng(1), snr_db=np.full(len(poses), -80.0))
    # a constant frame (raw images saturate in a burst) shares nothing with the scene: CC 0
    ccs = [np.corrcoef(b.ravel(), c.ravel())[0, 1] if b.std() > 0 else 0.0 for b, c in zip(burst, clean) if c.std() > 0]
    return float((burst > 0.5).mean()), float(np.mean(ccs))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=5.0, help="length of each setting's test run")
    ap.add_argument("--samples", type=int, default=300, help="windows scored per setting")
    args = ap.parse_args()
    grid = SensorGrid.default()
    print(f"# bench_processing  {platform.node()}  {os.cpu_count()} cores  python {platform.python_version()}  "
          f"{time.strftime('%Y-%m-%d')}: lab test run seed 2026, {args.minutes:g} min, {args.samples} windows")
    head = ("| setting | black px | median / p99 px | ceiling CC | burst: px > 0.5, CC | "
            "CC persistence / naive / flow @1,3,5,10 | NRMSD naive / flow @1,3,5,10 |")
    print(head)
    print("|" + "---|" * 7)
    with tempfile.TemporaryDirectory() as tmp:
        for label, proc in SETTINGS.items():
            path = os.path.join(tmp, f"{len(os.listdir(tmp))}.zarr")
            generate(path, runs=0, test_runs=1, minutes=args.minutes, seed=2026, processing=proc, workers=1)
            store = open_store(path)
            images = store.run("test_000")["images"][:].astype(np.float32)
            res = evaluate(store, ["persistence", "naive", "flow"], samples=args.samples, seed=0, ceiling=True)
            s = res.summary()
            poses = store.run("test_000")["pose"][::50]
            burst_px, burst_cc = burst_look(proc, grid, poses)

            def row(m, k, s=s, res=res):
                return "/".join(f"{s[m][str(h)][k]['mean']:.2f}" for h in res.horizons)

            print(f"| {label} | {(images == 0).mean():.0%} | {np.median(images):.2f} / {np.percentile(images, 99):.2f} | "
                  f"{s['ceiling']['1']['cc']['mean']:.3f} | {burst_px:.0%}, {burst_cc:+.2f} | "
                  f"{row('persistence', 'cc')} ; {row('naive', 'cc')} ; {row('flow', 'cc')} | "
                  f"{row('naive', 'nrmsd')} ; {row('flow', 'nrmsd')} |", flush=True)


if __name__ == "__main__":
    main()
