"""PyTorch access to windows. Imports torch; ``import sonarset`` alone never does.

The trainer (frames held on its device) and the DataLoader both batch through the one
:class:`~sonarset.windows.WindowBatcher`, configured here to hand out tensors.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch.utils.data import BatchSampler, DataLoader, Dataset, RandomSampler, SequentialSampler

from sonarset.windows import FrameBank, WindowBatcher, WindowIndex


@dataclass(frozen=True)
class _RowsOn:
    """Row indices as a tensor on the frames' device (classes, not lambdas: DataLoader workers
    started by spawn pickle the dataset)."""

    device: torch.device

    def __call__(self, rows: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(rows, device=self.device)


@dataclass(frozen=True)
class _As:
    """A gathered block as a tensor of ``dtype`` (NumPy blocks without a copy)."""

    dtype: torch.dtype

    def __call__(self, block: np.ndarray | torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(block).to(self.dtype)


def torch_batcher(bank: FrameBank, device: str | torch.device = "cpu",
                  dtype: torch.dtype = torch.float32) -> WindowBatcher:
    """Batches of ``dtype`` tensors on ``device``.

    On a GPU the frames are held there in their stored dtype (float16 stays float16: half the
    memory) and each batch is gathered there; on the CPU NumPy gathers each batch from the bank
    (faster than torch indexing) and the block becomes a tensor without a copy.
    """
    device = torch.device(device)
    if device.type == "cpu":
        return WindowBatcher(bank.images, bank.velocity, images_as=_As(dtype), commands_as=_As(dtype))
    images = torch.from_numpy(bank.images).to(device)
    velocity = torch.from_numpy(bank.velocity).to(device)
    return WindowBatcher(images, velocity, to_rows=_RowsOn(device), images_as=_As(dtype), commands_as=_As(dtype))


class SonarWindowDataset(Dataset):
    """Map-style dataset of windows held in memory.

    ``ds[k]`` gives one window as a dict of tensors: ``frames`` (n_in, R, A), ``commands``
    (n_in+H, 2), ``targets`` (H, R, A). ``ds[[k1, k2, ...]]`` gives a whole batch with a leading
    batch axis in one gather, which :func:`make_loader` uses to skip per-sample collation.
    """

    def __init__(self, bank: FrameBank, index: WindowIndex, dtype: torch.dtype = torch.float32):
        self.bank, self.index, self.dtype = bank, index, dtype
        self.batcher = torch_batcher(bank, "cpu", dtype)

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, k: int | Sequence[int] | np.ndarray) -> dict[str, torch.Tensor]:
        single = np.isscalar(k) or (isinstance(k, np.ndarray) and k.ndim == 0)
        raw = np.atleast_1d(np.asarray(k))
        # an index is a whole number: ds[1.7] must not quietly read window 1, nor ds[True] window 1
        if raw.dtype.kind not in "iu" and not (raw.dtype.kind == "f" and raw.size == 0):
            raise TypeError(f"window indices must be integers, got {raw.dtype} ({k!r:.60})")
        which = raw.astype(np.int64)
        if which.size and (which.min() < -len(self) or which.max() >= len(self)):
            raise IndexError(f"window index out of range for {len(self)} windows")
        batch = self.batcher.gather(self.index, which)
        out = {"frames": batch.frames, "commands": batch.commands, "targets": batch.targets}
        return {k2: v[0] for k2, v in out.items()} if single else out


def make_loader(dataset: SonarWindowDataset, batch_size: int = 64, *, shuffle: bool = True,
                seed: int = 0, drop_last: bool = False, num_workers: int = 0) -> DataLoader:
    """A DataLoader that fetches each batch with one vectorised gather (no per-sample collate)."""
    generator = torch.Generator().manual_seed(seed)
    base = RandomSampler(dataset, generator=generator) if shuffle else SequentialSampler(dataset)
    sampler = BatchSampler(base, batch_size=batch_size, drop_last=drop_last)
    # batch_size=None turns off automatic batching: each sampled *list* goes to __getitem__.
    return DataLoader(dataset, sampler=sampler, batch_size=None, num_workers=num_workers)
