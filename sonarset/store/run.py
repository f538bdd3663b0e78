"""A run of a SonarSet store, read lazily and checked as it is read (spec/FORMAT.md §2).

The helpers that open a run's arrays (``run_members``, ``open_array``, ``decode_problems``) are
what ``validate`` walks a run with too: the reader raises the first of their problems.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import zarr

from sonarset.errors import FormatError, RemoteError, SonarSetError, one_line
from sonarset.format.arrays import (
    ARRAYS, OPTIONAL_ARRAYS, array_meta_problems, coordinate_problems, expected_shape, frame_interval_problems,
    time_order_problems, value_problems,
)
from sonarset.format.attrs import RunAttrs
from sonarset.format.problems import Problem, raise_first
from sonarset.format.rules import command_limit_problems
from sonarset.store.integrity import CHECKSUM_MISMATCH, ChunkChecker, chunk_coords, is_checksum_error
from sonarset.store.root import StoreRoot
from sonarset.store.zarrio import child_names


def run_members(group: zarr.Group) -> dict[str, zarr.Array | None]:
    """The arrays of a run group by name, opened by one listing; where one member's metadata is
    unreadable, every child as stored, unopened (None: ``open_array`` then says which)."""
    try:
        return dict(group.arrays())
    except RemoteError:  # the server failed, not the store: never a finding
        raise
    except Exception:
        return dict.fromkeys(child_names(group))


def open_array(group: zarr.Group, key: str, where: str, n_frames: int, grid_shape: tuple[int, int],
               present: Mapping[str, zarr.Array | None]) -> tuple[zarr.Array | None, list[Problem]]:
    """Array ``key`` of the run group at ``where`` (whose members are ``present``: ``run_members``),
    and every problem with its metadata; None where its values cannot be read (missing,
    unreadable, or a dtype or shape the spec does not allow)."""
    if key not in present:
        return None, [Problem(where, f"missing {'required' if ARRAYS[key].required else 'optional'} array {key!r}")]
    aw = f"{where}/{key}"
    try:
        arr = present[key] if present[key] is not None else group[key]
        if not isinstance(arr, zarr.Array):
            return None, [Problem(aw, "is a group, not an array")]
        dims = tuple(arr.metadata.dimension_names or ())
        dtype, shape = str(arr.dtype), tuple(arr.shape)
    except RemoteError:
        raise
    except Exception as exc:  # metadata zarr cannot parse, or parsed but we cannot interpret
        return None, [Problem(aw, f"unreadable zarr metadata ({one_line(exc)})")]
    problems = [p.at(where) for p in array_meta_problems(key, dtype, dims, shape, n_frames, grid_shape)]
    readable = dtype in ARRAYS[key].dtypes and shape == expected_shape(key, n_frames, grid_shape)
    return (arr if readable else None), problems


def decode_problems(arr: zarr.Array, start: int, stop: int, exc: Exception) -> list[Problem]:
    """Frames ``start .. stop-1`` of ``arr`` failed to decode with ``exc``: the first chunk among
    them that fails on its own."""
    chunks = arr.metadata.chunk_grid.chunk_shape
    for coords in chunk_coords(arr, start, stop):
        sel = tuple(slice(c * cs, min((c + 1) * cs, n)) for c, cs, n in zip(coords, chunks, arr.shape))
        try:
            arr[sel]
        except RemoteError:
            raise
        except Exception as one:
            key = arr.metadata.encode_chunk_key(coords)
            if is_checksum_error(one):
                return [Problem("", f"chunk {key} is corrupt or truncated: {CHECKSUM_MISMATCH} (its bytes "
                                    "disagree with the crc32c stored with them)")]
            return [Problem("", f"chunk {key} is corrupt or truncated: cannot be decoded ({one_line(one)})")]
    return [Problem("", f"frames {start}..{stop - 1} cannot be read ({one_line(exc)})")]


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

    def __init__(self, store: StoreRoot, name: str, attrs: RunAttrs, group: zarr.Group | None = None,
                 members: dict[str, zarr.Array | None] | None = None):
        """``group`` and ``members`` (``run_members``): the run's group and arrays where the caller
        opened them already (a listing of the store opens them all at once)."""
        self.store, self.name, self.attrs = store, name, attrs
        #: Frames in the run (the length of every per-frame array), and the split it belongs to.
        self.n_frames, self.split = attrs.n_frames, attrs.split
        self.where = f"{store.location}/{name}"
        try:
            self.group = store.group[name] if group is None else group
        except RemoteError:
            raise
        except Exception as exc:
            raise FormatError(f"{self.where}: unreadable zarr metadata ({one_line(exc)})") from None
        self._members = members
        self._identity = self._folder_identity()
        self._arrays: dict[str, zarr.Array] = {}
        self._checkers: dict[str, ChunkChecker] = {}
        self._time: np.ndarray | None = None

    def _folder_identity(self) -> tuple[int, int] | None:
        """(device, inode) of a local run's folder; None for remote stores or when it is gone. A
        replaced run (an overwriting import swaps a new folder in) has another identity."""
        root = getattr(self.store.group.store, "root", None)
        if not isinstance(self.store.group.store, zarr.storage.LocalStore) or root is None:
            return None
        try:
            st = os.stat(os.path.join(str(root), self.store.group.path, self.name))
        except OSError:
            return None
        return st.st_dev, st.st_ino

    def replaced(self) -> bool:
        """Whether the run's folder was replaced since the run was opened (a local store only)."""
        return self._identity is not None and self._folder_identity() != self._identity

    def _unchanged(self) -> None:
        """FormatError when the run was replaced since it was opened: what was read may mix the two."""
        if self.replaced():
            raise FormatError(f"{self.where}: run changed while reading (another writer replaced it); "
                              "open it again to read the new one")

    def _member_arrays(self) -> dict[str, zarr.Array | None]:
        if self._members is None:
            self._members = run_members(self.group)
        return self._members

    def has(self, key: str) -> bool:
        return key in self._member_arrays()

    def array(self, key: str) -> zarr.Array:
        """Array ``key`` after its metadata was checked against the spec (dtype, shape, dimension
        names); FormatError if it is missing, unreadable or does not conform."""
        if key in self._arrays:
            return self._arrays[key]
        if key not in ARRAYS:
            raise KeyError(key)
        arr, problems = open_array(self.group, key, self.where, self.n_frames, self.store.grid.shape,
                                   self._member_arrays())
        raise_first(problems)
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
            # cheap (a listing), and before anything reads: an absurd length is refused, not allocated
            raise_first([p.at(f"{self.where}/{key}") for p in self._checker(key).beyond_storage()])
        for key in ("range", "azimuth"):
            raise_first([p.at(self.where) for p in coordinate_problems(key, self.read(key), self.store.grid)])
        if chunks:
            for key in keys:
                if self._checker(key).local is None:
                    # Remote: checking a chunk means fetching it, so each chunk is checked when
                    # it is read (``read``), through the chunk cache, not all of them at open.
                    continue
                raise_first([p.at(f"{self.where}/{key}") for p in self._checker(key).first_problem()])

    def read(self, key: str, start: int = 0, stop: int | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """Frames ``start .. stop-1`` of array ``key`` (all of a coordinate array), checked.

        The chunks read must be present and as long as their headers say, must decode, and the
        values must be what the spec allows (images finite and in [0, 1], the rest finite; a
        whole ``time`` array also strictly increasing and spaced as the declared frame rate; a
        whole ``velocity`` array commands a ground robot could follow), by the rules ``validate``
        applies (``sonarset.format``); commands beyond the store's own rig are only implausible.

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
        raise_first([p.at(where) for p in self._checker(key).first_problem(start, stop)])
        try:
            block = arr[start:stop]
        except RemoteError:
            raise
        except Exception as exc:
            raise_first([p.at(where) for p in decode_problems(arr, start, stop, exc)])
        step = block.shape[0] if out is None else max(1, arr.metadata.chunk_grid.chunk_shape[0])
        for i in range(0, block.shape[0], step):
            piece = block[i:i + step]
            for problem in value_problems(key, piece, start + i):
                raise FormatError(f"{problem.at(self.where)}{self._chunk_of(key, problem.frame)}")
            if out is not None:
                out[i:i + piece.shape[0]] = piece
        if out is not None:
            block = out
        if key == "velocity" and start == 0 and stop == n:
            raise_first([p.at(self.where) for p in command_limit_problems(block)])
        if key == "time" and start == 0 and stop == n:
            raise_first([p.at(self.where) for p in
                         time_order_problems(block) or frame_interval_problems(block, self.store.attrs.frame_rate_hz)])
        self._unchanged()  # after the read: a swap during it, or since the run's other reads, is caught
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
