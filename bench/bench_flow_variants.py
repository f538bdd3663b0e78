"""Where the acoustic flow's error lies: physics fixes to the warp, each scored against the flow baseline.

    python bench/bench_flow_variants.py STORE [--samples 300] [--seed 0] [--families lab,corridor]

EchoPT closes only a fifth of the CC gap between flow and the observable ceiling at AR-10
(BENCHMARKS.md, "World families"). Before asking a network for more, this measures what simple
physics would buy, on the same seeded windows of each family's test run:

- ``flow``: the baseline (``models/baselines.AcousticFlow``), rolled out: each step re-samples the
  previous prediction bilinearly, edge values outside the field of view;
- ``composite``: one warp of the last measured frame along the whole chained motion (no
  accumulated re-sampling blur);
- ``composite+gain``: that, with each echo's level moved by the range change (wall spreading,
  20 log10 r, and two-way air absorption, docs/physics.md) on the display's dB scale;
- ``background``: the rollout with pixels from outside the field of view set to the frame's
  median (what empty space looks like) instead of the nearest edge value, which an iterated warp
  smears into streaks along the near-range and side edges.

Prints mean CC and NRMSD per family and horizon. No learned model is involved.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
import torch

from sonarset import open_store
from sonarset.models.baselines import AcousticFlow, rollout, sample_polar
from sonarset.models.flow import arc_motion, source_points
from sonarset.scoring.metrics import cc_and_nrmsd
from sonarset.windows import N_IN, FrameBank, WindowIndex, gather

HORIZONS = (1, 3, 5, 10)
ABSORPTION_DB_PER_M = 1.3  # docs/physics.md, one way


def warp(images: np.ndarray, grid, r: np.ndarray, th: np.ndarray, fill: str = "edge") -> np.ndarray:
    """The baselines' bilinear sampling at source points (metres, radians); ``fill="background"``
    puts the frame's median where the source lies outside the field of view, instead of the
    nearest edge value."""
    out = sample_polar(images, grid, torch.as_tensor(r, dtype=torch.float32), torch.as_tensor(th, dtype=torch.float32))
    if fill == "background":
        outside = ((r < grid.range_min_m) | (r > grid.range_max_m)
                   | (th < grid.azimuth_min_rad) | (th > grid.azimuth_max_rad))
        out = np.where(outside, np.median(images.reshape(len(images), -1), axis=1)[:, None, None], out)
    return out


def variants(store, frames: np.ndarray, commands: np.ndarray, n_in: int, horizon: int):
    """Yields (t, {variant: predictions of target t}) for t = 1 .. horizon."""
    grid, rig = store.grid, store.rig
    span = store.processing.span_db
    B, (R, A) = len(frames), grid.shape
    r0 = np.broadcast_to(grid.range_centres()[None, :, None], (B, R, A))
    th0 = np.broadcast_to(grid.azimuth_centres()[None, None, :], (B, R, A))
    cmd = np.asarray(commands, np.float64)
    motions = [tuple(a[:, None, None] for a in arc_motion(np, cmd[:, n_in + s, 0], cmd[:, n_in + s, 1],
                                                          rig.frame_interval_s)) for s in range(horizon)]

    def back(r, th, s):  # points of frame s + 1's sensor frame, seen from frame s
        x, y = source_points(np, r, th, motions[s], rig.sensor_offset_m)
        return np.hypot(x, y), np.arctan2(y, x)

    last = frames[:, -1]
    flow = rollout(AcousticFlow(grid, rig), frames, commands, horizon)  # the baseline itself
    background = last
    for t in range(1, horizon + 1):
        r, th = back(r0, th0, t - 1)
        background = warp(background, grid, r, th, "background")
        for s in range(t - 2, -1, -1):
            r, th = back(r, th, s)
        composite = warp(last, grid, r, th)
        gain_db = 20 * np.log10(r / r0) + 2 * ABSORPTION_DB_PER_M * (r - r0)
        gained = np.clip(composite + np.where(composite > 0.02, gain_db / span, 0), 0, 1)
        yield t, {"flow": flow[:, t - 1], "background": background, "composite": composite,
                  "composite+gain": gained}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--families", default="", help="only these families (default: every family with test runs)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    store = open_store(args.store, check=True)
    only = {f.strip() for f in args.families.split(",") if f.strip()}
    print(f"# bench_flow_variants  {platform.node()}  {os.cpu_count()} cores  {time.strftime('%Y-%m-%d')}")
    print("# mean CC / NRMSD over the same windows; flow is the baseline")
    horizon = max(HORIZONS)
    for family in sorted(f for f in store.worlds("test") if not only or f in only):
        bank = FrameBank.from_store(store, split="test", worlds=[family])
        index = WindowIndex.build(bank, N_IN, horizon).sample(args.samples, seed=args.seed)
        batch = gather(bank, index, image_dtype=np.float32)
        for t, preds in variants(store, batch.frames, batch.commands, N_IN, horizon):
            if t not in HORIZONS:
                continue
            cells = []
            for name, p in preds.items():
                cc, nrmsd = cc_and_nrmsd(p, batch.targets[:, t - 1])
                cells.append(f"{name} {np.nanmean(cc):.3f} / {np.nanmean(nrmsd):.3f}")
            print(f"{family:10s} AR-{t:<3d} " + " | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
