"""Which part of a trained EchoWarp carries its gain: the model scored with each of its outputs
switched off, on the benchmark's datasets.

    python bench/bench_echowarp_parts.py RUN [--samples 300] [--out parts-out]

EchoWarp's head has three outputs (models/echowarp/model.py): the correction of where each pixel is
sampled from in the last frame, the gates that add the older registered frames, and the source
term. Each variant zeroes one of them in the trained weights (the correction's zero is no shift,
the gates' and the source's zero is nothing added), so the model falls back to the composite warp
for that part. ``composite`` zeroes all three: the last frame warped once along the composed
motion, EchoWarp untrained. Every variant and flow are scored on the same windows of protocol v1's
datasets (``--samples`` per dataset, the protocol's horizons, stores from the benchmark's cache),
and the share of the flow-to-observable CC gap each closes is printed per dataset at AR-10.

This is a knock-out of one trained model, not an ablation at equal budget (which retrains each
variant: recipes/echowarp/ablation/): a part the network learned to lean on shows here.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import torch

from sonarset.models.benchmark.protocol import PROTOCOL_V1
from sonarset.models.benchmark.run import run_benchmark
from sonarset.models.benchmark.stores import cache_dir
from sonarset.models.echopt.checkpoint import load_checkpoint, save_checkpoint


def variants(model) -> dict[str, list[int]]:
    """The head's output channels each variant zeroes."""
    n_in = model.cfg.n_in
    correction, gates, source = [0, 1], list(range(2, n_in + 1)), [n_in + 1]
    return {"full": [], "no-correction": correction, "no-older-frames": gates, "no-source": source,
            "composite": correction + gates + source}


def print_gap_shares(results: dict, labels: dict[str, str]) -> None:
    """The share of the flow-to-observable CC gap each method of ``labels`` closes at the longest
    horizon, per dataset: a Markdown table, rows labelled as ``labels`` says."""
    names = list(results["datasets"])
    longest = str(max(int(h) for h in results["datasets"][names[0]]["horizons"]))
    print(f"\nshare of the flow-to-observable CC gap closed at AR-{longest}\n")
    print("| variant | " + " | ".join(names) + " |")
    print("|---" * (1 + len(names)) + "|")
    for method, label in labels.items():
        cells = [results["datasets"][n]["horizons"][longest]["methods"][method]["gap_share"]["cc"] for n in names]
        print(f"| {label} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="an EchoWarp run directory or .safetensors checkpoint")
    ap.add_argument("--samples", type=int, default=300, help="windows per dataset")
    ap.add_argument("--out", default="parts-out")
    args = ap.parse_args()
    model, card = load_checkpoint(args.run, kind="echowarp")
    folder = Path(tempfile.mkdtemp(prefix="echowarp-parts-"))
    specs = ["flow"]
    trained = {k: v.clone() for k, v in model.state_dict().items()}
    for name, channels in variants(model).items():
        state = {k: v.clone() for k, v in trained.items()}  # each variant from the trained weights
        for c in channels:
            state["head.weight"][c] = 0
            state["head.bias"][c] = 0
        model.load_state_dict(state)
        save_checkpoint(folder / name / "model.safetensors", model, card)
        specs.append(f"echowarp:{folder / name}")
    protocol = dataclasses.replace(PROTOCOL_V1, version=f"v1-parts-{args.samples}", samples=args.samples)
    torch.manual_seed(0)
    # v1's stores, from v1's cache
    results = run_benchmark(specs, args.out, protocol=protocol, cache=cache_dir(PROTOCOL_V1), log=print)
    first = next(iter(results["datasets"].values()))["horizons"][str(max(protocol.horizons))]["methods"]
    print(f"\n{args.samples} windows per dataset")
    print_gap_shares(results, {m: m.split()[-1].split("/")[0] for m in first if m != "flow"})


if __name__ == "__main__":
    main()
