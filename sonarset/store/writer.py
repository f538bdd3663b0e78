"""Writing one run group block by block, made visible only when complete (spec/FORMAT.md §5)."""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec

from sonarset.errors import InputValidationError, SonarSetError
from sonarset.format.arrays import ARRAYS, OPTIONAL_ARRAYS, expected_shape, run_array_problems, time_order_problems
from sonarset.format.attrs import NAMESPACE, RunAttrs, run_name_problems
from sonarset.format.problems import raise_first
from sonarset.store.root import StoreRoot
from sonarset.store.run import Run

DEFAULT_CHUNK_FRAMES = 64  # 64 x 200 x 90 float16 = 2.3 MB: large enough to stream, small to cache


def with_checksum(*codecs) -> tuple:
    """A chunk's bytes-to-bytes codecs, then its crc32c checksum (format 1.2, spec/FORMAT.md §2):
    the checksum covers the stored bytes, so every flipped bit is caught before decoding."""
    return (*codecs, Crc32cCodec())


def compressor(dtype: np.dtype, sparse: bool = False) -> BloscCodec:
    # lz4: raw energyscapes carry a noise floor that no codec squeezes much (zstd-3 gives 1.5x, lz4
    # with bitshuffle 1.3x), so speed wins: 3x faster writes and reads (bench/bench_generate.py).
    # Post-processed energyscapes are mostly exact zeros: without a shuffle lz4 packs them 5x, and
    # 4x faster than with bitshuffle (2.1x).
    return BloscCodec(cname="lz4", clevel=1, shuffle="noshuffle" if sparse else "bitshuffle",
                      typesize=np.dtype(dtype).itemsize)


class RunWriter:
    """Writes one run group of the store ``root`` block by block; ``commit()`` makes it visible.

    Use as a context manager: an exception inside deletes the half-written group. A killed
    process leaves it with ``complete: false``, which readers ignore and the next writer of the
    same name replaces.
    """

    def __init__(
        self,
        root: StoreRoot,
        name: str,
        n_frames: int,
        *,
        split: str = "train",
        source: Mapping[str, Any] | None = None,
        optional: tuple[str, ...] = (),
        image_dtype: str = "float16",
        overwrite: bool = False,
        consolidate: bool = True,
        chunk_frames: int = DEFAULT_CHUNK_FRAMES,
    ):
        raise_first(run_name_problems(name), SonarSetError)
        unknown = set(optional) - set(OPTIONAL_ARRAYS)
        if unknown:
            raise SonarSetError(f"unknown optional arrays: {', '.join(sorted(unknown))}")
        if image_dtype not in ARRAYS["images"].dtypes:
            raise SonarSetError(f"image dtype must be float16 or float32, got {image_dtype}")
        if n_frames < 1:
            raise SonarSetError(f"run {name!r}: needs at least one frame")
        self.store, self.name, self.n_frames = root, name, int(n_frames)
        self.consolidate = consolidate
        self.attrs = RunAttrs(complete=False, n_frames=self.n_frames, split=split, source=dict(source or {}))
        group = root.group
        if name in group.group_keys() or name in group.array_keys():
            existing = root.run_attrs(name)
            if existing is not None and existing.complete and not overwrite:
                raise SonarSetError(f"{root.location}: run {name!r} already exists; overwrite replaces it",
                                    parameter="overwrite")
            del group[name]
        self.group = group.create_group(name, attributes={NAMESPACE: self.attrs.model_dump(mode="json")})
        self.arrays = self._create_frame_arrays(optional, image_dtype, chunk_frames)
        self._write_coordinates()
        self._written = np.zeros(self.n_frames, dtype=bool)
        # Per-frame vectors are one chunk each: written block by block, every block would rewrite
        # (decompress and compress) the whole chunk. They are a few bytes a frame, so they are
        # kept here and written once, at commit, before the completion flag.
        self._small = {k: np.full(a.shape, np.nan, a.dtype) for k, a in self.arrays.items() if k != "images"}

    def _create_frame_arrays(self, optional: tuple[str, ...], image_dtype: str,
                             chunk_frames: int) -> dict[str, zarr.Array]:
        """The run's per-frame arrays, empty (NaN): images in chunks of ``chunk_frames`` frames,
        the small per-frame vectors in one chunk each."""
        T, (R, A) = self.n_frames, self.store.grid.shape
        cf = max(1, min(chunk_frames, T))
        arrays: dict[str, zarr.Array] = {}
        sparse = self.store.attrs.processing.clip_at_zero  # images mostly exact zeros
        for key in ("images", "velocity", "time", *optional):
            spec = ARRAYS[key]
            dtype = image_dtype if key == "images" else spec.write_dtype
            shape = expected_shape(key, T, (R, A))
            chunks = (cf, R, A) if key == "images" else shape
            arrays[key] = self.group.create_array(
                key, shape=shape, chunks=chunks, dtype=dtype, dimension_names=spec.dims,
                compressors=with_checksum(compressor(np.dtype(dtype), sparse and key == "images")),
                fill_value=np.nan,
                attributes={"units": spec.units, "description": spec.description},
            )
        return arrays

    def _write_coordinates(self) -> None:
        """The range and azimuth bin centres of the store's grid."""
        grid = self.store.grid
        for key, values in (("range", grid.range_centres()), ("azimuth", grid.azimuth_centres())):
            spec = ARRAYS[key]
            arr = self.group.create_array(
                key, shape=values.shape, chunks=values.shape, dtype=spec.write_dtype, dimension_names=spec.dims,
                compressors=with_checksum(), fill_value=np.nan,
                attributes={"units": spec.units, "description": spec.description},
            )
            arr[:] = values

    def write(self, start: int, checked: bool = False, **blocks: np.ndarray | None) -> None:
        """Write frames ``start .. start+len-1`` of the given arrays (images, velocity, time...)."""
        blocks = {k: np.asarray(v) for k, v in blocks.items() if v is not None}
        for key in blocks:
            if key not in self.arrays:
                raise SonarSetError(f"run {self.name!r}: array {key!r} was not declared when the writer was made")
        n = blocks["images"].shape[0] if "images" in blocks else None
        if n is None or any(v.shape[0] != n for v in blocks.values()) or set(blocks) != set(self.arrays):
            raise SonarSetError(f"run {self.name!r}: each block must give every array ({', '.join(self.arrays)}) "
                                "with the same number of frames")
        if start < 0 or start + n > self.n_frames:
            raise SonarSetError(f"run {self.name!r}: frames {start}..{start + n - 1} outside 0..{self.n_frames - 1}")
        problems = [] if checked else run_array_problems(self.store.grid, blocks)
        if problems:
            raise InputValidationError(f"run {self.name!r} frames {start}..{start + n - 1}", problems)
        for key, values in blocks.items():
            if key in self._small:
                self._small[key][start:start + n] = values
            else:
                self.arrays[key][start:start + n] = values.astype(self.arrays[key].dtype, copy=False)
        self._written[start:start + n] = True

    def commit(self) -> RunAttrs:
        """Write the per-frame vectors, then the completion flag; returns the run's attributes."""
        if not self._written.all():
            missing = int(np.flatnonzero(~self._written)[0])
            raise SonarSetError(f"run {self.name!r}: frame {missing} was never written")
        # each block was checked alone: check across them
        raise_first([p.at(f"run {self.name!r}") for p in time_order_problems(self._small["time"])], SonarSetError)
        for key, values in self._small.items():
            self.arrays[key][:] = values
        attrs = self.attrs.model_copy(update={"complete": True})
        # Flagged complete only once storage holds what a reader will accept (every array and chunk
        # present, sized as declared): a writer that lost an array to a concurrent one fails here.
        Run(self.store, self.name, attrs).check(chunks=True)
        # The completion flag is the run's last write: everything before it is already durable.
        self.group.attrs.update({NAMESPACE: attrs.model_dump(mode="json")})
        if self.consolidate:
            self.store.consolidate()
        self._committed = True
        return attrs

    def abort(self) -> None:
        self.store.delete_run(self.name)

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and not getattr(self, "_committed", False):
            self.abort()
