"""Where flow's one-step error lies, and what a correction that knows where a pixel is could take back.

    python bench/bench_flow_error.py STORE [--samples 300] [--fit-windows 1500] [--seed 0] [--families lab,corridor]

For one-shot forecasts on each family's test run, prints:

- the share of flow's squared error in each fifth of the range and each sixth of the azimuth (how
  much sits at the near range and the sides of the view, where a one-step warp deforms the PSF most:
  the azimuth PSF is shift-invariant in sin(azimuth), not in azimuth);
- flow against two linear corrections of it, fitted by least squares on windows of that family's
  *training* runs and scored on the test windows: ``local`` adds one 7 x 5 linear filter of the
  flow image (the same everywhere, like a convolution), ``by place`` one such filter per cell of
  (azimuth ninth x range band x turn rate x speed) (a filter that knows where the pixel lies and how
  the robot moved). Each also shown as the share of test windows it improves.

No network is involved: the gap between the two corrections is what a model gains from knowing a
pixel's position and the warp's geometry (what ``--geometry-channels`` gives EchoPT).
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from sonarset import open_store
from sonarset.models.baselines import AcousticFlow
from sonarset.scoring.metrics import cc_and_nrmsd
from sonarset.windows import N_IN, FrameBank, WindowIndex, gather

KERNEL = (7, 5)
RANGE_BANDS = (20, 50, 100)  # band edges, range pixels: the default grid's 0.95 m, 1.6 m, 2.75 m
AZIMUTH_BANDS = 9
OMEGA_EDGES = (-0.6, -0.2, 0.2, 0.6)  # rad/s
SPEED_EDGES = (0.0, 0.15)  # m/s


def one_step(store, family: str, split: str, n: int, seed: int):
    """(flow forecasts, targets, newest commands) of ``n`` seeded one-shot windows of ``family``'s
    ``split`` runs."""
    bank = FrameBank.from_store(store, split=split, worlds=[family])
    index = WindowIndex.build(bank, N_IN, 1).sample(n, seed=seed)
    batch = gather(bank, index, image_dtype=np.float32)
    flow = AcousticFlow(store.grid, store.rig).predict(batch.frames, batch.commands)
    return flow, batch.targets[:, 0], batch.commands[:, -1]


def features(flow: np.ndarray) -> np.ndarray:
    """(B, R, A, taps + 1): each pixel's KERNEL neighbourhood of the flow image (edge-padded), and 1."""
    kr, ka = KERNEL
    pad = np.pad(flow, ((0, 0), (kr // 2, kr // 2), (ka // 2, ka // 2)), mode="edge")
    R, A = flow.shape[1:]
    taps = [pad[:, i:i + R, j:j + A] for i in range(kr) for j in range(ka)]
    return np.stack(taps + [np.ones_like(flow)], -1)


def cells(shape: tuple[int, int], commands: np.ndarray):
    """Per window its motion cell, and per pixel its place cell (azimuth band x range band)."""
    R, A = shape
    motion = np.digitize(commands[:, 1], OMEGA_EDGES) * (len(SPEED_EDGES) + 1) + np.digitize(commands[:, 0], SPEED_EDGES)
    place = (np.minimum(np.arange(A) * AZIMUTH_BANDS // A, AZIMUTH_BANDS - 1)[None, :]
             + AZIMUTH_BANDS * np.digitize(np.arange(R), RANGE_BANDS)[:, None])
    return motion, place


def fit(flow, target, commands, by_place: bool, chunk: int = 32):
    """Least-squares filter(s) of the correction target - flow: one, or one per (motion, place) cell."""
    n_motion = (len(OMEGA_EDGES) + 1) * (len(SPEED_EDGES) + 1)
    motion, place = cells(flow.shape[1:], commands)
    n_place = int(place.max()) + 1 if by_place else 1
    k = KERNEL[0] * KERNEL[1] + 1
    xtx = np.zeros((n_motion if by_place else 1, n_place, k, k))
    xty = np.zeros(xtx.shape[:3])
    flat = place.reshape(-1)
    pixels = [np.flatnonzero(flat == c) for c in range(n_place)] if by_place else [np.arange(flat.size)]
    for lo in range(0, len(flow), chunk):
        X = features(flow[lo:lo + chunk]).reshape(-1, flat.size, k)
        y = (target[lo:lo + chunk] - flow[lo:lo + chunk]).reshape(-1, flat.size)
        for m in np.unique(motion[lo:lo + chunk]) if by_place else [0]:
            b = np.flatnonzero(motion[lo:lo + chunk] == m) if by_place else slice(None)
            for c, px in enumerate(pixels):
                Xc = X[b][:, px].reshape(-1, k).astype(np.float64)
                xtx[m, c] += Xc.T @ Xc
                xty[m, c] += Xc.T @ y[b][:, px].reshape(-1)
    ridge = 1e-3 * np.trace(xtx, axis1=2, axis2=3)[..., None, None] / k * np.eye(k) + 1e-9 * np.eye(k)
    return np.linalg.solve(xtx + ridge, xty[..., None])[..., 0]  # (motion, place, k)


def apply(coef, flow, commands, by_place: bool) -> np.ndarray:
    motion, place = cells(flow.shape[1:], commands)
    out = np.empty_like(flow)
    for b in range(len(flow)):
        X = features(flow[b:b + 1])[0]
        w = coef[motion[b]][place] if by_place else coef[0, 0]  # (R, A, k) or (k,)
        out[b] = flow[b] + (X * w).sum(-1)
    return np.clip(out, 0, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--samples", type=int, default=300, help="test windows per family")
    ap.add_argument("--fit-windows", type=int, default=1500, help="training windows per family to fit on")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--families", default="", help="only these families (default: every family with test runs)")
    args = ap.parse_args()
    store = open_store(args.store, check=True)
    only = {f.strip() for f in args.families.split(",") if f.strip()}
    print(f"# bench_flow_error  {platform.node()}  {os.cpu_count()} cores  {time.strftime('%Y-%m-%d')}")
    for family in sorted(f for f in store.worlds("test") if not only or f in only):
        t0 = time.perf_counter()
        flow, target, cmd = one_step(store, family, "test", args.samples, args.seed)
        err = (target - flow) ** 2
        R, A = err.shape[1:]
        by_range = [err[:, i * R // 5:(i + 1) * R // 5].sum() / err.sum() for i in range(5)]
        by_azimuth = [err[:, :, i * A // 6:(i + 1) * A // 6].sum() / err.sum() for i in range(6)]
        print(f"{family}: flow's one-step squared error by range fifth (near first) "
              f"{' '.join(f'{s:.2f}' for s in by_range)}; by azimuth sixth {' '.join(f'{s:.2f}' for s in by_azimuth)}")
        f_tr, t_tr, c_tr = one_step(store, family, "train", args.fit_windows, args.seed)
        cc0, nr0 = cc_and_nrmsd(flow, target)
        cells_out = [f"flow CC {np.nanmean(cc0):.4f} NRMSD {np.nanmean(nr0):.4f}"]
        for name, by_place in (("local", False), ("by place", True)):
            pred = apply(fit(f_tr, t_tr, c_tr, by_place), flow, cmd, by_place)
            cc, nr = cc_and_nrmsd(pred, target)
            ok = np.isfinite(cc) & np.isfinite(cc0)
            cells_out.append(f"{name} CC {np.nanmean(cc):.4f} NRMSD {np.nanmean(nr):.4f} "
                             f"(windows improved {np.mean(cc[ok] > cc0[ok]):.2f})")
        print(f"  one-shot, {args.samples} test windows: " + " | ".join(cells_out)
              + f"  [{time.perf_counter() - t0:.0f} s]", flush=True)


if __name__ == "__main__":
    main()
