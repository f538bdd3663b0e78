"""EchoPT behind the evaluation engine's predictor interface (NumPy in, NumPy out): a torch
checkpoint (``echopt:PATH``, ``echopt:pretrained``) or an ONNX export (``echopt:PATH.onnx``,
run by onnxruntime, models/echopt/onnx_runtime.py)."""

from __future__ import annotations

import concurrent.futures as cf

import numpy as np
import torch

from sonarset.format.attrs import SensorGrid

from sonarset.models.echopt.checkpoint import load_checkpoint, resolve
from sonarset.models.echopt.precision import autocast, resolve_device, resolve_precision

#: Windows per forward pass, by device. Measured (bench/bench_infer.py, BENCHMARKS.md): on a CPU
#: samples/s peak at 8-32 windows in fp32 and bf16 and fall for larger batches, whose activations
#: (25 channels of 200 x 90 at the head) leave the caches; a GPU wants large batches.
INFERENCE_BATCH = {"cpu": 16, "cuda": 256}


def inference_batch(device: str) -> int:
    return INFERENCE_BATCH["cuda" if str(device).startswith("cuda") else "cpu"]


class EchoPTPredictor:
    def __init__(self, model, card: dict, grid: SensorGrid, device: str = "cpu", batch_size: int | None = None,
                 precision: str = "auto"):
        self.device = device
        self.precision = resolve_precision(precision, device)
        # channels-last: the convolutions' fast layout in oneDNN and cuDNN (bench_infer: faster
        # from batch 8 on in both precisions)
        self.model = model.to(memory_format=torch.channels_last)
        self.card, self.grid = card, grid
        self.batch_size = batch_size or inference_batch(device)
        self.name = "echopt"
        self.n_in = model.cfg.n_in  # input frames per window, as trained
        self.label = "echopt"  # names the checkpoint in notes: echopt-small, run-small/model

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        out = np.empty((frames.shape[0], *frames.shape[2:]), dtype=np.float32)
        chunks = [slice(lo, lo + self.batch_size) for lo in range(0, len(frames), self.batch_size)]

        def run(sl: slice) -> None:
            f = torch.from_numpy(np.ascontiguousarray(frames[sl], dtype=np.float32)).to(self.device)
            c = torch.from_numpy(np.ascontiguousarray(commands[sl], dtype=np.float32)).to(self.device)
            with torch.no_grad(), autocast(self.device, self.precision):  # both thread-local: set here
                pred = self.model(f.contiguous(memory_format=torch.channels_last), c)
            # energyscapes live in [0, 1]: clamp so that auto-regressive inputs stay in range
            out[sl] = pred.float().clamp_(0, 1).cpu().numpy()

        threads = torch.get_num_threads()
        if self.device != "cpu" or threads == 1 or len(chunks) == 1:
            for sl in chunks:
                run(sl)
            return out
        # On a CPU, one batch per core, each single-threaded, beats every batch spread over all
        # cores: this model's kernels are too small to keep several threads busy (bench_infer:
        # +15-25% on 2 cores). torch's thread count is process-wide, so it is restored after.
        torch.set_num_threads(1)
        try:
            list(self._pool(threads).map(run, chunks))
        finally:
            torch.set_num_threads(threads)
        return out

    def _pool(self, threads: int) -> cf.ThreadPoolExecutor:
        if getattr(self, "_workers", None) is None or self._workers._max_workers != threads:
            self._workers = cf.ThreadPoolExecutor(threads, thread_name_prefix="echopt")
        return self._workers


def load_echopt_predictor(spec: str, grid: SensorGrid, device: str = "cpu", precision: str = "auto") -> EchoPTPredictor:
    """The predictor of a checkpoint spec: ``pretrained``, a directory or a ``.safetensors`` path
    (ONNX exports: registry.make_predictor routes them to onnx_runtime, without torch)."""
    dev = resolve_device(device)
    model, card = load_checkpoint(spec, grid, dev)
    p = EchoPTPredictor(model, card, grid, dev, precision=precision)
    path = resolve(spec)
    p.label = path.stem if path.stem.startswith("echopt") else f"echopt {path.parent.name}/{path.stem}"
    return p
