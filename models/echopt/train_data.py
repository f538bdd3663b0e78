"""Where training's windows come from: every frame in memory (``MemoryWindows``), or streamed from
the store (``StreamedWindows``, ``TrainConfig.stream``). Both give the trainer the same things: the
training windows batch by batch (each a function of the rollout length k), the validation windows
and their batcher, and the epoch's length in steps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
import torch

from sonarset.errors import SonarSetError
from sonarset.store.store import SonarStore
from sonarset.stream import batches_per_rank, window_bank
from sonarset.torchdata import StreamingLoader, StreamingWindowDataset, torch_batcher
from sonarset.windows import FrameBank, RunLayout, WindowBatcher, WindowIndex

from sonarset.models.echopt.distributed import Dist
from sonarset.models.echopt.train_config import TrainConfig



def held_out(index: WindowIndex, store: SonarStore, cfg: TrainConfig) -> tuple[WindowIndex, WindowIndex]:
    """``index`` split into training and ``cfg.n_val`` validation windows; SonarSetError naming the
    store when its training runs hold no window, or too few for the validation set."""
    if len(index) == 0:
        raise SonarSetError(f"{store.location}: no training run is long enough for one window "
                            f"({index.n_in} input frames and the {index.horizon} ahead)")
    if not 0 < cfg.n_val < len(index):
        raise SonarSetError(f"{store.location}: its training runs hold {len(index)} windows, too few to hold out "
                            f"n_val {cfg.n_val} for validation and train on the rest", parameter="n_val")
    return index.split(cfg.n_val, seed=cfg.seed)

@dataclass
class MemoryWindows:
    """Every frame of the training runs in memory (on the training device), each batch one gather:
    every process draws the same global batch order from (seed, epoch) and takes its slice."""

    run_names: list[str]
    batcher: WindowBatcher
    train_idx: WindowIndex
    val_idx: WindowIndex
    batch_size: int
    seed: int
    dist: Dist

    @classmethod
    def make(cls, store: SonarStore, cfg: TrainConfig, n_in: int, horizon: int, dist: Dist,
             device: str) -> "MemoryWindows":
        bank = FrameBank.from_store(store, split="train", worlds=cfg.world_list())
        train_idx, val_idx = held_out(WindowIndex.build(bank, n_in, horizon), store, cfg)
        return cls(bank.run_names, torch_batcher(bank, device), train_idx, val_idx, cfg.batch_size, cfg.seed, dist)

    @property
    def n_train(self) -> int:
        return len(self.train_idx)

    steps_per_epoch = None  # whole batches of the training windows

    @property
    def val_batcher(self) -> WindowBatcher:
        return self.batcher

    def epoch(self, epoch: int, start: int, steps: int) -> Iterator[Callable[[int], tuple]]:
        """Batches ``start .. steps-1`` of ``epoch``, each a function of the rollout length k."""
        order = np.random.default_rng([self.seed, epoch]).permutation(len(self.train_idx))
        local = self.batch_size // self.dist.world  # this process's slice of each global batch
        for b in range(start, steps):
            which = order[b * self.batch_size:(b + 1) * self.batch_size][self.dist.rank * local:(self.dist.rank + 1) * local]

            def windows(k: int, which=which) -> tuple:
                g = self.batcher.gather(self.train_idx, which, k)
                return g.frames, g.commands, g.targets
            yield windows


def fewer_than_a_batch(location: str, n_train: int, n_val: int, per: str = "") -> SonarSetError:
    """The error of a store too small for one batch: validation takes its windows and their
    overlapping neighbours first, so the count left is what the batch size meets."""
    return SonarSetError(f"{location}: {n_train} training windows (after {n_val} validation windows and the windows "
                         f"overlapping them), fewer than one batch{per}", parameter="batch_size")


@dataclass(frozen=True)
class _Float32On:
    """A gathered NumPy block as a float32 tensor on ``device``: the validation windows are decoded
    on the CPU and only each batch goes to the device (on a GPU too, where in memory every frame is
    held there)."""

    device: torch.device

    def __call__(self, block: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(block).to(self.device).float()


@dataclass
class StreamedWindows:
    """Training windows streamed from the store (``TrainConfig.stream``, sonarset.stream): each process reads
    its own shards, slab by slab through a shuffle buffer, so memory is bounded by the buffer, not
    the store. The validation windows (the same purged split as in memory) are read once and held
    compressed (``window_bank``), each validation batch decoded as it is gathered: the same
    batches, and so the same loss, as in memory."""

    run_names: list[str]
    loader: StreamingLoader
    val_batcher: WindowBatcher
    val_idx: WindowIndex
    n_train: int
    steps_per_epoch: int
    n_in: int
    device: str

    @classmethod
    def make(cls, store: SonarStore, cfg: TrainConfig, n_in: int, horizon: int, dist: Dist,
             device: str) -> "StreamedWindows":
        layout = RunLayout.of(store, split="train", worlds=cfg.world_list())
        train_idx, val_idx = held_out(layout.index(n_in, horizon), store, cfg)
        val_bank = window_bank(store, layout, val_idx)  # packed: a sixth of the frames' bytes
        local = cfg.batch_size // dist.world
        ds = StreamingWindowDataset(layout, train_idx.starts, n_in=n_in, horizon=horizon, batch_size=local,
                                    seed=cfg.seed, shuffle_buffer=cfg.shuffle_buffer, drop_last=True, rank=dist.rank,
                                    world_size=dist.world, **getattr(store, "open_options", {}))
        steps = batches_per_rank(len(train_idx), dist.world, cfg.loader_workers, local)
        if steps == 0:
            raise fewer_than_a_batch(store.location, len(train_idx), cfg.n_val, " per process and loader worker")
        loader = StreamingLoader(ds, cfg.loader_workers, max_batches=steps, convert=False)
        to_device = _Float32On(torch.device(device))
        val_batcher = WindowBatcher(val_bank.images, val_bank.velocity, images_as=to_device, commands_as=to_device)
        return cls(layout.run_names, loader, val_batcher, val_idx, len(train_idx), steps, n_in, device)

    def epoch(self, epoch: int, start: int, steps: int) -> Iterator[Callable[[int], tuple]]:
        self.loader.skip_to(epoch, start)
        for b in self.loader:
            def windows(k: int, b=b) -> tuple:
                to = self.device
                # images as stored (float16) to the device, float32 there
                return (b["frames"].to(to).float(), b["commands"][:, :self.n_in + k].to(to),
                        b["targets"][:, :k].to(to).float())
            yield windows
