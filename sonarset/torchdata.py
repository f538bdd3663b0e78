"""PyTorch access to windows. Imports torch; ``import sonarset`` alone never does."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch.utils.data import BatchSampler, DataLoader, Dataset, RandomSampler, SequentialSampler

from .windows import FrameBank, WindowIndex


class SonarWindowDataset(Dataset):
    """Map-style dataset of windows held in memory.

    ``ds[k]`` gives one window as a dict of tensors: ``frames`` (n_in, R, A), ``commands``
    (n_in+H, 2), ``targets`` (H, R, A). ``ds[[k1, k2, ...]]`` gives a whole batch with a leading
    batch axis in one gather, which :func:`make_loader` uses to skip per-sample collation.
    """

    def __init__(self, bank: FrameBank, index: WindowIndex, dtype: torch.dtype = torch.float32):
        self.bank, self.index, self.dtype = bank, index, dtype

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, k: int | Sequence[int] | np.ndarray) -> dict[str, torch.Tensor]:
        single = np.isscalar(k) or (isinstance(k, np.ndarray) and k.ndim == 0)
        which = np.atleast_1d(np.asarray(k, dtype=np.int64))
        if which.size and (which.min() < -len(self) or which.max() >= len(self)):
            raise IndexError(f"window index out of range for {len(self)} windows")
        rows = self.index.rows(which)
        # One gather and one dtype conversion for inputs and targets together; both are views.
        block = torch.from_numpy(self.bank.images[rows]).to(self.dtype)
        out = {
            "frames": block[:, :self.index.n_in],
            "commands": torch.from_numpy(self.bank.velocity[rows]).to(self.dtype),
            "targets": block[:, self.index.n_in:],
        }
        return {k2: v[0] for k2, v in out.items()} if single else out


def make_loader(dataset: SonarWindowDataset, batch_size: int = 64, *, shuffle: bool = True,
                seed: int = 0, drop_last: bool = False, num_workers: int = 0) -> DataLoader:
    """A DataLoader that fetches each batch with one vectorised gather (no per-sample collate)."""
    generator = torch.Generator().manual_seed(seed)
    base = RandomSampler(dataset, generator=generator) if shuffle else SequentialSampler(dataset)
    sampler = BatchSampler(base, batch_size=batch_size, drop_last=drop_last)
    # batch_size=None turns off automatic batching: each sampled *list* goes to __getitem__.
    return DataLoader(dataset, sampler=sampler, batch_size=None, num_workers=num_workers)
