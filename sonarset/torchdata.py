"""PyTorch access to windows. Imports torch; ``import sonarset`` alone never does.

The trainer (frames held on its device) and the DataLoader both batch through the one
:class:`~sonarset.windows.WindowBatcher`, configured here to hand out tensors.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import BatchSampler, DataLoader, Dataset, IterableDataset, RandomSampler, SequentialSampler
from torch.utils.data import get_worker_info

from sonarset.errors import SonarSetError
from sonarset.stream import (DEFAULT_SHUFFLE_BUFFER, DEFAULT_SLAB_FRAMES, HeldFrames, ShardPlan, Slab, WindowStream,
                             canonical_order, consumed_per_shard, make_slabs, rank_shard_sizes)
from sonarset.windows import N_IN, FrameBank, RunLayout, WindowBatcher, WindowIndex


@dataclass(frozen=True)
class _RowsOn:
    """Row indices as a tensor on the frames' device (classes, not lambdas: DataLoader workers
    started by spawn pickle the dataset)."""

    device: torch.device

    def __call__(self, rows: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(rows, device=self.device)


@dataclass(frozen=True)
class _HeldRows:
    """Global frame rows as positions among a bank's held frames (a tensor on ``device``)."""

    held: HeldFrames
    device: torch.device | None

    def __call__(self, rows: np.ndarray):
        pos = self.held.positions(rows)
        return pos if self.device is None else torch.as_tensor(pos, device=self.device)


@dataclass(frozen=True)
class _Stored:
    """A view as its own tensor in the stored dtype: a worker sends a tensor's whole storage, so
    the inputs and targets, views of one block, are copied apart first."""

    def __call__(self, block: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(block))


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
    if isinstance(bank.images, HeldFrames):  # some frames only (sonarset.stream.window_bank)
        held = bank.images
        images, velocity = held.held, np.ascontiguousarray(bank.velocity[held.rows])
        if device.type != "cpu":
            images, velocity = torch.from_numpy(images).to(device), torch.from_numpy(velocity).to(device)
        rows = _HeldRows(held, None if device.type == "cpu" else device)
        return WindowBatcher(images, velocity, to_rows=rows, images_as=_As(dtype), commands_as=_As(dtype))
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


class StreamingWindowDataset(IterableDataset):
    """Windows streamed from a store (``sonarset.stream``), batched: for stores bigger than memory.

    Each iteration is one epoch of one shard: the (DDP rank, DataLoader worker) it runs in picks
    its shard, opens the store itself (so DataLoader workers must be started by spawn; a zarr
    store opened before a fork is not safe to use after it), and yields dicts of tensors:
    ``frames`` (B, n_in, R, A), ``commands`` (B, n_in + H, 2), ``targets`` (B, H, R, A) as ``dtype``,
    ``starts`` (B,) the windows' global start frames, and ``shard`` and ``batch`` (its number in
    the shard) for :class:`StreamingLoader`'s order. Shards are disjoint and together hold every
    window once per epoch (with ``drop_last``: all but fewer than ``batch_size`` per shard).

    ``state_dict()`` is the epoch and the batches of each shard handed out so far;
    ``load_state_dict`` makes the next iteration continue there exactly (the skipped batches cost
    no I/O). With DataLoader workers only :class:`StreamingLoader` keeps that count (a plain
    DataLoader's workers count in their own copies), and moves to the next epoch. ``rank`` and
    ``world_size`` default to torch.distributed's when it is initialised (when iterated or sent to
    workers, so the process group may be set up after the dataset is made).
    """

    def __init__(self, layout: RunLayout, starts: np.ndarray, *, n_in: int = N_IN, horizon: int = 1,
                 batch_size: int = 64, seed: int = 0, shuffle_buffer: int = DEFAULT_SHUFFLE_BUFFER,
                 slab_frames: int | None = None, drop_last: bool = False, rank: int | None = None,
                 world_size: int | None = None, dtype: torch.dtype = torch.float32,
                 storage_options: dict | None = None, cache_bytes: int = 0, remote_limits=None):
        if batch_size < 1 or shuffle_buffer < 1:
            raise SonarSetError("batch_size and shuffle_buffer must be >= 1")
        self.layout, self.starts = layout, np.sort(np.asarray(starts, dtype=np.int64))
        self.n_in, self.horizon, self.batch_size, self.seed = n_in, horizon, batch_size, seed
        self.shuffle_buffer, self.drop_last, self.dtype = shuffle_buffer, drop_last, dtype
        self.slab_frames, self.storage_options, self.cache_bytes = slab_frames, storage_options, cache_bytes
        self.remote_limits = remote_limits
        self.rank, self.world_size = rank, world_size
        self._rank_world()  # a rank given must be one of the world's
        self.epoch = 0
        self.consumed: dict[int, int] = {}  # shard -> batches handed out this epoch
        self.images_dtype_in_worker = True  # False: DataLoader workers yield images as stored
        self._slabs: list[Slab] | None = None

    @classmethod
    def from_store(cls, location: str, split: str | None = "train", worlds: Sequence[str] | None = None, *,
                   n_in: int = N_IN, horizon: int = 1, **kwargs) -> "StreamingWindowDataset":
        """Every window of ``split`` (of ``worlds``) of the store at ``location`` (a path or URL)."""
        from sonarset.store.store import open_store

        store = open_store(location, storage_options=kwargs.get("storage_options"), cache_bytes=0,
                           remote_limits=kwargs.get("remote_limits"))
        layout = RunLayout.of(store, split=split, worlds=worlds)
        return cls(layout, layout.index(n_in, horizon).starts, n_in=n_in, horizon=horizon, **kwargs)

    # -- where this process stands -------------------------------------------------------------
    def _rank_world(self) -> tuple[int, int]:
        """(rank, world size): as given, else torch.distributed's where it is initialised, else (0, 1)."""
        if self.rank is not None:
            world = self.world_size if self.world_size is not None else 1
            if not 0 <= self.rank < world:
                raise SonarSetError(f"rank {self.rank} is not one of a world of {world} processes (give world_size)")
            return self.rank, world
        import torch.distributed as dist

        if dist.is_available() and dist.is_initialized():
            return dist.get_rank(), dist.get_world_size()
        return 0, 1

    def slabs(self) -> list[Slab]:
        if self._slabs is None:
            frames = self.slab_frames or DEFAULT_SLAB_FRAMES
            self._slabs = make_slabs(self.layout, self.starts, self.n_in + self.horizon, frames)
        return self._slabs

    def shard_batches(self, workers: int) -> list[int]:
        """Batches of each of this rank's shards per epoch, with ``workers`` DataLoader workers."""
        rank, world = self._rank_world()
        sizes = rank_shard_sizes(len(self.starts), world, workers, rank)
        B = self.batch_size
        return [s // B if self.drop_last else -(-s // B) for s in sizes]

    def set_epoch(self, epoch: int) -> None:
        self.epoch, self.consumed = int(epoch), {}

    def state_dict(self) -> dict:
        return {"epoch": self.epoch, "consumed": {str(k): v for k, v in self.consumed.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.epoch = int(state["epoch"])
        self.consumed = {int(k): int(v) for k, v in state.get("consumed", {}).items()}

    def __getstate__(self) -> dict:
        # pickled in the process that joined the job, for DataLoader workers, which have not: the
        # rank goes with them; the slabs are rebuilt there (cheap, and smaller to send)
        rank, world = self._rank_world()
        return {**self.__dict__, "_slabs": None, "rank": rank, "world_size": world}

    def __iter__(self) -> Iterator[dict]:
        from sonarset.store.store import open_store

        info = get_worker_info()
        workers, worker = (info.num_workers, info.id) if info is not None else (1, 0)
        rank, world = self._rank_world()
        shard, n_shards = rank * workers + worker, world * workers
        store = open_store(self.layout.location, storage_options=self.storage_options, cache_bytes=self.cache_bytes,
                           remote_limits=self.remote_limits)
        plan = ShardPlan.make(self.slabs(), self.epoch, self.seed, shard, n_shards, self.shuffle_buffer)
        skip = self.consumed.get(shard, 0)
        stream = WindowStream(store, self.layout, self.slabs(), self.n_in, self.horizon, self.batch_size, plan,
                              skip_batches=skip, drop_last=self.drop_last)
        # a StreamingLoader's workers send the images as stored (float16: half the bytes between
        # processes) and the loader converts them
        images_as = _As(self.dtype) if self.images_dtype_in_worker or info is None else _Stored()
        for number, b in enumerate(stream, start=skip):
            self.consumed[shard] = number + 1  # this process's copy (the loader keeps the main one)
            yield {"frames": images_as(b.frames), "commands": _As(self.dtype)(b.commands),
                   "targets": images_as(b.targets), "starts": torch.from_numpy(b.starts),
                   "shard": shard, "batch": number}


class StreamingLoader:
    """A DataLoader over a :class:`StreamingWindowDataset` that hands out one epoch per iteration
    in a fixed order, and can be stopped and resumed exactly.

    With ``num_workers`` > 0 the workers are started by spawn (each opens the store itself), read
    their shards in parallel and send the images as stored (``convert=False`` hands them out so);
    batches are handed out round robin over this rank's shards (``sonarset.stream.canonical_order``),
    the order an in-order DataLoader gives, which a resumed epoch keeps too. ``state_dict()`` /
    ``load_state_dict()`` are the dataset's: the epoch and each shard's batches handed out. An epoch
    iterated to its end moves the dataset to the next one.
    """

    def __init__(self, dataset: StreamingWindowDataset, num_workers: int = 0, prefetch_factor: int = 2,
                 max_batches: int | None = None, convert: bool = True):
        self.dataset, self.num_workers, self.prefetch_factor = dataset, int(num_workers), prefetch_factor
        self.max_batches = max_batches  # per epoch (DDP: every rank the same)
        # with workers, images cross processes as stored (float16: half the bytes); ``convert=False``
        # hands them out so (a trainer converts them on its device), else they become dataset.dtype here
        self.convert = convert

    def _first_shard(self) -> int:
        return self.dataset._rank_world()[0] * max(1, self.num_workers)

    def _todo(self) -> list[tuple[int, int]]:
        """(shard, batch number) of the batches this epoch still hands out, in order."""
        first = self._first_shard()
        order = canonical_order(self.dataset.shard_batches(self.num_workers))[:self.max_batches]
        return [(first + w, r) for w, r in order if r >= self.dataset.consumed.get(first + w, 0)]

    def __len__(self) -> int:
        """Batches left in this epoch."""
        return len(self._todo())

    def state_dict(self) -> dict:
        return self.dataset.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.dataset.load_state_dict(state)

    def skip_to(self, epoch: int, taken: int) -> None:
        """Position the loader at batch ``taken`` of ``epoch`` (its canonical order): what a
        training step count says, without a saved loader state."""
        first = self._first_shard()
        done = consumed_per_shard(self.dataset.shard_batches(self.num_workers), taken)
        self.dataset.load_state_dict({"epoch": epoch, "consumed": {first + w: n for w, n in enumerate(done)}})

    def __iter__(self) -> Iterator[dict]:
        ds = self.dataset
        todo = self._todo()
        if self.num_workers:
            loader = DataLoader(ds, batch_size=None, num_workers=self.num_workers, multiprocessing_context="spawn",
                                prefetch_factor=self.prefetch_factor)
            ds.images_dtype_in_worker = False  # pickled so into the workers as they start; converted below
            try:
                it = iter(loader)
            finally:
                ds.images_dtype_in_worker = True
        else:
            it = iter(DataLoader(ds, batch_size=None))
        held: dict[tuple[int, int], dict] = {}
        try:
            for key in todo:
                while key not in held:
                    b = next(it)
                    held[(int(b["shard"]), int(b["batch"]))] = b
                ds.consumed[key[0]] = key[1] + 1
                b = held.pop(key)
                if self.convert:
                    b = {**b, "frames": b["frames"].to(ds.dtype), "targets": b["targets"].to(ds.dtype)}
                yield b
        finally:
            del it  # stops the workers, also when the consumer leaves early
        ds.set_epoch(ds.epoch + 1)
