"""Inference speed of EchoPT (or EchoWarp: ``--model echowarp:RUN``): torch fp32, torch bf16
autocast and onnxruntime, in one run.

    python bench/bench_infer.py [--model pretrained] [--batches 1,16,128] [--threads 1,2] [--seconds 2]
                                [--opsets 18,20]

Samples/s for every (engine, threads, batch), each the median of ``--rounds`` rounds in which the
engines take turns (a noisy machine slows all of them alike, so the ratios to torch fp32 hold);
then batch-1 latency p50/p99 on one thread (a robot's control loop: the goal is <= 10 ms); then
the predictor as evaluation runs it (NumPy windows, batches of ``INFERENCE_BATCH``, one
single-threaded batch per core). Inputs are sparse like the default 'ertis' images (~12% of
pixels lit). Channels-last is measured against the default layout in fp32 and bf16. For a model
that forecasts each horizon directly (EchoWarp), last: its forecast to ten steps against
``forecast_at`` the scored horizons alone, as the evaluation asks for them. With ``--opsets``, also
onnxruntime's batch-1 latency with the graph exported at each ONNX opset, in alternated rounds.
"""

from __future__ import annotations

import argparse
import copy
import os
import platform
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from sonarset.models.echopt.checkpoint import load_checkpoint
from sonarset.models.echopt.config import make_config
from sonarset.models.echopt.networks import KINDS
from sonarset.models.echopt.model import EchoPT
from sonarset.models.echopt.predictor import INFERENCE_BATCH, EchoPTPredictor
from sonarset.models.echopt.onnx_export import random_windows
from sonarset.models.echopt.precision import cpu_bf16_flags, resolve_precision

warnings.filterwarnings("ignore", message="Using padding='same'")


def torch_engine(model: EchoPT, bf16: bool, channels_last: bool = True):
    m = copy.deepcopy(model).to(memory_format=torch.channels_last if channels_last else torch.contiguous_format)

    def run(frames: torch.Tensor, commands: torch.Tensor) -> None:
        x = frames.contiguous(memory_format=torch.channels_last) if channels_last else frames
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            m(x, commands)

    return run


def onnx_engine(path: Path, threads: int):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads, opts.inter_op_num_threads = threads, 1
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    # a direct forecaster's graph (EchoWarp) takes the horizons: the next frame's, as torch's forward
    extra = {"horizons": np.array([1], np.int64)} if len(sess.get_inputs()) == 3 else {}

    def run(frames: torch.Tensor, commands: torch.Tensor) -> None:
        sess.run(None, {"frames": frames.numpy(), "commands": commands.numpy(), **extra})

    return run


def rate(run, frames, commands, seconds: float) -> float:
    run(frames, commands)  # warm-up: kernels and primitive caches
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        run(frames, commands)
        n += 1
    return n * len(frames) / (time.perf_counter() - t0)


def latencies(run, frames, commands, calls: int) -> np.ndarray:
    run(frames, commands)
    out = np.empty(calls)
    for i in range(calls):
        t0 = time.perf_counter()
        run(frames, commands)
        out[i] = time.perf_counter() - t0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="pretrained", help="checkpoint spec, or a preset name with --random")
    ap.add_argument("--random", action="store_true", help="a randomly initialised model of preset --model")
    ap.add_argument("--batches", default="1,16,128")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--seconds", type=float, default=1.5, help="per measurement")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--latency-calls", type=int, default=300)
    ap.add_argument("--opsets", default="", help="also onnxruntime's batch-1 latency at each of these ONNX opsets")
    args = ap.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    thread_counts = [int(t) for t in args.threads.split(",")]
    if args.random:
        torch.manual_seed(0)
        model = EchoPT(make_config(args.model)).eval()
    else:  # a checkpoint spec, KIND:PATH for another kind than EchoPT (echowarp:runs/echowarp-small)
        kind, sep, path = args.model.partition(":")
        model = load_checkpoint(path, kind=kind)[0] if sep and kind in KINDS else load_checkpoint(args.model)[0]
    print(f"# bench_infer  {platform.node()}  {platform.processor() or platform.machine()}  {os.cpu_count()} cores  "
          f"torch {torch.__version__}  CPU bf16 flags: {', '.join(cpu_bf16_flags()) or 'none'} "
          f"(auto -> {resolve_precision('auto', 'cpu')})  {time.strftime('%Y-%m-%d')}")
    print(f"# model {args.model}{' (random init)' if args.random else ''}: {model.n_params() / 1e6:.2f} M parameters, "
          f"grid {model.cfg.n_range} x {model.cfg.n_azimuth}")
    onnx_path = None
    try:
        import onnxruntime  # noqa: F401

        from sonarset.models.echopt.onnx_export import export_onnx

        if not args.random:
            onnx_path = Path(tempfile.mkdtemp()) / "model.onnx"
            export_onnx(args.model, onnx_path)
    except (ImportError, Exception) as exc:  # noqa: BLE001  the bench goes on without onnxruntime
        print(f"# onnxruntime column skipped: {exc}")
        onnx_path = None

    engines = {"torch fp32": lambda t: torch_engine(model, False), "torch bf16": lambda t: torch_engine(model, True),
               "torch fp32 NCHW": lambda t: torch_engine(model, False, False),
               "torch bf16 NCHW": lambda t: torch_engine(model, True, False)}
    if onnx_path is not None:
        engines["onnxruntime"] = lambda t: onnx_engine(onnx_path, t)
    print("\n## samples/s (median of rounds; ratio to torch fp32 channels-last at the same threads and batch)\n")
    print("| engine | threads | " + " | ".join(f"batch {b}" for b in batches) + " |")
    print("|---|---|" + "---|" * len(batches))
    for threads in thread_counts:
        torch.set_num_threads(threads)
        made = {name: make(threads) for name, make in engines.items()}
        table = {name: {} for name in made}
        for b in batches:
            frames, commands = random_windows(model, b, seed=b)
            runs = {name: [] for name in made}
            for _ in range(args.rounds):
                for name, run in made.items():
                    runs[name].append(rate(run, frames, commands, args.seconds / args.rounds))
            for name in made:
                table[name][b] = statistics.median(runs[name])
        for name in made:
            cells = [f"{table[name][b]:.0f} ({table[name][b] / table['torch fp32'][b]:.2f}x)" for b in batches]
            print(f"| {name} | {threads} | " + " | ".join(cells) + " |")
        sys.stdout.flush()

    print("\n## batch-1 latency, 1 thread (ms)\n")
    print("| engine | p50 | p99 | max |")
    print("|---|---|---|---|")
    torch.set_num_threads(1)
    frames, commands = random_windows(model, 1, seed=7)
    for name, make in engines.items():
        if "NCHW" in name:
            continue
        lat = latencies(make(1), frames, commands, args.latency_calls) * 1e3
        print(f"| {name} | {np.percentile(lat, 50):.2f} | {np.percentile(lat, 99):.2f} | {lat.max():.2f} |")

    threads = max(thread_counts)
    torch.set_num_threads(threads)
    print(f"\n## the predictor as evaluation runs it ({threads} threads, 128 NumPy windows, batches of "
          f"{INFERENCE_BATCH['cpu']})\n")
    frames, commands = (t.numpy() for t in random_windows(model, 128, seed=3))
    print("| precision | samples/s |")
    print("|---|---|")
    for precision in ("fp32", "bf16"):
        p = EchoPTPredictor(model, {}, None, "cpu", precision=precision)
        print(f"| {precision} | {rate(lambda f, c, p=p: p.predict(f, c), frames, commands, args.seconds):.0f} |")
    if callable(getattr(model, "forecast_at", None)):
        scored_horizons(model, args.rounds)
    if args.opsets and onnx_path is not None:
        opset_latency(args.model, model, [int(o) for o in args.opsets.split(",")], args.rounds, args.latency_calls)


def opset_latency(spec: str, model, opsets: list[int], rounds: int, calls: int) -> None:
    """onnxruntime's batch-1 latency on one thread with the checkpoint exported at each opset, the
    graphs taking turns round by round, and each export's difference from torch."""
    from sonarset.models.echopt.onnx_export import export_onnx

    folder = Path(tempfile.mkdtemp())
    exports = {o: export_onnx(spec, folder / f"opset{o}.onnx", opset=o) for o in opsets}
    runs = {o: onnx_engine(e.path, 1) for o, e in exports.items()}
    frames, commands = random_windows(model, 1, seed=7)
    lat = {o: [] for o in opsets}
    for _ in range(rounds):
        for o, run in runs.items():
            lat[o].extend(latencies(run, frames, commands, max(1, calls // rounds)) * 1e3)
    first = np.percentile(lat[opsets[0]], 50)
    print(f"\n## onnxruntime batch-1 latency by ONNX opset, 1 thread ({rounds} alternated rounds)\n")
    print(f"| opset | p50 ms | p99 ms | opset {opsets[0]}'s p50 / this | max abs difference from torch |")
    print("|---|---|---|---|---|")
    for o in opsets:
        p50 = np.percentile(lat[o], 50)
        print(f"| {o} | {p50:.2f} | {np.percentile(lat[o], 99):.2f} | {first / p50:.2f}x | {exports[o].max_abs_diff:.1e} |")


def scored_horizons(model, rounds: int, windows: int = 64, horizons: tuple[int, ...] = (1, 3, 5, 10)) -> None:
    """A direct forecaster (EchoWarp) as the evaluation runs it: its whole forecast to the longest
    horizon against ``forecast_at`` the scored horizons alone, in alternating rounds, bf16 where auto
    picks it."""
    from sonarset.models.echopt.predictor import DirectForecastPredictor

    precision = resolve_precision("auto", "cpu")
    p = DirectForecastPredictor(model, {}, None, "cpu", precision=precision)
    rng = np.random.default_rng(5)
    shape = (windows, model.cfg.n_in, model.cfg.n_range, model.cfg.n_azimuth)
    frames = (rng.random(shape) * (rng.random(shape) > 0.88)).astype(np.float32)
    commands = (rng.uniform(-1, 1, (windows, model.cfg.n_in + horizons[-1], 2)) * [0.3, 1.0]).astype(np.float32)
    times = {"whole": [], "scored": []}
    for _ in range(rounds):
        t0 = time.perf_counter()
        whole = p.rollout(frames, commands, horizons[-1])[:, [h - 1 for h in horizons]]
        t1 = time.perf_counter()
        scored = p.forecast_at(frames, commands, horizons)
        times["whole"].append(t1 - t0)
        times["scored"].append(time.perf_counter() - t1)
    w, s = statistics.median(times["whole"]), statistics.median(times["scored"])
    print(f"\n## the scored horizons alone ({windows} windows, {precision}, {torch.get_num_threads()} threads)\n")
    print(f"forecast to {horizons[-1]} steps {w:.2f} s; forecast_at {horizons} {s:.2f} s ({w / s:.2f}x); "
          f"max |difference| at those steps {np.abs(whole - scored).max():.1e}")


if __name__ == "__main__":
    main()
