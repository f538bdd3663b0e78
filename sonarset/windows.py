"""Sliding windows over runs: n_in frames + n_in+H commands -> the next H frames.

Layout after Diffusion Policy's replay buffer: the frames of all runs are concatenated into one
flat in-memory array (a :class:`FrameBank`), and a window is just the global index of its first
frame (a :class:`WindowIndex`). Gathering a batch is then one vectorised NumPy take.

One batcher, :class:`WindowBatcher`, turns windows into batches for every consumer: NumPy arrays
for evaluation (:func:`gather`, :func:`iter_batches`), and torch tensors, on the training device or
behind a DataLoader (``sonarset.torchdata``), from the same row arithmetic.

Alignment (docs/conventions.md, "Windows"): the window starting at frame i of a run uses frames i..i+n_in-1 and
commands i..i+n_in-1+H, and targets frames i+n_in..i+n_in-1+H. ``velocity[k]`` moved the robot
from frame k-1 to k, so command i+n_in is the one that leads to the first target. Windows never
cross runs, nor a gap a run records (its attribute ``gaps``, spec/FORMAT.md section 4: pings a
sensor lost between two frames): a window's frames are consecutive measurements.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from sonarset.errors import SonarSetError
from sonarset.format.attrs import SensorGrid
from sonarset.store.store import SonarStore

#: Input frames of a window: the paper's geometry (docs/conventions.md, "Windows"), the one
#: definition. A learned model's own count is in its config (EchoPT's defaults to this); the
#: baselines are fed these windows.
N_IN = 3

#: The run attribute listing a run's gaps: ``[[k, lost], ...]``, ``lost`` >= 1 frames missing
#: between its frames k-1 and k (1 <= k < n_frames), as ``import-bag`` records lost pings.
RUN_GAPS = "gaps"


def run_gaps(run) -> np.ndarray:
    """The frames of ``run`` (a ``Run``) that follow a recorded gap, sorted (int64; empty when it
    records none); a malformed record is an error naming the run."""
    extra = run.attrs.model_extra or {}
    raw = extra.get(RUN_GAPS)
    if raw is None:
        return np.zeros(0, np.int64)
    try:
        pairs = np.asarray(raw, dtype=np.float64).reshape(-1, 2) if len(raw) else np.zeros((0, 2))
    except (TypeError, ValueError):
        pairs = None
    if pairs is None or not np.isfinite(pairs).all() or (pairs != np.round(pairs)).any() or \
            ((pairs[:, 0] < 1) | (pairs[:, 0] >= run.n_frames) | (pairs[:, 1] < 1)).any():
        raise SonarSetError(f"run {run.name!r}: attribute {RUN_GAPS!r} must list [frame, lost] pairs, 1 <= frame < "
                            f"{run.n_frames} and lost >= 1, got {str(raw)[:80]}")
    return np.unique(pairs[:, 0].astype(np.int64))


def _select_runs(store: SonarStore, runs: Sequence[str] | None = None, split: str | None = None,
                worlds: Sequence[str] | None = None) -> list[str]:
    """The runs named, or every complete run of ``split`` (of the world families ``worlds`` if
    given); none is an error naming what the store has."""
    names = list(runs) if runs is not None else store.runs(split, worlds=worlds)
    if not names:
        what = f"split {split!r}" if split else "the store"
        if worlds is not None:
            have = sorted(store.worlds(split))
            raise SonarSetError(f"{store.location}: no complete runs of world {', '.join(worlds)} in {what} "
                                f"(worlds: {', '.join(have) or 'none recorded'})")
        raise SonarSetError(f"{store.location}: no complete runs in {what} (splits: "
                            f"{', '.join(sorted(store.splits())) or 'none'})")
    return names


@dataclass(frozen=True)
class RunLayout:
    """Some runs of a store numbered frame by frame, run after run: a FrameBank's numbering, known
    without reading a frame (the streamed path's whole view of the runs)."""

    location: str
    run_names: list[str]
    run_offsets: np.ndarray  # (n_runs + 1,) int64
    grid: SensorGrid
    frame_interval_s: float | None = None  # median spacing of the runs' time stamps
    gaps: np.ndarray | None = None  # (G,) int64: the frames (numbered as here) that follow a recorded gap

    @classmethod
    def of(cls, store: SonarStore, runs: Sequence[str] | None = None, split: str | None = None,
           worlds: Sequence[str] | None = None) -> "RunLayout":
        """The runs named, or every complete run of ``split`` (of ``worlds``); their time stamps (a
        few bytes a frame) are read, checked, for the frame interval."""
        names = _select_runs(store, runs, split, worlds)
        run_objs = [store.run(n) for n in names]
        offsets = np.concatenate([[0], np.cumsum([r.n_frames for r in run_objs])]).astype(np.int64)
        run_gap_frames = [run_gaps(r) for r in run_objs]
        # the frame interval: the spacing of consecutive frames, not of the frames across a gap
        steps = np.concatenate([np.delete(np.diff(r.read_time()), g - 1) for r, g in zip(run_objs, run_gap_frames)])
        gaps = np.concatenate([g + offsets[j] for j, g in enumerate(run_gap_frames)]).astype(np.int64)
        return cls(store.location, names, offsets, store.grid, float(np.median(steps)) if steps.size else None,
                   gaps)

    @property
    def n_frames(self) -> int:
        return int(self.run_offsets[-1])

    def index(self, n_in: int, horizon: int = 1) -> "WindowIndex":
        """Every window of these runs: the same starts as ``WindowIndex.build`` over their FrameBank."""
        return WindowIndex.build(self, n_in, horizon)


@dataclass
class FrameBank:
    """All frames and commands of some runs, concatenated (N frames in total)."""

    images: np.ndarray  # (N, R, A) float16 or float32
    velocity: np.ndarray  # (N, 2) float32: (v [m/s], omega [rad/s])
    run_offsets: np.ndarray  # (n_runs + 1,) int64: run j is frames run_offsets[j]:run_offsets[j+1]
    run_names: list[str]
    grid: SensorGrid
    # median spacing of the runs' time stamps, seconds (None: unknown, or no run of 2+ frames)
    frame_interval_s: float | None = None
    gaps: np.ndarray | None = None  # (G,) int64: frames that follow a recorded gap (RunLayout.gaps)

    @classmethod
    def from_store(
        cls,
        store: SonarStore,
        runs: Sequence[str] | None = None,
        split: str | None = None,
        image_dtype: str | np.dtype | None = None,
        progress: Callable[[str, int, int], None] | None = None,
        worlds: Sequence[str] | None = None,
    ) -> "FrameBank":
        """Load runs (by name, or every complete run of ``split``, of the world families ``worlds``
        if given) into memory, each chunk decoded once."""
        layout = RunLayout.of(store, runs, split, worlds)
        run_objs = [store.run(n) for n in layout.run_names]
        offsets = layout.run_offsets
        dtype = np.dtype(image_dtype) if image_dtype is not None else run_objs[0].array("images").dtype
        images = np.empty((layout.n_frames, *store.grid.shape), dtype=dtype)
        velocity = np.empty((layout.n_frames, 2), dtype=np.float32)
        for j, run in enumerate(run_objs):
            lo, hi = int(offsets[j]), int(offsets[j + 1])
            # Read slabs of many chunks: zarr overlaps their I/O and decoding (2x faster than
            # chunk by chunk) while the temporary copy stays small. ``read`` checks each slab's
            # chunks and values: a broken store stops here, not as silent zeros in a metric.
            step = run.array("images").chunks[0] * 16
            for s in range(0, hi - lo, step):
                e = min(hi - lo, s + step)
                run.read("images", s, e, out=images[lo + s:lo + e])
                if progress is not None:
                    progress(run.name, e, hi - lo)
            velocity[lo:hi] = run.read("velocity")
        return cls(images, velocity, offsets, layout.run_names, store.grid, layout.frame_interval_s, layout.gaps)

    @classmethod
    def from_arrays(cls, runs: Sequence[tuple[np.ndarray, np.ndarray]], grid: SensorGrid,
                    names: Sequence[str] | None = None) -> "FrameBank":
        """Build a bank from in-memory (images, velocity) pairs, one per run."""
        sizes = [len(im) for im, _ in runs]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        images = np.concatenate([np.asarray(im) for im, _ in runs])
        velocity = np.concatenate([np.asarray(v, dtype=np.float32) for _, v in runs])
        return cls(images, velocity, offsets, list(names or [f"run_{i:03d}" for i in range(len(runs))]), grid)

    @property
    def n_frames(self) -> int:
        return int(self.run_offsets[-1])

    @property
    def n_runs(self) -> int:
        return len(self.run_names)

    @property
    def nbytes(self) -> int:
        return int(self.images.nbytes + self.velocity.nbytes)


@dataclass(frozen=True)
class WindowIndex:
    """Windows as global start frames into a :class:`FrameBank` (int64, any order)."""

    starts: np.ndarray
    run_offsets: np.ndarray
    n_in: int = N_IN
    horizon: int = 1

    @classmethod
    def build(cls, bank: FrameBank | RunLayout, n_in: int = N_IN, horizon: int = 1) -> "WindowIndex":
        """Every window of ``bank``'s runs: none crosses from one run to the next, nor a recorded
        gap (``bank.gaps``): the window at i is dropped when frame i+1..i+span-1 follows one."""
        if n_in < 1 or horizon < 1:
            raise SonarSetError(f"n_in and horizon must be >= 1 (got {n_in}, {horizon})")
        span = n_in + horizon
        starts = [np.arange(lo, hi - span + 1, dtype=np.int64)
                  for lo, hi in zip(bank.run_offsets[:-1], bank.run_offsets[1:]) if hi - lo >= span]
        s = np.concatenate(starts) if starts else np.zeros(0, dtype=np.int64)
        gaps = getattr(bank, "gaps", None)
        if gaps is not None and len(gaps) and s.size:
            after = np.zeros(int(bank.run_offsets[-1]) + 1, np.int64)
            after[np.asarray(gaps, np.int64)] = 1
            seen = np.cumsum(after)  # seen[j]: gaps before frames 0..j
            s = s[seen[s + span - 1] == seen[s]]
        return cls(s, bank.run_offsets, n_in, horizon)

    @property
    def span(self) -> int:
        """Frames touched by one window: inputs plus targets."""
        return self.n_in + self.horizon

    def __len__(self) -> int:
        return int(self.starts.shape[0])

    def subset(self, which: np.ndarray | Sequence[int]) -> "WindowIndex":
        return WindowIndex(self.starts[np.asarray(which, dtype=np.int64)], self.run_offsets, self.n_in, self.horizon)

    def sample(self, n: int, seed: int = 0) -> "WindowIndex":
        """``n`` windows drawn without replacement (all if fewer), in ascending order."""
        if n >= len(self):
            return self
        pick = np.sort(np.random.default_rng(seed).choice(len(self), size=n, replace=False))
        return self.subset(pick)

    def rows(self, which: np.ndarray | slice | None = None, horizon: int | None = None) -> np.ndarray:
        """Global frame indices (B, n_in + h) of the windows ``index[which]``: inputs, then the first
        ``h = horizon`` targets (default: all of the index's horizon)."""
        h = self.horizon if horizon is None else horizon
        if not 1 <= h <= self.horizon:
            raise SonarSetError(f"horizon {h}: these windows hold 1 to {self.horizon} targets")
        starts = np.atleast_1d(self.starts if which is None else self.starts[which])
        return starts[:, None] + np.arange(self.n_in + h)

    def locate(self, k: int) -> tuple[int, int]:
        """(run position in the bank, frame index within that run) of window ``k``."""
        g = int(self.starts[k])
        j = int(np.searchsorted(self.run_offsets, g, side="right") - 1)
        return j, g - int(self.run_offsets[j])

    def split(self, n_val: int = 1600, seed: int = 0, purge: bool = True) -> tuple["WindowIndex", "WindowIndex"]:
        """A seeded random validation subset of ``n_val`` windows, and the rest for training.

        The paper draws 1600 random validation windows. Neighbouring windows share frames, so with
        ``purge`` (default) training windows that touch any validation frame are dropped too: the
        validation loss then measures frames the model never saw.
        """
        if not 0 < n_val < len(self):
            raise SonarSetError(f"cannot hold out {n_val} validation windows from {len(self)}")
        rng = np.random.default_rng(seed)
        val_pos = np.sort(rng.choice(len(self), size=n_val, replace=False))
        train_mask = np.ones(len(self), dtype=bool)
        train_mask[val_pos] = False
        if purge:
            n = int(self.run_offsets[-1])
            covered = np.zeros(n + 1, dtype=np.int64)
            # Mark every frame used by a validation window (difference array, then cumsum).
            np.add.at(covered, self.starts[val_pos], 1)
            np.add.at(covered, self.starts[val_pos] + self.span, -1)
            used = np.cumsum(covered)[:n] > 0
            used_cum = np.concatenate([[0], np.cumsum(used)])
            touches = used_cum[self.starts + self.span] - used_cum[self.starts] > 0
            train_mask &= ~touches
        return self.subset(np.flatnonzero(train_mask)), self.subset(val_pos)


@dataclass
class WindowBatch:
    """A batch of B windows: NumPy arrays, or torch tensors from a torch batcher."""

    frames: np.ndarray  # (B, n_in, R, A) measured input frames
    commands: np.ndarray  # (B, n_in + H, 2) commands i .. i+n_in-1+H
    targets: np.ndarray  # (B, H, R, A) frames i+n_in .. i+n_in-1+H
    starts: np.ndarray  # (B,) global start frames

    def __len__(self) -> int:
        return int(self.frames.shape[0])


@dataclass(frozen=True)
class WindowBatcher:
    """The one batcher over a :class:`WindowIndex` (after Diffusion Policy's sequence sampler):
    flat frame and command arrays, and windows as precomputed rows into them.

    Every consumer batches through it: evaluation (NumPy arrays), training and the DataLoader
    (``sonarset.torchdata.torch_batcher``: tensors, on the training device or converted from the
    gathered NumPy block). ``to_rows`` turns the NumPy row indices into the arrays' index type (a
    tensor on their device); ``images_as`` and ``commands_as`` convert what was gathered (dtype,
    array kind). Inputs and targets are gathered as one block, and both are views of it.
    """

    images: Any  # (N, R, A)
    velocity: Any  # (N, 2)
    to_rows: Callable[[np.ndarray], Any] | None = None
    images_as: Callable[[Any], Any] | None = None
    commands_as: Callable[[Any], Any] | None = None

    @classmethod
    def of(cls, bank: FrameBank, image_dtype: str | np.dtype | None = None) -> "WindowBatcher":
        """NumPy batches from ``bank``, images converted to ``image_dtype`` when given."""
        images_as = None if image_dtype is None else (lambda block: block.astype(image_dtype, copy=False))
        return cls(bank.images, bank.velocity, images_as=images_as)

    def gather(self, index: WindowIndex, which: np.ndarray | slice | None = None,
               horizon: int | None = None) -> WindowBatch:
        """The windows ``index[which]`` with their first ``horizon`` targets (default: all)."""
        rows = index.rows(which, horizon)
        at = rows if self.to_rows is None else self.to_rows(rows)
        block, commands = self.images[at], self.velocity[at]  # (B, n_in + h, R, A), (B, n_in + h, 2)
        if self.images_as is not None:
            block = self.images_as(block)
        if self.commands_as is not None:
            commands = self.commands_as(commands)
        return WindowBatch(block[:, :index.n_in], commands, block[:, index.n_in:], rows[:, 0])


def gather(bank: FrameBank, index: WindowIndex, which: np.ndarray | slice | None = None,
           image_dtype: str | np.dtype | None = None) -> WindowBatch:
    """The windows ``index[which]`` as one NumPy batch (a single vectorised gather per array)."""
    return WindowBatcher.of(bank, image_dtype).gather(index, which)


def iter_batches(
    bank: FrameBank,
    index: WindowIndex,
    batch_size: int = 64,
    *,
    shuffle: bool = True,
    seed: int = 0,
    epoch: int = 0,
    drop_last: bool = False,
    image_dtype: str | np.dtype | None = None,
) -> Iterator[WindowBatch]:
    """Framework-free batches; the order depends only on (seed, epoch)."""
    n = len(index)
    order = np.random.default_rng([seed, epoch]).permutation(n) if shuffle else np.arange(n)
    stop = n - n % batch_size if drop_last else n
    batcher = WindowBatcher.of(bank, image_dtype)
    for lo in range(0, stop, batch_size):
        yield batcher.gather(index, order[lo:lo + batch_size])


def load_windows(store: SonarStore, split: str | None = "train", n_in: int = N_IN, horizon: int = 1,
                 image_dtype: str | np.dtype | None = None) -> tuple[FrameBank, WindowIndex]:
    """Load the runs of ``split`` into memory and index their windows."""
    bank = FrameBank.from_store(store, split=split, image_dtype=image_dtype)
    return bank, WindowIndex.build(bank, n_in, horizon)
