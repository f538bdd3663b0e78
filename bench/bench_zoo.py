"""The learned methods at equal budget: parameters, FLOP per training sample and training samples/s
of EchoPT and the reference methods (models/zoo/), beside the machine's matmul roof.

    python bench/bench_zoo.py [--kinds echopt,convlstm,simvp,unet] [--preset small] [--grid 200x90]
                              [--batch 32] [--steps 3] [--out bench_zoo.json] [--recipes recipes/zoo]

With ``--recipes DIR`` each kind is built as DIR/KIND-small.toml trains it (its preset, prior,
inputs and, for EchoPT, the geometry branch), so the table describes the networks the zoo trains.

For each kind at ``--preset`` on the grid: parameters; GFLOP per training sample, forward and
backward, of a one-step and of a 3-step rollout step (the trainer's own loss, models/echopt/losses.py:
EchoPT, ConvLSTM and the U-Net chain three forwards, SimVP forecasts three steps in one pass),
counted by torch.utils.flop_counter.FlopCounterMode; training samples/s of full optimizer steps
(forward, backward, Adam; data in memory) in fp32 and, where the CPU has bf16 units
(models/echopt/precision.py), in bf16 autocast; and the achieved GFLOP/s against the roof of the
same process: a large torch.matmul in fp32 and bf16, TFLOP/s. Prints a table and writes JSON.
The C heap is set as the CLI sets it (``sonarset.perf.keep_freed_memory``): the rates are what
``sonarset train`` gets.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings

import torch
from torch.utils.flop_counter import FlopCounterMode, conv_backward_flop

from sonarset.format.attrs import SensorGrid
from sonarset.models.echopt.losses import REFERENCE_TERMS, rollout_losses, weighted_loss
from sonarset.models.echopt.networks import KINDS, build
from sonarset.models.echopt.precision import cpu_bf16_flags
from sonarset.models.echopt.recipes import config_of, load_recipe
from sonarset.perf import keep_freed_memory
from sonarset.scoring.echoes import tolerance_bins

warnings.filterwarnings("ignore", message="Using padding='same'")


def _grouped_conv_backward_flop(grad_out_shape, x_shape, w_shape, bias, stride, padding, dilation, transposed,
                                output_padding, groups, output_mask, out_shape, **kw) -> int:
    """torch's count of a convolution's backward, with the weight gradient of a grouped convolution
    divided by its groups: torch counts it as if every input channel met every output channel, so
    a depth-wise convolution's backward (SimVP's gSTA) came out ~100x its real cost."""
    args = (grad_out_shape, x_shape, w_shape, bias, stride, padding, dilation, transposed, output_padding, groups)
    torch_count = conv_backward_flop.__wrapped__  # on shapes, as this function is called
    inputs = torch_count(*args, [output_mask[0], False], out_shape, **kw)
    weights = torch_count(*args, [False, output_mask[1]], out_shape, **kw)
    return inputs + weights // groups


def flop_counter() -> FlopCounterMode:
    return FlopCounterMode(display=False,
                           custom_mapping={torch.ops.aten.convolution_backward: _grouped_conv_backward_flop})


def network(kind: str, preset: str, grid: tuple[int, int], recipes: str = "") -> torch.nn.Module:
    """``kind`` at ``preset``, or (``recipes``) as its recipe file builds it."""
    overrides = {}
    if recipes:
        cfg = config_of(load_recipe(os.path.join(recipes, f"{kind}-{preset}.toml")))
        overrides = {"prior": cfg.prior, "inputs": cfg.inputs}
        if cfg.geometry_channels >= 0:
            overrides["geometry_channels"] = cfg.geometry_channels
    torch.manual_seed(0)
    return build(kind, preset, *grid, **overrides).to(memory_format=torch.channels_last)


def batch(n: int, grid: tuple[int, int], k: int, n_in: int = 3) -> tuple[torch.Tensor, ...]:
    """Sparse sonar-like frames and commands within the robot's limits."""
    g = torch.Generator().manual_seed(1)
    shape = (n, n_in, *grid)
    frames = (torch.rand(shape, generator=g) * (torch.rand(shape, generator=g) > 0.88)).contiguous(
        memory_format=torch.channels_last)
    commands = (torch.rand((n, n_in + k, 2), generator=g) * 2 - 1) * torch.tensor([0.3, 1.0])
    tshape = (n, k, *grid)
    return frames, commands, torch.rand(tshape, generator=g) * (torch.rand(tshape, generator=g) > 0.88)


def gflop_per_sample(model: torch.nn.Module, grid: tuple[int, int], k: int, n: int = 2) -> float:
    """Forward and backward of one training step with a ``k``-step rollout, per window."""
    frames, commands, targets = batch(n, grid, k)
    with flop_counter() as counter:
        weighted_loss(rollout_losses(model, frames, commands, targets, {"mse": 1.0})).backward()
    model.zero_grad(set_to_none=True)
    return counter.get_total_flops() / n / 1e9


def samples_per_s(model: torch.nn.Module, grid: tuple[int, int], k: int, n: int, steps: int, precision: str,
                  terms: dict[str, float] | None = None) -> float:
    """Full optimizer steps (forward, backward, Adam) as the trainer takes them, with the loss
    ``terms`` (default MSE; a term against the flow baseline uses the network's ``flow_prior``, the
    ``echo`` term the default sensor's matching tolerance on this grid, as training does)."""
    opt = torch.optim.Adam(model.parameters(), lr=1e-5, weight_decay=1e-4)
    frames, commands, targets = batch(n, grid, k)
    terms = terms or {"mse": 1.0}
    echo_window = tolerance_bins(SensorGrid.default().model_copy(update={"n_range": grid[0], "n_azimuth": grid[1]}))
    flow = getattr(model, "flow_prior", None) if any(t in REFERENCE_TERMS for t in terms) else None

    def step() -> None:
        loss = weighted_loss(rollout_losses(model, frames, commands, targets, terms, precision=precision, flow=flow,
                                            echo_window=echo_window))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    step()  # warm-up: oneDNN picks its kernels
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return steps * n / (time.perf_counter() - t0)


def matmul_tflops(dtype: torch.dtype, n: int, seconds: float = 0.5, bursts: int = 3) -> float:
    """The roof: TFLOP/s of repeated n x n torch.matmul in ``dtype`` (bf16: what autocast's products
    run in), the best of ``bursts``: on a shared machine the fastest is the closest to the hardware's."""
    a, b = torch.rand(n, n, dtype=dtype), torch.rand(n, n, dtype=dtype)
    torch.matmul(a, b)
    best = 0.0
    for _ in range(bursts):
        reps, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            torch.matmul(a, b)
            reps += 1
        best = max(best, 2 * n ** 3 * reps / (time.perf_counter() - t0) / 1e12)
    return best


def main() -> None:
    keep_freed_memory()  # as the CLI does (cli/app.py): without it each step's activations are fresh page faults
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--preset", default="small")
    ap.add_argument("--grid", default="200x90", help="range x azimuth bins")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=3, help="timed optimizer steps per measurement (after one warm-up)")
    ap.add_argument("--k", type=int, default=3, help="rollout steps of the multi-step measurements")
    ap.add_argument("--matmul", type=int, default=2048, help="size of the roof's square matmul")
    ap.add_argument("--out", default="bench_zoo.json")
    ap.add_argument("--recipes", default="", help="build each kind as DIR/KIND-PRESET.toml does (e.g. recipes/zoo)")
    args = ap.parse_args()
    grid = tuple(int(x) for x in args.grid.split("x"))
    precisions = ["fp32"] + (["bf16"] if cpu_bf16_flags() and torch.backends.mkldnn.is_available() else [])
    roof = {p: matmul_tflops(torch.float32 if p == "fp32" else torch.bfloat16, args.matmul) for p in ("fp32", "bf16")}
    print(f"# bench_zoo  {platform.node()}  {os.cpu_count()} cores  torch {torch.__version__}  "
          f"{torch.get_num_threads()} threads  preset {args.preset}  grid {grid[0]}x{grid[1]}  batch {args.batch}")
    print(f"# CPU bf16 flags: {', '.join(cpu_bf16_flags()) or 'none'}; matmul roof ({args.matmul}^2): "
          f"fp32 {roof['fp32']:.3f} TFLOP/s, bf16 {roof['bf16']:.3f} TFLOP/s")
    print(f"{'kind':9s} {'M params':>8s} {'GFLOP/sample':>14s} " + " ".join(
        f"{p + ' k=' + str(k) + ' samples/s (% roof)':>28s}" for p in precisions for k in (1, args.k)))
    kinds = args.kinds.split(",")
    if args.recipes:  # the zoo's recipes are its reference methods: EchoWarp trains by its own (recipes/echowarp/)
        missing = [k for k in kinds if not os.path.exists(os.path.join(args.recipes, f"{k}-{args.preset}.toml"))]
        if missing:
            print(f"# no {args.preset} recipe in {args.recipes} for {', '.join(missing)}: skipped")
        kinds = [k for k in kinds if k not in missing]
    rows = []
    for kind in kinds:
        model = network(kind, args.preset, grid, args.recipes)
        flops = {k: gflop_per_sample(model, grid, k) for k in (1, args.k)}
        row = {"kind": kind, "params": sum(p.numel() for p in model.parameters()),
               "gflop_per_sample": {str(k): v for k, v in flops.items()}, "training": []}
        for precision in precisions:
            for k in (1, args.k):
                rate = samples_per_s(model, grid, k, args.batch, args.steps, precision)
                achieved = flops[k] * rate  # GFLOP/s
                row["training"].append({"precision": precision, "k": k, "samples_per_s": rate, "gflop_per_s": achieved,
                                        "roof_share": achieved / 1e3 / roof[precision]})
        rows.append(row)
        cells = " ".join(f"{t['samples_per_s']:19.1f} ({100 * t['roof_share']:4.1f}%)" for t in row["training"])
        print(f"{kind:9s} {row['params'] / 1e6:8.2f} {flops[1]:6.2f} / {flops[args.k]:5.2f} {cells}", flush=True)
    print(f"# GFLOP/sample: forward + backward of one training window, one-step / {args.k}-step rollout")
    result = {"bench": "bench_zoo", "date": time.strftime("%Y-%m-%d"), "host": platform.node(),
              "cores": os.cpu_count(), "threads": torch.get_num_threads(), "torch": torch.__version__,
              "preset": args.preset, "recipes": args.recipes, "grid": list(grid), "batch": args.batch, "steps": args.steps,
              "k": args.k,
              "cpu_bf16_flags": list(cpu_bf16_flags()), "matmul_tflops": roof, "models": rows}
    with open(args.out, "w") as f:
        json.dump(result, f, indent=2)
    print(f"# wrote {args.out}")


if __name__ == "__main__":
    main()
