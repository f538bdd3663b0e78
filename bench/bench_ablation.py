"""Ablation at equal CPU budget: prior `last` vs `flow`, one-step vs rollout training (issue 12).

    sonarset generate lab.zarr --seed 0                      # the paper's dataset, default images
    python bench/bench_ablation.py lab.zarr --out ablation --minutes 6 --threads 1
    python bench/bench_ablation.py lab.zarr --out seeds --recipes shipped --seeds 1,2,3 --steps 150 --threads 1

Trains EchoPT-small four times on the same training windows, each for the same wall time on the
same machine (run nothing else meanwhile): {prior last, prior flow} x {one-step loss, rollout
loss with a curriculum on k and noise on the context frames}. Then scores the four best-validation
models with the baselines on the same 1000 test windows (the store's test run), at one-shot and
AR-3/5/10, and prints one table: CC and NRMSD per horizon, training steps and minutes. With several
`--seeds`, every recipe is trained once per seed, all models are scored on the same windows, and a
second table gives each recipe's mean and sample standard deviation over the seeds, so a win is not
one lucky seed. Every run is a normal training directory: `--resume` continues it, `sonarset eval`
scores it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

from sonarset import open_store
from sonarset.models.eval.report import write_report
from sonarset.models.eval.evaluate import evaluate
from sonarset.models.echopt.train import train
from sonarset.models.echopt.train_config import TrainConfig

#: The recipes: what differs between them. Everything else is shared (COMMON).
RECIPES = {
    "last-1step": dict(prior="last"),
    "flow-1step": dict(prior="flow"),
    # A CPU affords a few hundred steps: the curriculum starts at k = 2 (the prior already makes
    # one-step forecasts) and reaches 4 within the budget.
    "last-rollout": dict(prior="last", curriculum="0:2,50:3,100:4", context_noise=0.01),
    "flow-rollout": dict(prior="flow", curriculum="0:2,50:3,100:4", context_noise=0.01),
    # The shipped echopt-small's recipe (models/pretrained/echopt-small.json), for the seed spread.
    "shipped": dict(prior="flow", curriculum="0:2,50:3,100:4,300:5", context_noise=0.01),
}
COMMON = dict(preset="small", batch_size=32, lr=3e-4, optimizer="adamw", schedule="none", n_val=256, eval_every=80,
              val_horizon=4, test_samples=0, device="cpu")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--out", default="ablation")
    ap.add_argument("--minutes", type=float, default=6.0, help="training wall time per recipe")
    ap.add_argument("--steps", type=int, default=0, help="a step budget instead of wall time (0: --minutes); "
                                                      "equal steps keep seeds comparable on a busy machine")
    ap.add_argument("--samples", type=int, default=1000, help="test windows")
    ap.add_argument("--recipes", default=",".join(RECIPES))
    ap.add_argument("--seeds", default="0", help="comma-separated training seeds (test windows are fixed)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default); 1 keeps the "
                                                          "budget equal when something else uses the other core")
    args = ap.parse_args()
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    store = open_store(args.store)
    out = Path(args.out)
    print(f"# bench_ablation  {platform.node()}  {os.cpu_count()} cores  {time.strftime('%Y-%m-%d %H:%M')}  "
          f"{args.minutes:g} min per recipe, seeds {args.seeds}, {args.threads or 'default'} torch threads", flush=True)
    seeds = [int(x) for x in args.seeds.split(",")]
    tag = "-".join(map(str, seeds))
    trained = {}
    for seed in seeds:
        for name in args.recipes.split(","):
            run = out / f"{name}-s{seed}"
            cfg = TrainConfig(**{**COMMON, **RECIPES[name]}, seed=seed,
                              max_minutes=0 if args.steps else args.minutes, max_steps=args.steps,
                              command=f"bench/bench_ablation.py {name} seed {seed}")
            t0 = time.perf_counter()
            res = train(store, run, cfg, resume=run.exists())
            minutes = (time.perf_counter() - t0) / 60
            key = name if len(seeds) == 1 else f"{name}-s{seed}"
            trained[key] = (run, res.steps, minutes)
            print(f"{key}: {res.steps} steps, {res.epochs_done:.3f} epochs, {minutes:.1f} min, best val "
                  f"{res.best_val_loss:.5f}", flush=True)
    from sonarset.models.echopt.predictor import load_echopt_predictor

    learned = {}
    for name, (run, _, _) in trained.items():
        learned[name] = load_echopt_predictor(str(run), store.grid)
        learned[name].name = name
    res = evaluate(store, ["persistence", "naive", "flow"], predictors=learned, samples=args.samples, seed=0)
    write_report(res, out / f"eval-s{tag}")
    s = res.summary()
    print("| method | steps | train min | CC 1 / 3 / 5 / 10 | NRMSD 1 / 3 / 5 / 10 |")
    print("|---|---|---|---|---|")
    rows = {}
    for m in res.methods:
        cc = " / ".join(f"{s[m][str(h)]['cc']['mean']:.3f}" for h in res.horizons)
        nr = " / ".join(f"{s[m][str(h)]['nrmsd']['mean']:.3f}" for h in res.horizons)
        steps, mins = (trained[m][1], f"{trained[m][2]:.1f}") if m in trained else ("", "")
        rows[m] = {"steps": steps, "minutes": mins, **{h: s[m][str(h)] for h in res.horizons}}
        print(f"| {m} | {steps} | {mins} | {cc} | {nr} |", flush=True)
    (out / f"ablation-s{tag}.json").write_text(json.dumps(rows, indent=2) + "\n")
    if len(seeds) > 1:
        print_spread(res, args.recipes.split(","), seeds)


def print_spread(res, recipes: list[str], seeds: list[int]) -> None:
    """Per recipe: mean +- sample sd over the seeds of the per-seed mean scores."""
    import numpy as np

    s = res.summary()
    print(f"\n| recipe ({len(seeds)} seeds) | CC 1 / 3 / 5 / 10 | NRMSD 1 / 3 / 5 / 10 |")
    print("|---|---|---|")
    for name in recipes:
        cells = []
        for metric in ("cc", "nrmsd"):
            per_h = []
            for h in res.horizons:
                v = np.array([s[f"{name}-s{seed}"][str(h)][metric]["mean"] for seed in seeds])
                per_h.append(f"{v.mean():.3f} +- {v.std(ddof=1):.3f}")
            cells.append(" / ".join(per_h))
        print(f"| {name} | {cells[0]} | {cells[1]} |", flush=True)


if __name__ == "__main__":
    main()
