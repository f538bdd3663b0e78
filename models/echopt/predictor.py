"""A trained network behind the evaluation engine's predictor interface (NumPy in, NumPy out):
EchoPT or a reference method (models/zoo/) from a torch checkpoint (``KIND:PATH``,
``echopt:pretrained``), or EchoPT from an ONNX export (``echopt:PATH.onnx``, run by onnxruntime,
models/echopt/onnx_runtime.py)."""

from __future__ import annotations

import concurrent.futures as cf
from typing import Callable

import numpy as np
import torch

from sonarset.format.attrs import SensorGrid

from sonarset.models.echopt.checkpoint import load_checkpoint, resolve
from sonarset.models.echopt.losses import forecaster
from sonarset.models.echopt.networks import kind_of
from sonarset.models.echopt.precision import autocast, resolve_device, resolve_precision
from sonarset.models.predictor import BasePredictor, block_rollout, checked_horizons, rollout_steps

#: Windows per forward pass, by device. Measured (bench/bench_infer.py, BENCHMARKS.md): on a CPU
#: samples/s peak at 8-32 windows in fp32 and bf16 and fall for larger batches, whose activations
#: (25 channels of 200 x 90 at the head) leave the caches; a GPU wants large batches.
INFERENCE_BATCH = {"cpu": 16, "cuda": 256}


def inference_batch(device: str) -> int:
    return INFERENCE_BATCH["cuda" if str(device).startswith("cuda") else "cpu"]


class LearnedPredictor(BasePredictor):
    """A trained network of any kind as a predictor (models/predictor.py's protocol; its rollout
    chains ``predict``); its ``name`` is the kind (echopt, convlstm, ...)."""

    def __init__(self, model, card: dict, grid: SensorGrid, device: str = "cpu", batch_size: int | None = None,
                 precision: str = "auto"):
        self.device = device
        self.precision = resolve_precision(precision, device)
        # channels-last: the convolutions' fast layout in oneDNN and cuDNN (bench_infer: faster
        # from batch 8 on in both precisions)
        self.model = model.to(memory_format=torch.channels_last)
        self.card, self.grid = card, grid
        self.batch_size = batch_size or inference_batch(device)
        self.name = kind_of(model)
        self.n_in = model.cfg.n_in  # input frames per window, as trained
        self.label = self.name  # names the checkpoint in notes: echopt-small, run-small/model

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        out = np.empty((frames.shape[0], *frames.shape[2:]), dtype=np.float32)
        self._chunked(frames, commands, lambda f, c: self.model(f, c), out)
        return out

    def _chunked(self, frames: np.ndarray, commands: np.ndarray, step: Callable, out: np.ndarray,
                 batch_size: int | None = None) -> None:
        """``out[chunk] = step(frames, commands)`` of each chunk of ``batch_size`` windows (default:
        the predictor's), clamped."""
        size = batch_size or self.batch_size
        chunks = [slice(lo, lo + size) for lo in range(0, len(frames), size)]

        def run(sl: slice) -> None:
            f = torch.from_numpy(np.ascontiguousarray(frames[sl], dtype=np.float32)).to(self.device)
            c = torch.from_numpy(np.ascontiguousarray(commands[sl], dtype=np.float32)).to(self.device)
            with torch.no_grad(), autocast(self.device, self.precision):  # both thread-local: set here
                pred = step(f.contiguous(memory_format=torch.channels_last), c)
            # energyscapes live in [0, 1]: clamp so that auto-regressive inputs stay in range
            out[sl] = pred.float().clamp_(0, 1).cpu().numpy()

        threads = torch.get_num_threads()
        if self.device != "cpu" or threads == 1 or len(chunks) == 1:
            for sl in chunks:
                run(sl)
            return
        # On a CPU, one batch per core, each single-threaded, beats every batch spread over all
        # cores: these models' kernels are too small to keep several threads busy (bench_infer:
        # +15-25% on 2 cores). torch's thread count is process-wide, so it is restored after.
        torch.set_num_threads(1)
        try:
            list(self._pool(threads).map(run, chunks))
        finally:
            torch.set_num_threads(threads)

    def _pool(self, threads: int) -> cf.ThreadPoolExecutor:
        if getattr(self, "_workers", None) is None or self._workers._max_workers != threads:
            self._workers = cf.ThreadPoolExecutor(threads, thread_name_prefix=self.name)
        return self._workers


#: The name the predictor had when EchoPT was the only learned model.
EchoPTPredictor = LearnedPredictor


class ForecastPredictor(LearnedPredictor):
    """A network that forecasts several steps in one pass (SimVP): its ``rollout`` is that forecast,
    in blocks of up to its ``max_horizon`` steps, each block's context the previous block's last
    predictions; ``predict`` is its first step."""

    def __init__(self, model, card: dict, grid: SensorGrid, device: str = "cpu", batch_size: int | None = None,
                 precision: str = "auto"):
        super().__init__(model, card, grid, device, batch_size, precision)
        # a forecast is max_horizon images per window at once: the device's batch counts images, so
        # that a chunk's activations stay in cache (EchoWarp on 2 cores: 27 ms per ten-step window in
        # chunks of 2 windows, 52 ms in chunks of 16; BENCHMARKS, "EchoWarp")
        self.forecast_batch = batch_size or max(1, round(self.batch_size / model.max_horizon))

    def rollout(self, frames: np.ndarray, commands: np.ndarray, horizon: int) -> np.ndarray:
        """(B, horizon, R, A) from frames (B, n_in, R, A) and commands (B, n_in + horizon, 2), as
        models.baselines.rollout's contract."""
        return block_rollout(self._forecast, frames, commands, horizon, self.model.max_horizon)

    def _forecast(self, frames: np.ndarray, commands: np.ndarray, m: int) -> np.ndarray:
        out = np.empty((frames.shape[0], m, *frames.shape[2:]), dtype=np.float32)
        self._chunked(frames, commands, lambda f, c: self.model.forecast(f, c, m), out, self.forecast_batch)
        return out


class DirectForecastPredictor(ForecastPredictor):
    """A network that forecasts each horizon from the measured frames, each its own slot of the pass
    (EchoWarp: a ``forecast_at`` method): asked for some horizons, it computes those alone."""

    def forecast_at(self, frames: np.ndarray, commands: np.ndarray, horizons: tuple[int, ...]) -> np.ndarray:
        """(B, len(horizons), R, A): the rollout's frames at ``horizons`` (increasing), with
        commands (B, n_in + horizons[-1], 2), in chunks of as many images as ``rollout``'s; beyond
        ``max_horizon``, whose forecasts chain blocks, the rollout's steps are taken."""
        horizons = checked_horizons(horizons)
        if horizons[-1] > self.model.max_horizon:
            return rollout_steps(self.rollout, frames, commands, horizons)
        out = np.empty((frames.shape[0], len(horizons), *frames.shape[2:]), dtype=np.float32)
        per_chunk = max(1, round(self.forecast_batch * self.model.max_horizon / len(horizons)))
        self._chunked(frames, commands[:, :self.n_in + horizons[-1]],
                      lambda f, c: self.model.forecast_at(f, c, horizons), out, per_chunk)
        return out


def load_learned_predictor(spec: str, grid: SensorGrid, device: str = "cpu", precision: str = "auto",
                           kind: str | None = None) -> LearnedPredictor:
    """The predictor of a checkpoint spec of any kind (``pretrained``, a run directory or a
    ``.safetensors`` path; the card says the kind); with ``kind``, a checkpoint of another kind is
    refused (ONNX exports: the registry routes them to onnx_runtime, without torch)."""
    dev = resolve_device(device)
    model, card = load_checkpoint(spec or "pretrained", grid, dev, kind=kind)
    cls = LearnedPredictor if forecaster(model) is None else (
        DirectForecastPredictor if callable(getattr(model, "forecast_at", None)) else ForecastPredictor)
    p = cls(model, card, grid, dev, precision=precision)
    path = resolve(spec or "pretrained", kind)
    p.label = path.stem if path.stem.startswith(p.name) else f"{p.name} {path.parent.name}/{path.stem}"
    return p


def load_echopt_predictor(spec: str, grid: SensorGrid, device: str = "cpu", precision: str = "auto") -> LearnedPredictor:
    """EchoPT's predictor of a checkpoint spec (``pretrained``, a directory or a ``.safetensors`` path)."""
    return load_learned_predictor(spec or "pretrained", grid, device, precision, kind="echopt")
