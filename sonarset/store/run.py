"""A run of a SonarSet store, read lazily and checked as it is read (spec/FORMAT.md §2)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import zarr

from sonarset.format.arrays import (
    ARRAYS, OPTIONAL_ARRAYS, array_meta_problems, coordinates_match, expected_shape, frame_interval_problem,
    time_order_problem, value_problem,
)
from sonarset.errors import FormatError, SonarSetError, one_line
from sonarset.store.integrity import ChunkChecker, chunk_coords
from sonarset.format.plausibility import command_problems
from sonarset.format.attrs import RunAttrs
from sonarset.store.zarrio import child_names

if TYPE_CHECKING:
    from sonarset.store.store import SonarStore


@dataclass
class RunData:
    """A run's arrays loaded into memory (NumPy)."""

    name: str
    split: str
    images: np.ndarray
    velocity: np.ndarray
    time: np.ndarray
    pose: np.ndarray | None = None
    snr_db: np.ndarray | None = None
    slip: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.images.shape[0])


class Run:
    """A complete run group, read lazily: ``run['images'][100:200]`` reads only those chunks.

    ``run.read(key, start, stop)`` is the checked read that the tools use: it refuses a missing,
    truncated or undecodable chunk and values the spec forbids, with a FormatError naming the
    run, the array and the chunk, instead of handing back fill values or garbage.
    """

    def __init__(self, store: "SonarStore", name: str, attrs: RunAttrs):
        self.store, self.name, self.attrs = store, name, attrs
        #: Frames in the run (the length of every per-frame array), and the split it belongs to.
        self.n_frames, self.split = attrs.n_frames, attrs.split
        self.where = f"{store.location}/{name}"
        try:
            self.group = store.group[name]
        except Exception as exc:
            raise FormatError(f"{self.where}: unreadable zarr metadata ({one_line(exc)})") from None
        self._members: set[str] | None = None
        self._arrays: dict[str, zarr.Array] = {}
        self._checkers: dict[str, ChunkChecker] = {}
        self._time: np.ndarray | None = None

    def _member_names(self) -> set[str]:
        if self._members is None:
            try:
                self._members = set(self.group.array_keys())
            except Exception:  # a member's metadata is unreadable: array() names it
                self._members = set(child_names(self.group))
        return self._members

    def has(self, key: str) -> bool:
        return key in self._member_names()

    def array(self, key: str) -> zarr.Array:
        """Array ``key`` after its metadata was checked against the spec (dtype, shape, dimension
        names); FormatError if it is missing, unreadable or does not conform."""
        if key in self._arrays:
            return self._arrays[key]
        if key not in ARRAYS:
            raise KeyError(key)
        where = f"{self.where}/{key}"
        if not self.has(key):
            raise FormatError(f"{self.where}: has no {key!r} array")
        try:
            arr = self.group[key]
        except Exception as exc:
            raise FormatError(f"{where}: unreadable zarr metadata ({one_line(exc)})") from None
        if not isinstance(arr, zarr.Array):
            raise FormatError(f"{where}: is a group, not an array")
        try:
            dims = tuple(arr.metadata.dimension_names or ())
            problems = array_meta_problems(key, str(arr.dtype), dims, tuple(arr.shape),
                                           expected_shape(key, self.n_frames, self.store.grid.shape))
        except Exception as exc:  # metadata zarr accepted but we cannot interpret
            raise FormatError(f"{where}: unusable zarr metadata ({one_line(exc)})") from None
        if problems:
            context = (f" (n_frames={self.n_frames}, grid {self.store.grid.shape[0]}x{self.store.grid.shape[1]})"
                       if problems[0].startswith("shape") else "")
            raise FormatError(f"{where}: {problems[0]}{context}")
        self._arrays[key] = arr
        return arr

    def __getitem__(self, key: str) -> zarr.Array:
        if key not in ARRAYS:
            raise KeyError(key)
        return self.array(key)

    @property
    def images(self) -> zarr.Array:
        return self["images"]

    @property
    def velocity(self) -> zarr.Array:
        return self["velocity"]

    @property
    def time(self) -> zarr.Array:
        return self["time"]

    def _checker(self, key: str) -> ChunkChecker:
        if key not in self._checkers:
            self._checkers[key] = ChunkChecker(self.array(key))
        return self._checkers[key]

    def check(self, chunks: bool = True) -> None:
        """Structural checks of this run (see ``SonarStore.check``); FormatError on the first problem."""
        keys = [k for k, spec in ARRAYS.items() if spec.required or self.has(k)]
        for key in keys:
            self.array(key)
        grid = self.store.grid
        for key, centres in (("range", grid.range_centres()), ("azimuth", grid.azimuth_centres())):
            values = self.read(key)
            if not coordinates_match(values, centres):
                raise FormatError(f"{self.where}/{key}: coordinates do not match the store grid "
                                  f"(got {values[0]:.6g}..{values[-1]:.6g}, grid {centres[0]:.6g}..{centres[-1]:.6g})")
        if chunks:
            for key in keys:
                if self._checker(key).local is None:
                    # Remote: checking a chunk means fetching it, so each chunk is checked when
                    # it is read (``read``), through the chunk cache, not all of them at open.
                    continue
                bad = self._checker(key).first_problem()
                if bad is not None:
                    raise FormatError(f"{self.where}/{key}: chunk {bad[0]} {bad[1]}")

    def read(self, key: str, start: int = 0, stop: int | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """Frames ``start .. stop-1`` of array ``key`` (all of a coordinate array), checked.

        The chunks read must be present and as long as their headers say, must decode, and the
        values must be what the spec allows (images finite and in [0, 1], the rest finite; a
        whole ``time`` array also strictly increasing and spaced as the declared frame rate; a
        whole ``velocity`` array within the rig's command limits, as ``validate`` demands).

        With ``out`` (an array of the block's shape, any float dtype) the values are checked and
        copied into it one chunk's worth at a time, while that piece is still in the CPU cache:
        the check then costs almost nothing on top of the copy the caller needs anyway
        (bench/bench_readcheck.py). Returns ``out``; on an error its content is undefined.
        """
        arr = self.array(key)
        n = arr.shape[0]
        stop = n if stop is None else min(int(stop), n)
        start = max(0, int(start))
        where = f"{self.where}/{key}"
        bad = self._checker(key).first_problem(start, stop)
        if bad is not None:
            raise FormatError(f"{where}: chunk {bad[0]} {bad[1]}")
        try:
            block = arr[start:stop]
        except Exception as exc:
            raise self._decode_error(key, start, stop, exc) from None
        step = block.shape[0] if out is None else max(1, arr.metadata.chunk_grid.chunk_shape[0])
        for i in range(0, block.shape[0], step):
            piece = block[i:i + step]
            problem = value_problem(key, piece, start + i)
            if problem is not None:
                frame, line = problem
                raise FormatError(f"{where}: {line}{self._chunk_of(key, frame)}")
            if out is not None:
                out[i:i + piece.shape[0]] = piece
        if out is not None:
            block = out
        if key == "velocity" and start == 0 and stop == n:
            # Only commands no ground robot could follow are unreadable; commands beyond this rig's
            # declared limits are implausible, which validate reports and --allow-implausible accepts.
            lines = command_problems(block, None)
            if lines:
                raise FormatError(f"{where}: {lines[0].split(': ', 1)[1]}")
        if key == "time" and start == 0 and stop == n:
            line = time_order_problem(block) or frame_interval_problem(block, self.store.attrs.frame_rate_hz)
            if line is not None:
                raise FormatError(f"{where}: {line}")
        return block

    def read_time(self) -> np.ndarray:
        """The whole ``time`` array, checked (``read``), kept after the first call."""
        if self._time is None:
            self._time = self.read("time")
        return self._time

    def _chunk_of(self, key: str, frame: int) -> str:
        arr = self.array(key)
        chunks = arr.metadata.chunk_grid.chunk_shape
        if any(c < s for c, s in zip(chunks[1:], arr.shape[1:])):
            return ""  # chunked along other axes too: the frame alone says where
        return f" in chunk {arr.metadata.encode_chunk_key((frame // chunks[0],) + (0,) * (arr.ndim - 1))}"

    def _decode_error(self, key: str, start: int, stop: int, exc: Exception) -> FormatError:
        """The error for a read that failed: it names the first chunk that fails on its own."""
        arr = self.array(key)
        chunks = arr.metadata.chunk_grid.chunk_shape
        for coords in chunk_coords(arr, start, stop):
            sel = tuple(slice(c * cs, min((c + 1) * cs, n)) for c, cs, n in zip(coords, chunks, arr.shape))
            try:
                arr[sel]
            except Exception as one:
                return FormatError(f"{self.where}/{key}: chunk {arr.metadata.encode_chunk_key(coords)} cannot be "
                                   f"decoded ({one_line(one)})")
        return FormatError(f"{self.where}/{key}: frames {start}..{stop - 1} cannot be read ({one_line(exc)})")

    def load(self, image_dtype: str | np.dtype | None = None) -> RunData:
        """Read the whole run into memory (decoding each chunk once), checked as ``read`` does."""
        images = self.read("images")
        if image_dtype is not None:
            images = images.astype(image_dtype, copy=False)
        opt = {k: (self.read(k) if self.has(k) else None) for k in OPTIONAL_ARRAYS}
        return RunData(self.name, self.split, images, self.read("velocity"), self.read_time(), **opt)

    def to_xarray(self):
        """The run as a lazy ``xarray.Dataset`` with dims (time, range, azimuth)."""
        try:
            import xarray as xr
        except ImportError:  # pragma: no cover - depends on the environment
            raise SonarSetError("xarray is not installed: pip install 'sonarset[xarray]'") from None
        return xr.open_zarr(self.store.group.store, group=self.name, consolidated=False)

    def __repr__(self) -> str:
        return f"Run({self.name!r}, split={self.split!r}, frames={self.n_frames})"
