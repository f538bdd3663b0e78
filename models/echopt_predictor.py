"""EchoPT behind the evaluation engine's predictor interface (NumPy in, NumPy out)."""

from __future__ import annotations

import numpy as np
import torch

from sonarset.schema import SensorGrid

from .checkpoint import load_checkpoint, resolve, resolve_device


class EchoPTPredictor:
    def __init__(self, model, card: dict, grid: SensorGrid, device: str = "cpu", batch_size: int = 128):
        self.model, self.card, self.grid = model, card, grid
        self.device, self.batch_size = device, batch_size
        self.name = "echopt"
        self.n_in = model.cfg.n_in  # input frames per window, as trained
        self.label = "echopt"  # names the checkpoint in notes: echopt-small, run-small/model

    @torch.no_grad()
    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        out = np.empty((frames.shape[0], *frames.shape[2:]), dtype=np.float32)
        for lo in range(0, len(frames), self.batch_size):
            f = torch.from_numpy(np.ascontiguousarray(frames[lo:lo + self.batch_size], dtype=np.float32)).to(self.device)
            c = torch.from_numpy(np.ascontiguousarray(commands[lo:lo + self.batch_size], dtype=np.float32)).to(self.device)
            # energyscapes live in [0, 1]: clamp so that auto-regressive inputs stay in range
            out[lo:lo + len(f)] = self.model(f, c).clamp_(0, 1).float().cpu().numpy()
        return out


def load_echopt_predictor(spec: str, grid: SensorGrid, device: str = "cpu") -> EchoPTPredictor:
    dev = resolve_device(device)
    model, card = load_checkpoint(spec, grid, dev)
    p = EchoPTPredictor(model, card, grid, dev)
    path = resolve(spec)
    p.label = path.stem if path.stem.startswith("echopt") else f"echopt {path.parent.name}/{path.stem}"
    return p
