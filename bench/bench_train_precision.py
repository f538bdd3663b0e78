"""bf16 against fp32 training at equal steps: does bf16 autocast reach the fp32 run's validation loss?

    python bench/bench_train_precision.py lab.zarr [--preset small] [--steps 300] [--batch 32] [--out DIR]

Trains the same network from the same seed twice, ``--precision fp32`` and ``--precision bf16``,
for the same optimizer steps (MSE loss, one-step windows: the paper's recipe), then scores both
runs' best weights in fp32 on the same validation windows, so that the comparison does not hang
on the precision a loss was computed in. Prints each run's wall time and the ratio of the losses.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

from sonarset.models.echopt.checkpoint import load_checkpoint
from sonarset.models.echopt.losses import validation_loss
from sonarset.models.echopt.train import train
from sonarset.models.echopt.train_config import TrainConfig
from sonarset.store.store import open_store
from sonarset.torchdata import torch_batcher
from sonarset.windows import FrameBank, WindowIndex

warnings.filterwarnings("ignore", message="Using padding='same'")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--prior", default="", help="none | last | flow (default: the preset's); none makes the "
                                                  "network draw the whole image, the harder case for bf16")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--n-val", type=int, default=512)
    ap.add_argument("--eval-every", type=int, default=50)
    ap.add_argument("--out", default="")
    args = ap.parse_args()
    store = open_store(args.store, check=True)
    root = Path(args.out or tempfile.mkdtemp(prefix="bench-precision-"))
    print(f"# bench_train_precision  {args.store}  preset {args.preset}  prior {args.prior or 'default'}  "
          f"{args.steps} steps of batch {args.batch}  "
          f"lr {args.lr}  {time.strftime('%Y-%m-%d')}")
    runs = {}
    for precision in ("fp32", "bf16"):
        cfg = TrainConfig(preset=args.preset, prior=args.prior, batch_size=args.batch, lr=args.lr, optimizer="adamw",
                          n_val=args.n_val, eval_every=args.eval_every, max_steps=args.steps, device="cpu",
                          test_samples=0, precision=precision, command=f"bench_train_precision {precision}")
        t0 = time.perf_counter()
        res = train(store, root / precision, cfg)
        runs[precision] = (res, time.perf_counter() - t0)
        curve = ", ".join(f"{r['step']}: {r['val_loss']:.6f}" for r in res.history)
        print(f"{precision}: {time.perf_counter() - t0:.0f} s, best validation loss (in {precision}) "
              f"{res.best_val_loss:.6f}; curve {curve}", flush=True)
    # both best models scored in fp32 on the same validation windows (the trainer's split, same seed)
    bank = FrameBank.from_store(store, split="train")
    _, val_idx = WindowIndex.build(bank, 3, 1).split(args.n_val, seed=0)
    batcher = torch_batcher(bank, "cpu")
    fp32_scores = {}
    for precision, (res, _) in runs.items():
        model, _ = load_checkpoint(res.out_dir, store.grid)
        fp32_scores[precision] = validation_loss(model, batcher, val_idx, 1)
    a, b = fp32_scores["fp32"], fp32_scores["bf16"]
    speed = runs["fp32"][1] / runs["bf16"][1]
    print(f"validation MSE in fp32 of the best weights: fp32 run {a:.6f}, bf16 run {b:.6f} "
          f"(bf16 / fp32 = {b / a:.4f}, {'within' if abs(b / a - 1) <= 0.02 else 'NOT within'} 2%); "
          f"bf16 trained {speed:.2f}x as fast")


if __name__ == "__main__":
    main()
