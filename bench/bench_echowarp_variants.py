"""Speed only: EchoWarp variants' training rate and share of the matmul roof, untrained.

    python bench/bench_echowarp_variants.py [--variants small,relu,full8,wide,wide-relu,patch4] [--steps 6]
                                           [--loss 'cc=1,w1=100,energy=2,nrmsd_capped=2,nrmsd=2,echo=6']

Each variant is built as ``sonarset train`` builds EchoWarp (ten horizons, batch 16, channels-last)
and timed as bench/bench_train.py's roof section times it (full optimizer steps with the recipe's
loss, bf16 where the CPU has bf16 units), in one process with the roof. What a design change would
buy in speed before anyone trains it: the share of the roof counts the network's FLOPs, so read it
beside the windows per second.
"""

from __future__ import annotations

import argparse

import torch
import torch.nn as nn

from bench_zoo import gflop_per_sample, matmul_tflops, samples_per_s

import sonarset.models.zoo.common as common
from sonarset.models.echopt.losses import parse_loss
from sonarset.models.echopt.networks import build
from sonarset.models.echopt.precision import resolve_precision
from sonarset.perf import keep_freed_memory

RECIPE_LOSS = "cc=1,w1=100,energy=2,nrmsd_capped=2,nrmsd=2,echo=6"
#: name -> (what it is, config overrides, activation)
VARIANTS = {
    "small": ("small (shipped until 2026-12-08)", {}, "gelu"),
    "relu": ("small, ReLU for GELU", {}, "relu"),
    "full8": ("small, 8 full-resolution channels for 16", {"full_channels": 8}, "gelu"),
    "wide": ("wide: U-Net 48-96-192 for 32-64-128", {"channels": (48, 96, 192)}, "gelu"),
    "wide-relu": ("wide with ReLU", {"channels": (48, 96, 192)}, "relu"),
    "patch4": ("patch4 (shipped): 4 x 4 patches, U-Net 64-128-256 from 1/4 resolution", {"patch": 4, "channels": (64, 128, 256),
                                                                             "full_channels": 64}, "gelu"),
}


def variant(overrides: dict, activation: str) -> nn.Module:
    torch.manual_seed(0)
    model = build("echowarp", "small", 200, 90, **overrides).to(memory_format=torch.channels_last)
    if activation == "relu":
        for module in model.modules():
            if isinstance(module, common.ConvAct):
                module[1] = nn.ReLU()
    return model


def main() -> None:
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--loss", default=RECIPE_LOSS)
    args = ap.parse_args()
    terms = parse_loss(args.loss)
    precision = resolve_precision("auto", "cpu")
    roof = matmul_tflops(torch.bfloat16 if precision == "bf16" else torch.float32, 2048)
    print(f"# {precision}, matmul roof {roof:.3f} TFLOP/s, loss {args.loss}")
    print("| EchoWarp variant | parameters | GFLOP per ten-horizon window | windows/s | share of the roof |")
    print("|---|---|---|---|---|")
    for name in args.variants.split(","):
        what, overrides, activation = VARIANTS[name]
        model = variant(overrides, activation)
        gflop = gflop_per_sample(model, (200, 90), 10)
        rate = samples_per_s(model, (200, 90), 10, 16, args.steps, precision, terms)
        params = sum(p.numel() for p in model.parameters()) / 1e6
        print(f"| {what} | {params:.2f} M | {gflop:.2f} | {rate:.1f} | {100 * rate * gflop / 1e3 / roof:.1f} % |",
              flush=True)


if __name__ == "__main__":
    main()
