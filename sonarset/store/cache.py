"""A read-through, size-bounded LRU cache of store values (chunks and metadata) for remote stores.

Readers of a remote store (``s3://``, ``gs://``, ``https://``...) ask for the same chunk many
times: a 64-frame image chunk serves up to 64 windows, and NumPy, torch and xarray readers slice
it window by window. Without a cache each slice is a network round trip. Wrapping the zarr store
keeps the most recently used values in memory, so each chunk crosses the network once while it
stays hot. Writers never use it (they must see the store as it is).
"""

from __future__ import annotations

from collections import OrderedDict

from zarr.abc.store import ByteRequest
from zarr.core.buffer import Buffer, BufferPrototype
from zarr.storage import WrapperStore

DEFAULT_CACHE_BYTES = 512 * 2**20


class ChunkCache(WrapperStore):
    """LRU cache of up to ``max_bytes`` of values read from the wrapped (read-only) store."""

    def __init__(self, store, max_bytes: int = DEFAULT_CACHE_BYTES):
        super().__init__(store)
        self.max_bytes = int(max_bytes)
        self._lru: OrderedDict = OrderedDict()
        self._size = 0
        self.hits = 0
        self.misses = 0

    def _with_store(self, store) -> "ChunkCache":
        return type(self)(store, self.max_bytes)

    async def get(self, key: str, prototype: BufferPrototype, byte_range: ByteRequest | None = None) -> Buffer | None:
        # zarr runs store calls on one event loop thread: no lock needed around the dict
        k = (key, repr(byte_range))
        if k in self._lru:
            self._lru.move_to_end(k)
            self.hits += 1
            return self._lru[k]
        self.misses += 1
        value = await self._store.get(key, prototype, byte_range)
        if value is not None and len(value) <= self.max_bytes:
            self._lru[k] = value
            self._size += len(value)
            while self._size > self.max_bytes:
                _, old = self._lru.popitem(last=False)
                self._size -= len(old)
        return value

    def __repr__(self) -> str:
        return f"ChunkCache({self._store!r}, {self._size}/{self.max_bytes} bytes, hits={self.hits}, misses={self.misses})"
