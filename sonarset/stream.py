"""Windows streamed from a store, for stores bigger than memory (training and evaluation with ``stream``).

The in-memory path (:class:`~sonarset.windows.FrameBank`) decodes every frame of a split first. Here
only the runs' layout is read up front (:class:`~sonarset.windows.RunLayout`, the FrameBank's own
numbering, so a window is the same global start frame in both), and frames are read when they are
needed:

- **Slabs.** A run's windows are grouped by their start frame into slabs of ``slab_frames`` frames
  (by default a multiple of the writer's chunk length, so a slab decodes whole chunks); a slab
  holds the frames of its windows, its own frames plus the ``span - 1`` that its last windows reach
  into. Windows never cross runs, and only the windows given (a split's, less the purged
  validation windows) are in a slab.
- **Shards.** Each epoch the slabs are put in a seeded order and the windows of that order are cut
  into ``n_shards`` contiguous pieces of equal size (within one window): shard ``s`` of an epoch is
  one (DDP rank, DataLoader worker). Shards are disjoint and together hold every window once, and a
  shard's size does not depend on the epoch, so every rank takes the same number of steps.
- **Shuffle buffer.** A shard keeps ``ceil(shuffle_buffer / windows per slab)`` slabs open and draws
  each window uniformly among the open slabs' remaining windows; a slab that runs out is replaced by
  the shard's next one. Memory is bounded by the open slabs (plus those read ahead), not by the store.
- **Determinism.** The order of a shard's windows is a function of (seed, epoch, shard) and the
  layout alone, computed without reading a frame, so skipping the first ``n`` batches of a shard
  (an exact resume mid-epoch) costs no I/O.
- **Drawn windows.** A fixed set of windows read once and gathered many times (a training run's
  validation windows, an evaluation's test windows) is a :func:`window_bank`: only their frames are
  read, a few chunks at a time, and held compressed (:class:`PackedFrames`), so it costs memory in
  proportion to the windows drawn, at a sixth of their frames' size, and never the store's.

NumPy only; ``sonarset.torchdata`` wraps it in a PyTorch ``IterableDataset``.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np
from numcodecs import Blosc

from sonarset.errors import SonarSetError
from sonarset.windows import FrameBank, RunLayout, WindowBatch, WindowIndex

#: Frames of a slab (4 chunks of the writer's 64 frames: 9 MB of float16 on the default grid). A
#: slab also decodes the chunk its last windows reach into, so smaller slabs decode more per window.
DEFAULT_SLAB_FRAMES = 256
#: Windows a shard mixes at once (its open slabs hold about this many frames: ~36 MB of float16 per
#: 1000 on the default grid; the default keeps 8 slabs open and `train --stream` on the paper's
#: dataset under 1.6 GiB).
DEFAULT_SHUFFLE_BUFFER = 2048
#: Slabs a shard reads ahead in a background thread.
PREFETCH_SLABS = 2
#: Frames ``window_bank`` reads at once (rounded to whole chunks): its temporary block stays ~9 MB
#: of float16 on the default grid however far apart the windows lie, where one read per stretch of
#: close windows was a whole run (1,600 validation windows touch every chunk of a 7,500-frame run).
READ_FRAMES = 256


@dataclass(frozen=True)
class Slab:
    """Frames ``lo .. hi-1`` of run ``run`` (its position in the layout), read as one block, and
    the global start frames of the windows that lie in them (ascending)."""

    run: int
    lo: int
    hi: int
    starts: np.ndarray


def make_slabs(layout: RunLayout, starts: np.ndarray, span: int, slab_frames: int = DEFAULT_SLAB_FRAMES) -> list[Slab]:
    """The slabs holding the windows ``starts`` (global start frames of ``span``-frame windows), in
    layout order: a window belongs to the slab its start frame falls in."""
    if slab_frames < 1:
        raise SonarSetError(f"slab_frames must be >= 1, got {slab_frames}", parameter="slab_frames")
    starts = np.sort(np.asarray(starts, dtype=np.int64))
    offsets = layout.run_offsets
    run_of = np.searchsorted(offsets, starts, side="right") - 1
    local = starts - offsets[run_of]
    if starts.size and np.any(local + span > (offsets[run_of + 1] - offsets[run_of])):
        raise SonarSetError(f"a window of {span} frames runs past the end of its run")
    key = run_of * (1 << 40) + local // slab_frames  # runs are far shorter than 2**40 slabs
    cuts = np.flatnonzero(np.diff(key)) + 1
    slabs = []
    for piece in np.split(np.arange(starts.size), cuts) if starts.size else []:
        j, k = int(run_of[piece[0]]), int(local[piece[0]] // slab_frames)
        n = int(offsets[j + 1] - offsets[j])
        slabs.append(Slab(j, k * slab_frames, min(n, (k + 1) * slab_frames + span - 1), starts[piece]))
    return slabs


def shard_sizes(n_windows: int, n_shards: int) -> list[int]:
    """Windows in each of ``n_shards`` shards of an epoch of ``n_windows`` (the same every epoch)."""
    return [(s + 1) * n_windows // n_shards - s * n_windows // n_shards for s in range(n_shards)]


def rank_shard_sizes(n_windows: int, world: int, workers: int, rank: int) -> list[int]:
    """Windows in each shard of ``rank`` (one shard per DataLoader worker, one without workers)."""
    per = max(1, workers)
    return shard_sizes(n_windows, world * per)[rank * per:(rank + 1) * per]


def batches_per_rank(n_windows: int, world: int, workers: int, batch_size: int) -> int:
    """Full batches every rank can take in an epoch: the fewest of any rank, each of whose shards
    yields ``size // batch_size`` full ones (DDP needs every rank to step alike)."""
    return min(sum(s // batch_size for s in rank_shard_sizes(n_windows, world, workers, r)) for r in range(world))


def canonical_order(counts: Sequence[int]) -> list[tuple[int, int]]:
    """The order a rank takes its shards' batches in: round robin over its shards, (shard position,
    batch number) pairs, a shard left out once it has no more. This is a DataLoader's in-order
    interleaving of its workers, written down so that a resumed loader can be held to it."""
    out, rounds = [], max(counts, default=0)
    for r in range(rounds):
        out += [(w, r) for w, c in enumerate(counts) if r < c]
    return out


def consumed_per_shard(counts: Sequence[int], taken: int) -> list[int]:
    """Batches of each shard among the first ``taken`` of ``canonical_order(counts)``."""
    done = [0] * len(counts)
    for w, _ in canonical_order(counts)[:taken]:
        done[w] += 1
    return done


@dataclass
class ShardPlan:
    """One shard of one epoch: its pieces (slab position, window starts taken from that slab) in
    opening order, and the order its windows are drawn in (piece, start) under the shuffle buffer."""

    pieces: list[tuple[int, np.ndarray]]
    piece_of: np.ndarray  # (n,) piece of each drawn window
    starts: np.ndarray  # (n,) its global start frame

    @classmethod
    def make(cls, slabs: list[Slab], epoch: int, seed: int, shard: int, n_shards: int,
             shuffle_buffer: int = DEFAULT_SHUFFLE_BUFFER) -> "ShardPlan":
        order = np.random.default_rng([seed, epoch]).permutation(len(slabs))
        sizes = np.array([len(slabs[i].starts) for i in order], dtype=np.int64)
        ends = np.cumsum(sizes)
        total = int(ends[-1]) if sizes.size else 0
        lo, hi = shard * total // n_shards, (shard + 1) * total // n_shards
        pieces = []
        for pos, i in enumerate(order):
            first = int(ends[pos] - sizes[pos])
            a, b = max(lo, first), min(hi, int(ends[pos]))
            if a < b:
                pieces.append((int(i), slabs[i].starts[a - first:b - first]))
        rng = np.random.default_rng([seed, epoch, shard, 1])
        pieces = [(i, rng.permutation(s)) for i, s in pieces]
        mean = (hi - lo) / max(1, len(pieces))
        piece_of, starts = _draw(pieces, max(1, math.ceil(shuffle_buffer / max(1.0, mean))), rng)
        return cls(pieces, piece_of, starts)

    def __len__(self) -> int:
        return int(self.starts.size)


def _draw(pieces: list[tuple[int, np.ndarray]], n_open: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The shuffle buffer: ``n_open`` pieces open at a time, each draw uniform over their remaining
    windows, an exhausted piece replaced by the next."""
    n = sum(len(s) for _, s in pieces)
    piece_of, starts = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    uniforms = rng.random(n)
    open_ = list(range(min(n_open, len(pieces))))
    left = [len(pieces[p][1]) for p in open_]
    nxt = len(open_)
    for t in range(n):
        r = int(uniforms[t] * sum(left))
        k = 0
        while r >= left[k]:
            r -= left[k]
            k += 1
        p = open_[k]
        seq = pieces[p][1]
        piece_of[t], starts[t] = p, seq[len(seq) - left[k]]
        left[k] -= 1
        if left[k] == 0:
            if nxt < len(pieces):
                open_[k], left[k] = nxt, len(pieces[nxt][1])
                nxt += 1
            else:
                del open_[k], left[k]
    return piece_of, starts


@dataclass
class WindowStream:
    """Batches of one shard of one epoch, read from the store slab by slab.

    ``store`` is an open SonarStore (each process opens its own), ``layout`` and ``slabs`` as made
    for it, ``span`` the window length (``n_in`` inputs + ``horizon`` targets). Iterating yields
    NumPy :class:`~sonarset.windows.WindowBatch` es (starts: global start frames), skipping the
    first ``skip_batches`` without reading their frames. The last batch is partial unless
    ``drop_last``.
    """

    store: object
    layout: RunLayout
    slabs: list[Slab]
    n_in: int
    horizon: int
    batch_size: int
    plan: ShardPlan
    skip_batches: int = 0
    drop_last: bool = False
    image_dtype: np.dtype | None = None
    prefetch: int = PREFETCH_SLABS
    _velocity: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def n_batches(self) -> int:
        n = len(self.plan)
        return n // self.batch_size if self.drop_last else -(-n // self.batch_size)

    def _read(self, piece: int) -> np.ndarray:
        slab = self.slabs[self.plan.pieces[piece][0]]
        run = self.store.run(self.layout.run_names[slab.run])
        block = run.read("images", slab.lo, slab.hi)
        return block if self.image_dtype is None else block.astype(self.image_dtype, copy=False)

    def _commands(self, j: int) -> np.ndarray:
        if j not in self._velocity:  # a run's commands: 8 bytes a frame, read once
            self._velocity[j] = self.store.run(self.layout.run_names[j]).read("velocity")
        return self._velocity[j]

    def __iter__(self) -> Iterator[WindowBatch]:
        B, span, plan = self.batch_size, self.n_in + self.horizon, self.plan
        n_batches = self.n_batches
        if self.skip_batches >= n_batches:
            return
        batch_of = np.arange(len(plan)) // B
        first = np.full(len(plan.pieces), n_batches, dtype=np.int64)
        last = np.full(len(plan.pieces), -1, dtype=np.int64)
        np.minimum.at(first, plan.piece_of, batch_of)
        np.maximum.at(last, plan.piece_of, batch_of)
        # pieces in the order they are first needed from the resume point on
        needed = [p for p in np.argsort(first, kind="stable") if last[p] >= self.skip_batches and first[p] < n_batches]
        loaded: dict[int, cf.Future] = {}
        offsets = self.layout.run_offsets
        reader = cf.ThreadPoolExecutor(1)
        try:
            ptr = 0
            for b in range(self.skip_batches, n_batches):
                # every piece this batch draws from, and up to ``prefetch`` later ones, read ahead
                while ptr < len(needed) and (first[needed[ptr]] <= b or
                                             sum(first[p] > b for p in loaded) < self.prefetch):
                    loaded[int(needed[ptr])] = reader.submit(self._read, int(needed[ptr]))
                    ptr += 1
                sel = slice(b * B, min(len(plan), (b + 1) * B))
                pieces, starts = plan.piece_of[sel], plan.starts[sel]
                frames = None
                commands = np.empty((len(starts), span, 2), dtype=np.float32)
                for i, (p, g) in enumerate(zip(pieces, starts)):
                    slab = self.slabs[plan.pieces[p][0]]
                    block = loaded[p].result()
                    if frames is None:
                        frames = np.empty((len(starts), span, *block.shape[1:]), dtype=block.dtype)
                    at = int(g - offsets[slab.run])
                    frames[i] = block[at - slab.lo:at - slab.lo + span]
                    commands[i] = self._commands(slab.run)[at:at + span]
                for p in np.unique(pieces):
                    if last[p] == b:
                        del loaded[p]  # no later batch draws from it: let it go
                yield WindowBatch(frames[:, :self.n_in], commands, frames[:, self.n_in:], starts)
        finally:  # a consumer that stops early does not wait for the reads ahead
            reader.shutdown(wait=False, cancel_futures=True)


def window_bank(store, layout: RunLayout, index: WindowIndex, image_dtype: str | np.dtype | None = None,
                packed: bool = True) -> FrameBank:
    """A FrameBank of ``layout``'s runs in which only the frames of ``index``'s windows are read
    (memory: their frames, not the store's): gathers, windows and ``locate`` work as on the whole
    bank, with the same numbers. The frames are read ``READ_FRAMES`` at a time (each chunk decoded
    once) and, ``packed``, held compressed (:class:`PackedFrames`, decoded as they are gathered:
    the images as stored, converted to ``image_dtype`` there); else as one array of ``image_dtype``."""
    rows = np.unique(index.rows())
    offsets = layout.run_offsets
    dtype = np.dtype(image_dtype) if image_dtype is not None else None
    parts: list[np.ndarray] = []  # unpacked: the blocks read, joined at the end
    held: PackedFrames | None = None
    velocity = np.empty((layout.n_frames, 2), dtype=np.float32)
    run_of = np.searchsorted(offsets, rows, side="right") - 1
    for j, name in enumerate(layout.run_names):
        run = store.run(name)
        velocity[offsets[j]:offsets[j + 1]] = run.read("velocity")
        mine = rows[run_of == j] - offsets[j]
        if not mine.size:
            continue
        images = run.array("images")
        chunk = max(1, images.chunks[0])
        span = chunk * max(1, READ_FRAMES // chunk)  # whole chunks: none is decoded twice
        cuts = np.flatnonzero(np.diff(mine // span)) + 1
        for part in np.split(mine, cuts):
            block = run.read("images", int(part[0]), int(part[-1]) + 1)[part - part[0]]
            if not packed:
                parts.append(block.astype(dtype or block.dtype, copy=False))
                continue
            if held is None:
                held = PackedFrames(block.shape[1:], block.dtype, dtype or block.dtype)
            held.append(block)
    if packed:
        frames = held if held is not None else PackedFrames(layout.grid.shape, np.float32, dtype or np.float32)
    else:
        frames = (np.concatenate(parts) if parts else
                  np.empty((0, *layout.grid.shape), dtype=dtype or np.float32))
    return FrameBank(HeldFrames(frames, rows, layout.n_frames), velocity, offsets, layout.run_names, layout.grid,
                     layout.frame_interval_s, layout.gaps)


class PackedFrames:
    """Frames held compressed one by one, decoded when gathered: an array-like of shape
    (n, R, A) indexed by integer positions (any shape of them).

    Energyscapes are mostly black (88 % of the pixels of the paper's dataset are exactly 0): Blosc's
    zstd at level 1 holds a frame in about a sixth of its bytes and decodes it in ~60 us, so a set
    of drawn windows gathered again and again (validation) costs a sixth of the memory, and one
    batch's decoding a few ms. Frames keep the dtype they were stored in and are converted to
    ``dtype`` when decoded: the values an in-memory bank of that dtype holds.
    """

    CODEC = Blosc(cname="zstd", clevel=1, shuffle=Blosc.NOSHUFFLE)

    def __init__(self, frame_shape: Sequence[int], stored: np.dtype, dtype: np.dtype):
        self.frame_shape, self.stored, self.dtype = tuple(frame_shape), np.dtype(stored), np.dtype(dtype)
        self._blobs: list[bytes] = []
        self.nbytes = 0  # compressed

    def append(self, frames: np.ndarray) -> None:
        """Hold ``frames`` (m, R, A) after the frames held so far."""
        for frame in np.asarray(frames, dtype=self.stored):
            blob = self.CODEC.encode(np.ascontiguousarray(frame))
            self._blobs.append(blob)
            self.nbytes += len(blob)

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self._blobs), *self.frame_shape)

    def __len__(self) -> int:
        return len(self._blobs)

    def __getitem__(self, at) -> np.ndarray:
        """The frames at positions ``at`` (non-negative integers), shaped ``at.shape + (R, A)``;
        each distinct frame decoded once, straight into the places that take it (no block of the
        distinct frames beside the result: a window's frames are shared by its neighbours)."""
        at = np.asarray(at)
        if at.dtype.kind not in "iu":
            raise TypeError(f"packed frames are indexed by integer positions, got {at.dtype}")
        out = np.empty((at.size, *self.frame_shape), dtype=self.dtype)
        frame = np.empty(self.frame_shape, dtype=self.stored)
        order = np.argsort(at, axis=None, kind="stable")
        flat = at.reshape(-1)[order]
        firsts = np.flatnonzero(np.r_[True, flat[1:] != flat[:-1]]) if flat.size else flat
        for lo, hi in zip(firsts, np.r_[firsts[1:], flat.size].astype(np.int64)):
            self.CODEC.decode(self._blobs[flat[lo]], out=frame)
            out[order[lo:hi]] = frame
        return out.reshape(*at.shape, *self.frame_shape)


@dataclass(frozen=True)
class HeldFrames:
    """The frames ``rows`` (ascending global indices) of an ``n_frames``-frame bank, indexed by
    global row like the whole bank's images array; asking for a frame not held is an error. ``held``
    is their array, or a :class:`PackedFrames`."""

    held: np.ndarray | PackedFrames
    rows: np.ndarray
    n_frames: int

    @property
    def dtype(self) -> np.dtype:
        return self.held.dtype

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.n_frames, *self.held.shape[1:])

    @property
    def nbytes(self) -> int:
        return int(self.held.nbytes)

    def positions(self, at) -> np.ndarray:
        """Where the global rows ``at`` (integers; negative ones count from the end) are held."""
        at_arr = np.asarray(at)
        if at_arr.dtype.kind not in "iu":  # a mask, a float or a slice would quietly pick other frames
            raise TypeError(f"frames are indexed by integer rows, got {at_arr.dtype} ({at!r:.60})")
        at_arr = np.where(at_arr < 0, at_arr + self.n_frames, at_arr).astype(np.int64)
        pos = np.searchsorted(self.rows, at_arr)
        if np.any(pos >= self.rows.size) or np.any(self.rows[np.minimum(pos, self.rows.size - 1)] != at_arr):
            raise IndexError("a frame outside the windows this bank was read for")
        return pos

    def __getitem__(self, at):
        return self.held[self.positions(at)]
