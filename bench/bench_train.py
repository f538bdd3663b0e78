"""Training throughput (samples/s) of EchoPT's presets and of the recommended model, against the
matmul roof of the same process, on CPU and on a GPU when there is one.

    python bench/bench_train.py [--presets small,paper] [--steps 5] [--devices cpu,cuda]
                                [--roof-kinds echowarp:10,echopt:3] [--roof-batch 16] [--roof-preset small]
                                [--roof-compile]
                                [--roof-loss mse]

The roof section (CPU): each ``KIND:K`` of ``--roof-kinds`` built as its small preset (``--roof-preset``) and trained as
its recipe trains it (a K-step rollout per window: EchoWarp forecasts its K horizons in one pass),
its forward and backward GFLOP per window (torch's flop counter), training samples/s in fp32 and in
bf16 autocast, and the achieved TFLOP/s as a share of a large torch.matmul's in the same precision,
measured in the same process (bench/bench_zoo.py's functions). ``--roof-loss`` is the training
loss, as a recipe's ``loss`` spells it (default MSE): a recipe's terms cost time the flop count
(the network's) does not credit, so its share is what that recipe's training achieves. The C heap
is set as the CLI sets it (``sonarset.perf.keep_freed_memory``), so the rates are what ``sonarset
train`` gets. On a CPU without bf16 units the share that counts is fp32's. ``--roof-compile`` adds
bf16 with the network ``torch.compile``-d (inductor's CPU code; its compilation is not timed):
whether the compiler earns its place on a CPU.

Times full optimizer steps (forward, backward, Adam) on batch 64 of the default 200 x 90 grid
with data already in memory, in fp32 and in bf16 autocast (the precision ``--precision auto`` picks
where the CPU has bf16 units), in interleaved rounds. On CUDA it times fp32, bf16 autocast and
bf16 autocast + torch.compile in the same run, at each of ``--cuda-batches``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
import warnings

import torch
import torch.nn.functional as F

from sonarset.models.echopt.config import make_config
from sonarset.models.echopt.losses import parse_loss
from sonarset.models.echopt.model import EchoPT
from sonarset.models.echopt.precision import cpu_bf16_flags, resolve_precision
from sonarset.perf import keep_freed_memory

warnings.filterwarnings("ignore", message="Using padding='same'")


def rate(preset: str, device: str, steps: int, batch: int, bf16: bool = False, compile_: bool = False) -> float:
    torch.manual_seed(0)
    model = EchoPT(make_config(preset)).to(device).to(memory_format=torch.channels_last)
    fwd = torch.compile(model) if compile_ else model
    opt = torch.optim.Adam(model.parameters(), lr=5e-5, weight_decay=1e-4)
    x = torch.rand(batch, 3, 200, 90, device=device).contiguous(memory_format=torch.channels_last)
    c = torch.rand(batch, 4, 2, device=device)
    y = torch.rand(batch, 200, 90, device=device)

    def step() -> None:
        with torch.autocast(device, dtype=torch.bfloat16, enabled=bf16):
            pred = fwd(x, c)
        loss = F.mse_loss(pred.float(), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(3 if compile_ else 1):  # warm-up (compilation)
        step()
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    if device == "cuda":
        torch.cuda.synchronize()
    return steps * batch / (time.perf_counter() - t0)


def main() -> None:
    keep_freed_memory()  # as the CLI does (cli/app.py): without it each step's activations are fresh page faults
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="small,paper")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--devices", default="cpu,cuda", help="cpu, cuda or both (cuda only where there is one)")
    ap.add_argument("--cuda-batches", default="64,256")
    ap.add_argument("--roof-kinds", default="echowarp:10,echopt:3", help="KIND:K,... ('' skips the roof section)")
    ap.add_argument("--roof-batch", type=int, default=16)
    ap.add_argument("--roof-preset", default="small", help="the preset each roof kind is built as")
    ap.add_argument("--matmul", type=int, default=2048, help="size of the roof's square matmul")
    ap.add_argument("--roof-compile", action="store_true", help="also time bf16 with torch.compile")
    ap.add_argument("--roof-loss", default="mse", help="the roof section's training loss, a recipe's loss spec")
    args = ap.parse_args()
    devices = args.devices.split(",")
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "none"
    print(f"# bench_train  {platform.node()}  {os.cpu_count()} cores  torch {torch.__version__}  "
          f"{torch.get_num_threads()} threads  GPU: {gpu}")
    print(f"# CPU bf16 flags: {', '.join(cpu_bf16_flags()) or 'none'} (--precision auto -> {resolve_precision('auto', 'cpu')})")
    for preset in filter(None, args.presets.split(",")):  # --presets '' times the roof section alone
        n = EchoPT(make_config(preset)).n_params()
        if "cpu" in devices:
            # interleaved rounds, median: a noisy machine slows both alike, so the ratio holds
            fp32, bf16 = [], []
            for _ in range(args.rounds):
                fp32.append(rate(preset, "cpu", args.steps, args.batch))
                bf16.append(rate(preset, "cpu", args.steps, args.batch, bf16=True))
            f, b = statistics.median(fp32), statistics.median(bf16)
            print(f"{preset:6s} ({n / 1e6:.2f} M params) batch {args.batch} cpu fp32: {f:8.1f} samples/s   "
                  f"bf16 autocast: {b:8.1f} samples/s ({b / f:.2f}x)", flush=True)
        if "cuda" in devices and torch.cuda.is_available():
            torch.backends.cuda.matmul.allow_tf32 = False  # fp32 means fp32 (the CPU's arithmetic)
            torch.backends.cudnn.allow_tf32 = False
            for batch in (int(b) for b in args.cuda_batches.split(",")):
                steps = max(args.steps * 4, 4096 // batch)
                plain = rate(preset, "cuda", steps, batch)
                half = rate(preset, "cuda", steps, batch, bf16=True)
                try:
                    fast = rate(preset, "cuda", steps, batch, bf16=True, compile_=True)
                except Exception as exc:  # a compiler failure is a finding to print, not the end of the bench
                    print(f"# torch.compile failed: {type(exc).__name__}: {str(exc)[:200]}")
                    fast = float("nan")
                print(f"{preset:6s} ({n / 1e6:.2f} M params) batch {batch} cuda fp32: {plain:8.0f} samples/s   "
                      f"bf16 autocast: {half:8.0f} ({half / plain:.2f}x)   bf16 + compile: {fast:8.0f} "
                      f"({fast / plain:.2f}x)", flush=True)
    if "cpu" in devices and args.roof_kinds:
        roof_section(args)


def roof_section(args) -> None:
    """Each model's training speed as a share of the matmul roof of this process."""
    from bench_zoo import gflop_per_sample, matmul_tflops, network, samples_per_s

    terms = parse_loss(args.roof_loss)
    roof = {p: matmul_tflops(torch.float32 if p == "fp32" else torch.bfloat16, args.matmul) for p in ("fp32", "bf16")}
    print(f"# matmul roof ({args.matmul}^2, this process): fp32 {roof['fp32']:.3f} TFLOP/s, bf16 "
          f"{roof['bf16']:.3f} TFLOP/s; the share that counts: "
          f"{'bf16' if resolve_precision('auto', 'cpu') == 'bf16' else 'fp32'}; loss {args.roof_loss}")
    for item in args.roof_kinds.split(","):
        kind, _, k = item.partition(":")
        model = network(kind, args.roof_preset, (200, 90))
        gflop = gflop_per_sample(model, (200, 90), int(k or 1))
        runs = [(precision, model, precision) for precision in ("fp32", "bf16")]
        if args.roof_compile:
            compiled = torch.compile(model)
            samples_per_s(compiled, (200, 90), int(k or 1), args.roof_batch, 1, "bf16", terms)  # compiles forward and backward
            runs.append(("bf16 + torch.compile", compiled, "bf16"))
        cells = []
        for label, net, precision in runs:
            rate = samples_per_s(net, (200, 90), int(k or 1), args.roof_batch, args.steps, precision, terms)
            cells.append(f"{label} {rate:6.1f} samples/s = {rate * gflop / 1e3:.3f} TFLOP/s "
                         f"({100 * rate * gflop / 1e3 / roof[precision]:.1f}% of roof)")
        print(f"{kind:9s} {args.roof_preset}, {k}-step windows, batch {args.roof_batch}: {gflop:.2f} GFLOP/window; "
              + ";  ".join(cells), flush=True)


if __name__ == "__main__":
    main()
