"""import-raw throughput, memory and fidelity, against a simple reference in the same run.

    python bench/bench_import_raw.py [--frames 64] [--workers 2] [--round-trip 6]

On the default 200 x 90 grid, eRTIS layout (32 microphones), 200 kHz recordings of the 25->50 kHz
sweep (7131 samples a channel, what a 5 m range needs):

  * end to end: ``import_raw`` of a ``--frames`` measurement recording (validation pass, beamforming
    with ``--workers`` threads, writing), measurements/s and peak numpy memory, for DAS ('raw'
    profile) and DMAS3-CF ('ertis' profile); goal >= 5 measurements/s on 2 cores;
  * the fast beamformer alone, one thread, CPU ms a measurement;
  * the simple reference: the exact path (frequency-domain steering, one inverse FFT per azimuth,
    or per azimuth and microphone for DMAS3) on the same signals, CPU ms a measurement, and the 2D
    correlation of its amplitudes with the fast path's;
  * round trip: a simulated test run (SNR 40 dB: the noise floor) rendered to microphone signals by
    the signal-level reference, imported, and compared frame by frame with the simulator's images
    (2D correlation), for both profiles.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from sonarset import open_store
from sonarset.ingest.raw import import_raw
from sonarset.format.attrs import SensorGrid
from sonarset.sim import generate
from sonarset.sensor.beamform import SignalBeamformer
from sonarset.sensor.ertis import read_layout_csv, sweep
from sonarset.sim.reference import write_raw_recording

PROFILES = {"das": "raw", "dmas3-cf": "ertis"}


def cc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--round-trip", type=int, default=6, help="frames of the round trip (0: skip)")
    ap.add_argument("--exact", type=int, default=1, help="measurements through the exact path (0: skip)")
    args = ap.parse_args()
    grid = SensorGrid.default()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f} (other jobs share the cores when above 0), {args.workers} worker thread(s); "
          f"grid {grid.describe()}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # a scene: a few frames of a simulated lab run, tiled (the cost does not depend on the echoes)
        t = time.perf_counter()
        n_rt = max(args.round_trip, 3)
        generate(tmp / "sim.zarr", runs=0, test_runs=1, minutes=n_rt * 0.2 / 60, seed=3, workers=1, snr_db=40.0,
                 processing="ertis")
        run = open_store(tmp / "sim.zarr").run("test_000")
        raw = write_raw_recording(run, tmp / "raw", seed=1)
        print(f"rendered {n_rt} frames of microphone signals with the signal-level reference in "
              f"{time.perf_counter() - t:.1f} s")
        sig = np.load(raw / "signals.npy")
        reps = -(-args.frames // len(sig))
        big = tmp / "big"
        big.mkdir()
        tiled = np.lib.format.open_memmap(big / "signals.npy", "w+", np.float32, (args.frames, *sig.shape[1:]))
        tiled[:] = np.tile(sig, (reps, 1, 1))[:args.frames]
        tiled.flush()
        del tiled
        np.save(big / "velocity.npy", np.tile(np.load(raw / "velocity.npy"), (reps, 1))[:args.frames])
        np.save(big / "time.npy", np.arange(args.frames) * 0.2)
        (big / "recording.json").write_text((raw / "recording.json").read_text().replace('"split": "test"',
                                                                                          '"split": "train"'))
        size = args.frames * sig[0].nbytes
        print(f"recording: {args.frames} measurements x {sig.shape[1]} channels x {sig.shape[2]} samples "
              f"(float32, {size / 1e6:.0f} MB)")

        print("\nend to end (validate, beamform, post-process, write):")
        for bf, profile in PROFILES.items():
            out = tmp / f"e2e_{bf}.zarr"
            tracemalloc.start()
            t, c = time.perf_counter(), time.process_time()
            import_raw(big, out, processing=profile, workers=args.workers)
            dt, cpu = time.perf_counter() - t, time.process_time() - c
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            # CPU time of all the process's threads: what the import costs, whoever else runs
            print(f"  {bf:9s} ({profile:5s}) {args.frames / dt:6.1f} measurements/s wall clock ({dt:.1f} s); "
                  f"{cpu / args.frames * 1e3:.0f} CPU ms a measurement = {args.workers * args.frames / cpu:.1f}/s on "
                  f"{args.workers} free cores; peak numpy memory {peak / 1e6:.0f} MB (recording {size / 1e6:.0f} MB)")

        print("\nbeamforming one measurement, one thread: fast path vs the simple reference (exact path):")
        for bf in PROFILES:
            sb = SignalBeamformer(grid, read_layout_csv(), sweep(200e3), 200e3, sig.shape[2], bf)
            sb.amplitude(sig[0])
            # CPU time: on a shared machine wall-clock one-thread times measure the other jobs
            t = time.process_time()
            for k in range(8):
                fast = sb.amplitude(sig[k % len(sig)])
            t_fast = (time.process_time() - t) / 8
            line = f"  {bf:9s} fast {t_fast * 1e3:7.1f} CPU ms"
            if args.exact:
                t = time.process_time()
                for k in range(args.exact):
                    exact = sb.exact_amplitude(sig[k % len(sig)])
                t_exact = (time.process_time() - t) / args.exact
                fast = sb.amplitude(sig[(args.exact - 1) % len(sig)])
                line += (f"   exact {t_exact * 1e3:8.1f} CPU ms   speed-up x{t_exact / t_fast:.0f}   2D correlation of "
                         f"amplitudes {cc(fast, exact):.4f}, peak ratio {fast.max() / exact.max():.4f}")
            print(line)

        if args.round_trip:
            print(f"\nround trip, {args.round_trip} frames: simulator images vs imported rendered signals "
                  "(2D correlation per frame):")
            for bf, profile in PROFILES.items():
                if profile != "ertis":
                    generate(tmp / f"sim_{profile}.zarr", runs=0, test_runs=1, minutes=n_rt * 0.2 / 60, seed=3,
                             workers=1, snr_db=40.0, processing=profile)
                    sim = open_store(tmp / f"sim_{profile}.zarr").run("test_000")
                else:
                    sim = run
                imp = import_raw(raw, tmp / f"rt_{bf}.zarr", processing=profile, workers=args.workers)
                a = sim.images[:].astype(np.float32)
                b = imp.images[:].astype(np.float32)
                ccs = [cc(x, y) for x, y in zip(a, b)]
                print(f"  {bf:9s} ({profile:5s}) mean {np.mean(ccs):.3f}  min {np.min(ccs):.3f}  "
                      f"per frame {' '.join(f'{c:.3f}' for c in ccs)}")
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
