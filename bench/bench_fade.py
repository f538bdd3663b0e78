"""Where a rolled-out forecast's echo energy goes (issue 12's no-fade check, taken apart).

    python bench/bench_fade.py lab.zarr --models flow,echopt:pretrained --windows 200

For random 10-step windows of the store's test runs, rolls each predictor out auto-regressively and
prints, per step, the ratio of the forecasts' mean to the targets' mean of: the peak pixel; the
echo energy above 0.05 (the eval report's "echo energy") and above 0.2; the sum of all pixels; and
the number of pixels above 0.05. A forecast that blurs (the conditional mean of an uncertain echo
position, which an MSE-trained model converges to) keeps its pixel sum but moves energy from bright
pixels to more, dimmer ones: the sum stays near 1 while the energy above a level drops and the
count above 0.05 grows.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from sonarset import open_store
from sonarset.windows import N_IN, FrameBank, WindowIndex, gather


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--models", default="flow,echopt:pretrained", help="comma-separated predictor specs")
    ap.add_argument("--windows", type=int, default=200)
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from sonarset.models.baselines import rollout
    from sonarset.models.eval.evaluate import baseline_rig
    from sonarset.models.registry import make_predictor

    store = open_store(args.store)
    bank = FrameBank.from_store(store, split="test", image_dtype=np.float32)
    index = WindowIndex.build(bank, N_IN, args.horizon)
    pick = np.sort(np.random.default_rng(args.seed).choice(len(index), min(args.windows, len(index)), replace=False))
    batch = gather(bank, index, pick)
    targets = batch.targets.astype(np.float32)
    baselines_rig, _ = baseline_rig(store, bank)  # what evaluate warps the baselines with
    print(f"# bench_fade  {platform.node()}  {os.cpu_count()} cores  {time.strftime('%Y-%m-%d %H:%M')}  "
          f"{store.location}, {len(pick)} test windows, seed {args.seed}")
    print("| predictor | step | peak | energy > 0.05 | energy > 0.2 | pixel sum | pixels > 0.05 |")
    print("|---|---:|---:|---:|---:|---:|---:|")

    def energy(x: np.ndarray, level: float) -> float:
        return float((x * (x > level)).sum(axis=(1, 2)).mean())

    for spec in args.models.split(","):
        pred = make_predictor(spec, store.grid, baselines_rig)
        out = rollout(pred, batch.frames.astype(np.float32), batch.commands.astype(np.float32), args.horizon)
        for h in range(args.horizon):
            p, t = out[:, h], targets[:, h]
            cells = [p.max(axis=(1, 2)).mean() / t.max(axis=(1, 2)).mean(), energy(p, 0.05) / energy(t, 0.05),
                     energy(p, 0.2) / energy(t, 0.2), p.sum() / t.sum(), (p > 0.05).sum() / max((t > 0.05).sum(), 1)]
            print(f"| {spec} | {h + 1} | " + " | ".join(f"{c:.2f}" for c in cells) + " |", flush=True)


if __name__ == "__main__":
    main()
