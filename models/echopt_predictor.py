"""EchoPT behind the evaluation engine's predictor interface (NumPy in, NumPy out): a torch
checkpoint (``echopt:PATH``, ``echopt:pretrained``) or an ONNX export (``echopt:PATH.onnx``,
run by onnxruntime, models/onnx_runtime.py)."""

from __future__ import annotations

import numpy as np
import torch

from sonarset.schema import SensorGrid

from .checkpoint import load_checkpoint, resolve, resolve_device
from .precision import autocast, resolve_precision

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

    @torch.no_grad()
    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        out = np.empty((frames.shape[0], *frames.shape[2:]), dtype=np.float32)
        for lo in range(0, len(frames), self.batch_size):
            f = torch.from_numpy(np.ascontiguousarray(frames[lo:lo + self.batch_size], dtype=np.float32)).to(self.device)
            c = torch.from_numpy(np.ascontiguousarray(commands[lo:lo + self.batch_size], dtype=np.float32)).to(self.device)
            with autocast(self.device, self.precision):
                pred = self.model(f.contiguous(memory_format=torch.channels_last), c)
            # energyscapes live in [0, 1]: clamp so that auto-regressive inputs stay in range
            out[lo:lo + len(f)] = pred.float().clamp_(0, 1).cpu().numpy()
        return out


def load_echopt_predictor(spec: str, grid: SensorGrid, device: str = "cpu", precision: str = "auto"):
    """The predictor of a checkpoint spec: ``pretrained``, a directory, a ``.safetensors`` path, or
    an ONNX export (``.onnx``: onnxruntime, whose precision is the graph's, fp32)."""
    if str(spec).endswith(".onnx"):
        from .onnx_runtime import load_onnx_predictor

        return load_onnx_predictor(spec, grid)
    dev = resolve_device(device)
    model, card = load_checkpoint(spec, grid, dev)
    p = EchoPTPredictor(model, card, grid, dev, precision=precision)
    path = resolve(spec)
    p.label = path.stem if path.stem.startswith("echopt") else f"echopt {path.parent.name}/{path.stem}"
    return p
