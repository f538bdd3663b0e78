"""The envelope of DMAS3-CF: the column through an isolated target, and the round trip, per detector.

    python bench/bench_envelope.py [--frames 6]

* Point target (unit, 1.5 m, +30 deg; 0.5-3.5 m x 60 directions; ertis post-processing, the target
  at full scale): the largest pixel of its column more than 0.3 m from its range, for 450 kHz and
  200 kHz recordings of the 80->20 kHz and 25->50 kHz sweeps. 0 is the floor.
* Round trip on the default grid (a simulated lab test run, seed 3, SNR 40 dB): (a) as
  ``tests/test_import_raw.py`` does it, one noise-free realization a frame against the run's images
  (which carry the noise floor); (b) like for like, the noise-free scenes, 4 realizations a frame,
  energy-averaged, against the fast model's noise-free images. Mean 2D correlation over frames.

Detectors: ``analytic`` (|hilbert|, what import-raw did before issue 24), ``rectify`` (the toolbox's
order; the default now), ``square``. Delay-and-sum is always ``analytic`` (its output is the
analytic signal), shown for reference.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import tempfile
from pathlib import Path

import numpy as np
from scipy import fft as sfft

from sonarset import open_store
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.sim import generate
from sonarset.sensor.beamform import SignalBeamformer
from sonarset.sensor.ertis import read_layout_csv, sweep
from sonarset.sensor.exact import DETECTORS, steering_projection
from sonarset.sim.families import load_world
from sonarset.sim.reference import microphone_signals
from sonarset.sim.robot import sensor_pose
from sonarset.sim.sonar import SonarModel, visible_echoes

CASES = [("das", "analytic")] + [("dmas3-cf", d) for d in DETECTORS]


def cc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def point_column(fs: float, f0: float, f1: float, beamformer: str, detector: str) -> float:
    grid = SensorGrid(range_min_m=0.5, range_max_m=3.5, n_range=120, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=60)
    emitted = sweep(fs, f0, f1, 0.0025)
    n = int((2 * grid.range_max_m / 343 + 0.004) * fs)
    proj = steering_projection(read_layout_csv(), np.array([math.radians(30)]))[0]
    N = sfft.next_fast_len(n + len(emitted), real=True)
    f = sfft.rfftfreq(N, 1 / fs)
    X = sfft.rfft(emitted, N)[None] * np.exp(-2j * np.pi * f[None] * ((2 * 1.5 - proj) / 343.0)[:, None])
    sig = sfft.irfft(X, N)[:, :n].astype(np.float32)
    amp = SignalBeamformer(grid, read_layout_csv(), emitted, fs, n, beamformer, detector=detector).amplitude(sig)
    px = SonarModel(grid, processing=Processing.ertis().model_copy(update={"beamformer": beamformer})).pixels(
        amp / amp.max())
    col = np.argmin(np.abs(grid.azimuth_centres() - math.radians(30)))
    return float(px[np.abs(grid.range_centres() - 1.5) > 0.3, col].max())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=6)
    args = ap.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    print("\npoint target: largest pixel of its column away from its range (0 = the floor)")
    configs = [(450e3, 80e3, 20e3), (450e3, 25e3, 50e3), (200e3, 80e3, 20e3), (200e3, 25e3, 50e3)]
    print("  " + " " * 20 + "".join(f"{fs / 1e3:.0f} kHz {a / 1e3:.0f}->{b / 1e3:.0f}  " for fs, a, b in configs))
    for bf, det in CASES:
        print(f"  {bf:9s} {det:9s} " + "".join(f"{point_column(fs, a, b, bf, det):17.4f}" for fs, a, b in configs))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        runs = {}
        for profile in ("ertis", "raw"):
            generate(tmp / f"{profile}.zarr", runs=0, test_runs=1, minutes=args.frames * 0.2 / 60, seed=3, workers=1,
                     snr_db=40.0, processing=profile)
            runs[profile] = open_store(tmp / f"{profile}.zarr").run("test_000")
        run = runs["ertis"]
        grid, src = run.store.grid, run.attrs.source
        world = load_world(src["world"], int(src["world_seed"]))
        echoes = [visible_echoes(world, sensor_pose(p), grid.range_max_m + 0.1) for p in run["pose"][:]]
        one = [microphone_signals(e, grid, seed=1_000_003 + k)[0] for k, e in enumerate(echoes)]
        four = [microphone_signals(e, grid, seed=k, realizations=4) for k, e in enumerate(echoes)]
        print(f"\nround trip, {len(echoes)} frames, mean (min) 2D correlation:")
        print("  beamformer detector  profile  (a) one realization vs the run   (b) like for like")
        for bf, det in CASES:
            profile = "raw" if bf == "das" else "ertis"
            proc = Processing.named(profile)
            model = SonarModel(grid, processing=proc)
            px = (lambda a, model=model: model.pixels(a)) if proc.post_processed else (lambda a, model=model: model.encode(a * a))
            sb = SignalBeamformer(grid, read_layout_csv(), sweep(200e3), 200e3, one[0].shape[1], bf, detector=det)
            sim = runs[profile].images[:].astype(np.float32)
            a = [cc(px(sb.amplitude(s)), sim[k]) for k, s in enumerate(one)]
            b = [cc(px(np.sqrt(np.mean([sb.amplitude(x) ** 2 for x in s], 0)).astype(np.float32)),
                    px(model.amplitude(e, 1)[0][0])) for s, e in zip(four, echoes)]
            print(f"  {bf:9s}  {det:9s} {profile:6s}   {np.mean(a):.3f} ({np.min(a):.3f})"
                  f"                  {np.mean(b):.3f} ({np.min(b):.3f})")


if __name__ == "__main__":
    main()
