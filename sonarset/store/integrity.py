"""Chunk integrity: what a reader verifies before it lets zarr decode a chunk.

zarr-python trusts storage. It reads a missing chunk as the array's fill value (zeros or NaN,
silently), and it decodes a blosc chunk as long as the chunk's own header claims it is: a small
chunk that blosc stored uncompressed ("memcpyed") and that was truncated in place then decodes to
whatever memory follows the buffer, finite numbers that look like data. So before decoding, a
reader checks that each chunk exists and that its size agrees with its header (blosc) or with the
chunk shape (no compressor). Other codec chains (zstd, gzip, sharding...) carry no size we can
check cheaply; for them we rely on their decoders' own errors and on the value checks.

From format 1.2 each chunk ends with a crc32c checksum of the bytes before it (zarr's ``crc32c``
codec, last in the chain): zarr verifies it as it decodes, so a flipped bit anywhere in a chunk
fails the read ("checksum mismatch", ``run.decode_problems``). The checks here look past it: the
sizes exclude its 4 bytes, and a chunk they find unsound is also said to fail its checksum when it does.
"""

from __future__ import annotations

import itertools
import math
import os
import struct
from typing import Iterable, Iterator

import numpy as np
import zarr
from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec

from sonarset.format.problems import Problem

BLOSC_HEADER_BYTES = 16
CHECKSUM_BYTES = 4  # the crc32c codec's trailer
CHECKSUM_MISMATCH = "checksum mismatch"


def checksum_fails(data: bytes) -> bool:
    """Whether a chunk as stored by the crc32c codec (its bytes, then their crc32c, little-endian)
    fails its checksum."""
    import google_crc32c  # zarr's own dependency for the codec

    if len(data) < CHECKSUM_BYTES:
        return True
    return google_crc32c.value(data[:-CHECKSUM_BYTES]) != int.from_bytes(data[-CHECKSUM_BYTES:], "little")


def is_checksum_error(exc: BaseException) -> bool:
    """Whether ``exc`` is zarr's crc32c codec refusing a chunk whose bytes fail their checksum."""
    return isinstance(exc, ValueError) and "checksum" in str(exc).lower()  # "Stored and computed checksum do not match"


def chunk_coords(arr: zarr.Array, start: int = 0, stop: int | None = None) -> Iterable[tuple[int, ...]]:
    """Grid coordinates of the stored chunks that hold frames ``start .. stop-1`` (first axis)."""
    chunks = arr.metadata.chunk_grid.chunk_shape  # outer (shard) chunks when sharded
    stop = arr.shape[0] if stop is None else stop
    if arr.ndim == 0 or stop <= start:
        return iter(())
    first = range(start // chunks[0], math.ceil(stop / chunks[0]))
    rest = [range(math.ceil(s / c)) for s, c in zip(arr.shape[1:], chunks[1:])]
    # itertools.product would first copy every range into a tuple: the time axis may declare 1e11 chunks
    return ((i, *tail) for i in first for tail in itertools.product(*rest))


def declared_chunks(arr: zarr.Array) -> int:
    """How many stored chunks the array's shape declares."""
    chunks = arr.metadata.chunk_grid.chunk_shape
    return math.prod(math.ceil(s / c) for s, c in zip(arr.shape, chunks)) if arr.ndim else 1


def _blosc_phrase(head: bytes, size: int, decoded_nbytes: int, trailer: int = 0) -> str | None:
    """What is wrong with a blosc chunk of ``size`` bytes starting with ``head`` (and ending with a
    checksum of ``trailer`` bytes); None if nothing.

    Blosc 1.x header: version, versionlz, flags, typesize (1 byte each), then little-endian uint32
    nbytes (decoded size), blocksize and cbytes (the whole blosc chunk, header included).
    """
    if size < BLOSC_HEADER_BYTES + trailer:
        return f"is corrupt or truncated: {size} bytes, shorter than a blosc header"
    nbytes, _, cbytes = struct.unpack("<III", head[4:BLOSC_HEADER_BYTES])
    if cbytes + trailer != size:
        total = f", {cbytes + trailer} with its checksum;" if trailer else ","
        return f"is corrupt or truncated: its blosc header declares {cbytes} bytes{total} the chunk has {size}"
    if nbytes != decoded_nbytes:
        return (f"is corrupt: its blosc header declares {nbytes} decoded bytes, "
                f"the chunk shape needs {decoded_nbytes}")
    return None


class ChunkChecker:
    """Checks the stored chunks of one array: present, and sized as their header or shape says."""

    def __init__(self, arr: zarr.Array):
        self.arr = arr
        codecs = tuple(arr.metadata.codecs)
        #: bytes of the crc32c checksum that ends each chunk (format 1.2), 0 without one
        self.trailer = CHECKSUM_BYTES if codecs and isinstance(codecs[-1], Crc32cCodec) else 0
        codecs = codecs[:-1] if self.trailer else codecs
        chunk_shape = arr.metadata.chunk_grid.chunk_shape
        self.decoded_nbytes = int(np.prod(chunk_shape)) * np.dtype(arr.dtype).itemsize
        plain = len(codecs) >= 1 and isinstance(codecs[0], BytesCodec)
        if plain and len(codecs) == 1:
            self.kind = "raw"
        elif plain and len(codecs) == 2 and isinstance(codecs[1], BloscCodec):
            self.kind = "blosc"
        else:
            self.kind = "other"
        store = arr.store_path.store
        root = getattr(store, "root", None)
        # Local files: a stat and a 16-byte read per chunk (plain strings: pathlib's joins cost as
        # much as the stat). Elsewhere one get per chunk, which a caching store (sonarset.store.cache)
        # keeps for the decode that follows.
        self.local = (os.path.join(str(root), arr.store_path.path) if isinstance(store, zarr.storage.LocalStore)
                      else None)

    def key(self, coords: tuple[int, ...]) -> str:
        return self.arr.metadata.encode_chunk_key(coords)

    def _problem(self, coords: tuple[int, ...]) -> str | None:
        """None when the chunk at ``coords`` looks sound, else what is wrong (a phrase)."""
        key = self.key(coords)
        if self.local is None:
            return self._fetch([key])[0]
        path = os.path.join(self.local, key)
        try:
            size = os.stat(path).st_size
            head = b""
            if self.kind == "blosc":
                with open(path, "rb") as f:
                    head = f.read(BLOSC_HEADER_BYTES)
            phrase = self._judge(size, head)
            if phrase is not None and self.trailer:  # damage found: read it whole, to say whether it is bit rot
                with open(path, "rb") as f:
                    phrase = self._with_checksum(phrase, f.read())
        except FileNotFoundError:
            return self._missing()
        except IsADirectoryError:
            return "is a directory, not a chunk file"
        return phrase

    def _with_checksum(self, phrase: str, data: bytes) -> str:
        """``phrase`` about an unsound chunk whose stored bytes are ``data``, saying that it also
        fails its checksum where it does."""
        return f"{phrase}; {CHECKSUM_MISMATCH}" if self.trailer and checksum_fails(data) else phrase

    def _fetch(self, keys: list[str]) -> list[str | None]:
        """What is wrong with each chunk of a non-local store (``_judge``), fetched concurrently,
        as zarr itself would: one at a time, a slab of 16 chunks would wait 16 round trips."""
        import asyncio

        from zarr.core.buffer import default_buffer_prototype
        from zarr.core.sync import sync

        store, base = self.arr.store_path.store, self.arr.store_path.path

        async def fetch_all():
            return await asyncio.gather(*(store.get(f"{base}/{k}", prototype=default_buffer_prototype())
                                          for k in keys))

        out = []
        for buf in sync(fetch_all()):
            raw = None if buf is None else buf.to_bytes()
            phrase = self._judge(None, b"") if raw is None else self._judge(len(raw), raw[:BLOSC_HEADER_BYTES])
            out.append(phrase if raw is None or phrase is None else self._with_checksum(phrase, raw))
        return out

    def _fetched(self, keys: Iterable[str], batch: int = 64) -> Iterator[tuple[str, str | None]]:
        """(key, phrase) of each chunk of a non-local store, fetched ``batch`` at a time: concurrent
        enough to hide round trips, and a caller that stops early never lists the rest."""
        keys = iter(keys)
        while block := list(itertools.islice(keys, batch)):
            yield from zip(block, self._fetch(block))

    def _judge(self, size: int | None, head: bytes) -> str | None:
        if size is None:
            return self._missing()
        if self.kind == "blosc":
            return _blosc_phrase(head, size, self.decoded_nbytes, self.trailer)
        if self.kind == "raw" and size != self.decoded_nbytes + self.trailer:
            checksum = f", and its checksum {self.trailer} more" if self.trailer else ""
            return f"is corrupt or truncated: {size} bytes, the chunk shape needs {self.decoded_nbytes}{checksum}"
        return None

    def _missing(self) -> str:
        fill = self.arr.metadata.fill_value
        return f"{_MISSING} (deleted?); zarr would silently read it as the fill value {fill}"

    def first_problem(self, start: int = 0, stop: int | None = None) -> list[Problem]:
        """The first unsound chunk holding frames start..stop-1 (what a reader refuses)."""
        coords = chunk_coords(self.arr, start, stop)  # lazy: a reader stops at the first unsound chunk
        if self.local is None:
            found = self._fetched(map(self.key, coords))
        else:
            found = ((self.key(c), self._problem(c)) for c in coords)
        for key, phrase in found:
            if phrase is not None:
                return [Problem("", f"chunk {key} {phrase}")]
        return []

    def damage(self) -> tuple[list[Problem], list[Problem]]:
        """Every unsound chunk, as ``validate`` reports them: the chunks missing from storage, in one
        problem, and the first whose size disagrees with its header or shape (zarr would decode it
        from memory past its end)."""
        missing, damaged = [], None
        coords = chunk_coords(self.arr)
        if self.local is None:
            found = self._fetched(map(self.key, coords))
        else:
            found = ((self.key(c), self._problem(c)) for c in coords)
        for key, phrase in found:
            if phrase is None:
                continue
            if phrase.startswith(_MISSING):
                missing.append(key)
            elif damaged is None:
                damaged = Problem("", f"chunk {key} {phrase}")
        lost = [Problem("", f"{len(missing)} chunk(s) missing from storage (deleted?), first: {missing[0]}")] if missing else []
        return lost, ([damaged] if damaged is not None else [])


    def beyond_storage(self) -> list[Problem]:
        """A local array whose shape declares far more chunks than its folder holds files (an
        edited length, a runaway writer): said from the counts, in the time of a listing of what
        is stored, where visiting each declared chunk could take hours. A remote array, which may
        not list, is probed instead (``_beyond_remote``)."""
        declared = declared_chunks(self.arr)
        if self.local is None:
            return self._beyond_remote(declared)
        stored = self._stored_files()
        if declared <= 2 * stored + 16:
            return []
        first = next(k for k in map(self.key, chunk_coords(self.arr)) if not os.path.exists(os.path.join(self.local, k)))
        return [Problem("", f"at least {declared - stored} of {declared} chunk(s) missing from storage "
                            f"(deleted, or a shape edited?), first: {first}")]

    def _beyond_remote(self, declared: int) -> list[Problem]:
        """Writers fill an array's chunks from the first frame on, so when the last declared chunk
        is missing, a bisection on the first chunk of each time step finds where storage ends in
        about log2(chunks) requests. Only a length far beyond that end is refused here; holes
        before it are what ``damage`` and the readers report, chunk by chunk."""
        if self.arr.ndim == 0:
            return []
        time_chunks = math.ceil(self.arr.shape[0] / self.arr.metadata.chunk_grid.chunk_shape[0])
        per_step = declared // max(time_chunks, 1)
        if time_chunks < 16 or self._has_time_chunk(time_chunks - 1):
            return []
        lo, hi = -1, time_chunks - 1  # chunk lo is stored (or lo is before the first), hi is not
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if self._has_time_chunk(mid) else (lo, mid)
        stored = hi * per_step
        if declared <= 2 * stored + 16:
            return []
        first = self.key((hi,) + (0,) * (self.arr.ndim - 1))
        return [Problem("", f"{declared} chunk(s) declared, but storage ends at chunk {first} "
                            f"(the last is missing too; deleted, or a shape edited?)")]

    def _has_time_chunk(self, i: int) -> bool:
        from zarr.core.sync import sync

        key = self.key((i,) + (0,) * (self.arr.ndim - 1))
        return sync(self.arr.store_path.store.exists(f"{self.arr.store_path.path}/{key}"))

    def _stored_files(self) -> int:
        """Files below the local array's folder other than its metadata: at most its stored chunks."""
        return sum(len(files) - ("zarr.json" in files) for _, _, files in os.walk(self.local))


_MISSING = "is missing from storage"
