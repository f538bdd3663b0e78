"""Streaming windows against the in-memory bank: windows/s, training samples/s and peak memory.

    python bench/bench_stream.py STORE [--seconds 20] [--train-steps 40] [--http]

Every figure comes from its own child process (peak RSS from wait4: the largest of that process and its
DataLoader workers; the largest worker beside it), one at a time:

- **windows**: batches of 64 one-step windows of the 'train' split, read as fast as they come: the
  in-memory path (load every frame, then gather seeded random batches) against the streaming path
  (``StreamingLoader``, 0 and 2 workers), from the local store and, with ``--http``, from the same
  store served on loopback (``python -m http.server`` semantics, no cache: each slab read once).
- **training**: ``sonarset train`` (small preset, batch 64) for ``--train-steps`` steps in memory and
  with ``--stream`` (0 and 2 workers): the samples/s of the steps and the process's peak RSS.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BATCH = 64


def child_windows(store: str, mode: str, workers: int, seconds: float) -> dict:
    """(in a child) windows/s and load time of one reading path."""
    import resource

    import numpy as np

    from sonarset import open_store
    from sonarset.torchdata import StreamingLoader, StreamingWindowDataset, torch_batcher
    from sonarset.windows import FrameBank, WindowIndex

    t0 = time.perf_counter()
    n, first = 0, None
    if mode == "memory":
        bank = FrameBank.from_store(open_store(store), split="train")
        index = WindowIndex.build(bank, 3, 1)
        batcher = torch_batcher(bank)
        rng = np.random.default_rng(0)
        first = time.perf_counter() - t0
        t1 = time.perf_counter()
        while time.perf_counter() - t1 < seconds:
            b = batcher.gather(index, rng.choice(len(index), BATCH, replace=False))
            n += len(b)
    else:
        ds = StreamingWindowDataset.from_store(store, "train", n_in=3, horizon=1, batch_size=BATCH, seed=0)
        t1 = None
        for b in StreamingLoader(ds, num_workers=workers):
            if t1 is None:  # the first batch: start-up (and the workers' spawn) is not throughput
                first, t1 = time.perf_counter() - t0, time.perf_counter()
                continue
            n += len(b["starts"])
            if time.perf_counter() - t1 >= seconds:
                break
    rate = n / (time.perf_counter() - t1)
    return {"windows_per_s": rate, "first_batch_s": first,
            "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "workers_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}


def run_child(args: list[str]) -> tuple[dict | None, float]:
    """Run this script (or a command) as a child; its JSON result and its own peak RSS (MB)."""
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    out, err = proc.stdout.read(), proc.stderr.read()
    if os.waitstatus_to_exitcode(status) != 0:
        print(f"# failed: {' '.join(args)}\n{err[-2000:]}", file=sys.stderr)
        return None, 0.0
    line = [text for text in out.splitlines() if text.startswith("{")]
    return (json.loads(line[-1]) if line else None), usage.ru_maxrss / 1024


def training(store: str, steps: int, stream: bool, workers: int, buffer: int = 0) -> tuple[float, float, float]:
    """(samples/s of the steps, wall s, peak RSS MB) of ``sonarset train`` on ``store``."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "sonarset.cli", "train", store, "--preset", "small", "--out", f"{tmp}/run",
               "--max-steps", str(steps), "--eval-every", str(steps), "--n-val", "256", "--batch-size", str(BATCH),
               "--test-samples", "0", "--device", "cpu"]
        if stream:
            cmd += ["--stream", "--workers", str(workers)] + (["--shuffle-buffer", str(buffer)] if buffer else [])
        t0 = time.perf_counter()
        _, rss = run_child(cmd)
        wall = time.perf_counter() - t0
        log = [json.loads(line) for line in Path(f"{tmp}/run/metrics.jsonl").read_text().splitlines()]
    return log[-1]["samples_per_s"], wall, rss


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("store")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--train-steps", type=int, default=40)
    ap.add_argument("--http", action="store_true", help="also read the store over HTTP on loopback")
    ap.add_argument("--skip-training", action="store_true")
    ap.add_argument("--buffers", default="", help="also train with these --shuffle-buffer sizes, e.g. 1024,8192")
    ap.add_argument("--child", nargs=3, metavar=("MODE", "WORKERS", "LOCATION"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        mode, workers, location = args.child
        print(json.dumps(child_windows(location, mode, int(workers), args.seconds)))
        return

    from sonarset import open_store

    store = open_store(args.store)
    print(f"# bench_stream  {platform.node()}  {os.cpu_count()} cores  python {platform.python_version()}  "
          f"{time.strftime('%Y-%m-%d')}")
    print(f"# {args.store}: {len(store.runs('train'))} training runs, {store.n_frames('train')} frames "
          f"({store.n_frames('train') * store.grid.shape[0] * store.grid.shape[1] * 2 / 2**30:.2f} GiB as float16)")
    print("\n| reading | source | workers | windows/s | ratio to memory | first batch | "
          "peak RSS, largest process | largest worker |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    sources = [("local disk", args.store)]
    server = None
    if args.http:
        from contextlib import ExitStack

        from sonarset.testing import serve_directory

        stack = ExitStack()
        base, _ = stack.enter_context(serve_directory(os.path.dirname(os.path.abspath(args.store))))
        sources.append(("http loopback", f"{base}/{os.path.basename(os.path.abspath(args.store))}"))
        server = stack
    ref = None
    for name, location in sources:
        for mode, workers in (("memory", 0), ("stream", 0), ("stream", 2)):
            if mode == "memory" and name != "local disk":
                continue
            res, rss = run_child([sys.executable, __file__, location, "--seconds", str(args.seconds), "--child", mode,
                                  str(workers), location])
            if res is None:
                continue
            ref = ref or res["windows_per_s"]
            print(f"| {mode} | {name} | {workers} | {res['windows_per_s']:.0f} | {res['windows_per_s'] / ref:.2f}x | "
                  f"{res['first_batch_s']:.1f} s | {rss:.0f} MB | "
                  f"{res['workers_rss_mb']:.0f} MB |", flush=True)
    if server is not None:
        server.close()
    if args.skip_training:
        return
    print(f"\n| training (small, batch {BATCH}, {args.train_steps} steps) | samples/s | ratio | wall | "
          "peak RSS, largest process |")
    print("|---|---:|---:|---:|---:|")
    base_rate = None
    rows = [("in memory", False, 0, 0), ("--stream", True, 0, 0), ("--stream --workers 2", True, 2, 0)]
    rows += [(f"--stream --shuffle-buffer {b}", True, 0, int(b)) for b in args.buffers.split(",") if b]
    for label, stream, workers, buffer in rows:
        rate, wall, rss = training(args.store, args.train_steps, stream, workers, buffer)
        base_rate = base_rate or rate
        print(f"| {label} | {rate:.1f} | {rate / base_rate:.2f}x | {wall:.0f} s | {rss:.0f} MB |", flush=True)


if __name__ == "__main__":
    main()
