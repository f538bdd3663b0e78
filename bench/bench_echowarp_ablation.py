"""EchoWarp's ablation at equal budget: variants each trained from scratch by the same recipe
(recipes/echowarp/ablation/), scored beside flow on the same windows of protocol v1's datasets.

    python bench/bench_echowarp_ablation.py RUN [RUN ...] [--samples 400] [--out ablation-out]

Each RUN is a run directory of ``sonarset train --config recipes/echowarp/ablation/VARIANT.toml``.
Where bench/bench_echowarp_parts.py switches parts off in one trained model (what the network
learned to lean on), this asks what each part is worth when the network is trained without it.
Prints, per variant: its training budget (windows, steps, wall time, best step, from its card and
metrics.jsonl), CC at every horizon and NRMSD and echo F1 at AR-10 averaged over the datasets, and
the share of the flow-to-observable CC gap closed at AR-10 per dataset; writes the benchmark's results.json to --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch

from sonarset.models.benchmark.protocol import PROTOCOL_V1
from sonarset.models.benchmark.run import run_benchmark
from sonarset.models.benchmark.stores import cache_dir

from bench_echowarp_parts import print_gap_shares


def budget(run: Path) -> dict:
    """What a run spent: windows (steps x batch), steps, its preset, wall seconds, the best step."""
    card = json.loads((run / "model.json").read_text())
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    steps = max(r["step"] for r in records)
    scored = [r for r in records if r.get("val_loss") is not None]
    best = min(scored, key=lambda r: r["val_loss"]) if scored else {"step": None, "val_loss": float("nan")}
    return {"preset": card["preset"], "steps": steps, "windows": steps * card["training"]["recipe"]["batch_size"],
            "seconds": max(r["elapsed_s"] for r in records), "best_step": best["step"], "best_val": best["val_loss"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="EchoWarp run directories, one per variant")
    ap.add_argument("--samples", type=int, default=400, help="windows per dataset")
    ap.add_argument("--out", default="ablation-out")
    args = ap.parse_args()
    spent = {run: budget(run) for run in args.runs}
    protocol = dataclasses.replace(PROTOCOL_V1, version=f"v1-ablation-{args.samples}", samples=args.samples)
    torch.manual_seed(0)
    specs = ["flow"] + [f"echowarp:{run}" for run in args.runs]
    results = run_benchmark(specs, args.out, protocol=protocol, cache=cache_dir(PROTOCOL_V1), log=print)
    names = list(results["datasets"])
    horizons = [str(h) for h in protocol.horizons]
    longest = horizons[-1]
    methods = list(results["datasets"][names[0]]["horizons"][longest]["methods"])

    def cell(name: str, h: str, method: str) -> dict:
        return results["datasets"][name]["horizons"][h]["methods"][method]

    print(f"\nbudget and CC averaged over the {len(names)} datasets ({args.samples} windows each)\n")
    print("| variant | windows | steps | wall | best step | " + " | ".join(f"CC h={h}" for h in horizons)
          + f" | NRMSD h={longest} | echo F1 h={longest} |")
    print("|---" * (7 + len(horizons)) + "|")
    for method, run in zip(methods, [None, *args.runs]):
        b = spent.get(run)
        label = "flow" if run is None else b["preset"]
        cost = "| - | - | - | - |" if b is None else \
            f"| {b['windows']} | {b['steps']} | {b['seconds'] / 60:.1f} min | {b['best_step']} |"
        means = [sum(cell(n, h, method)[metric]["mean"] for n in names) / len(names)
                 for metric, h in [("cc", h) for h in horizons] + [("nrmsd", longest), ("echo_f1", longest)]]
        print(f"| {label} {cost} " + " | ".join(f"{m:.3f}" for m in means) + " |")
    print_gap_shares(results, {method: spent[run]["preset"] for method, run in zip(methods[1:], args.runs)})


if __name__ == "__main__":
    main()
