"""Bounded waits on remote stores: every request to a URL store has a time limit, transient server
failures are retried with backoff, and what still fails is one line naming the URL and the cause.

Without this a server that accepts a connection and never answers (or sends a byte a second)
holds a reader for as long as the TCP stack allows, and an HTTP 500 or a body cut short surfaces
as aiohttp's own exception. The limits apply per request, so a store of any size is bounded by
its slowest request, not by its size:

- ``SONARSET_REMOTE_TIMEOUT`` (seconds, default 20): the most one request may take, the answer
  read in full. 20 s is generous for a chunk (a few MB) from object storage, and keeps a command
  that meets a dead server under 30 s with its start-up. A request that runs out of time is not
  retried: a server that said nothing for that long is not expected to answer the next time, and
  retrying would multiply the wait.
- ``SONARSET_REMOTE_RETRIES`` (default 3): how many times a request that failed transiently
  (HTTP 5xx, 408, 429, a body shorter than its Content-Length, a dropped connection) is tried
  again, after 0.5 s, 1 s, 2 s...

``RemoteLimits`` carries the same two numbers for the Python API (``open_store(url, remote_limits=RemoteLimits(timeout_s=10))``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import os
from typing import AsyncIterator, Iterable

from zarr.abc.store import ByteRequest
from zarr.core.buffer import Buffer, BufferPrototype
from zarr.storage import WrapperStore

from sonarset.errors import RemoteError, SonarSetError, one_line

TIMEOUT_VARIABLE = "SONARSET_REMOTE_TIMEOUT"
RETRIES_VARIABLE = "SONARSET_REMOTE_RETRIES"


@dataclasses.dataclass(frozen=True)
class RemoteLimits:
    """Per-request time limit (s) and the number of retries of a transient failure."""

    timeout_s: float = 20.0
    retries: int = 3
    backoff_s: float = 0.5

    def __post_init__(self):
        if not (self.timeout_s > 0 and self.timeout_s != float("inf")):
            raise SonarSetError(f"remote timeout must be a finite number of seconds > 0, got {self.timeout_s}")
        if self.retries < 0:
            raise SonarSetError(f"remote retries must be >= 0, got {self.retries}")

    @classmethod
    def from_environment(cls) -> "RemoteLimits":
        """The limits ``SONARSET_REMOTE_TIMEOUT`` and ``SONARSET_REMOTE_RETRIES`` set (defaults otherwise)."""
        values: dict = {}
        for name, field, kind in ((TIMEOUT_VARIABLE, "timeout_s", float), (RETRIES_VARIABLE, "retries", int)):
            text = os.environ.get(name)
            if text is None or not text.strip():
                continue
            try:
                values[field] = kind(text)
            except ValueError:
                raise SonarSetError(f"{name}={text!r} is not a {'number' if kind is float else 'whole number'}") from None
        try:
            return cls(**values)
        except SonarSetError as exc:
            raise SonarSetError(f"{TIMEOUT_VARIABLE}/{RETRIES_VARIABLE}: {exc}") from None


def transient(exc: BaseException) -> bool:
    """Whether a failed request is worth another try: a server error, a body cut short, a dropped
    connection. Missing keys, refusals (4xx) and timeouts are not."""
    status = getattr(exc, "status", None) or getattr(exc, "code", None)
    if isinstance(status, int):
        return status >= 500 or status in (408, 429)
    try:
        import aiohttp
    except ImportError:  # only fsspec's HTTP filesystem needs it
        aiohttp = None
    if aiohttp is not None and isinstance(exc, (aiohttp.ClientPayloadError, aiohttp.ServerDisconnectedError,
                                                aiohttp.ClientConnectionError)):
        return not isinstance(exc, aiohttp.ClientConnectorCertificateError)
    return isinstance(exc, (ConnectionError, asyncio.IncompleteReadError))


def cause(exc: BaseException) -> str:
    """Why a request failed, in words: the HTTP status, or a body cut short, else the exception."""
    status = getattr(exc, "status", None)
    if isinstance(status, int):
        return f"HTTP {status} {getattr(exc, 'message', '') or ''}".rstrip()
    if type(exc).__name__ == "ClientPayloadError":
        return f"the answer was cut short ({one_line(exc.__cause__ or exc.args[-1] if exc.args else exc)})"
    return one_line(exc)


class BoundedRemote(WrapperStore):
    """A zarr store whose every request ends within ``limits.timeout_s`` and whose transient
    failures are retried ``limits.retries`` times; ``url`` names the store in errors."""

    def __init__(self, store, url: str = "", limits: RemoteLimits | None = None):
        super().__init__(store)
        self.url = url.rstrip("/")
        self.limits = limits or RemoteLimits.from_environment()

    def _with_store(self, store) -> "BoundedRemote":
        return type(self)(store, self.url, self.limits)

    async def _call(self, key: str, make):
        """``await make()`` within the limits; RemoteError naming ``key`` when they are spent."""
        limits = self.limits
        for attempt in range(limits.retries + 1):
            try:
                return await asyncio.wait_for(make(), limits.timeout_s)
            except asyncio.TimeoutError:
                raise RemoteError(f"{self.where(key)}: no complete answer within {limits.timeout_s:g} s "
                                  f"(the limit is {TIMEOUT_VARIABLE})") from None
            except (FileNotFoundError, KeyError, SonarSetError):
                raise
            except Exception as exc:
                if not transient(exc):
                    if isinstance(exc, OSError):
                        raise
                    raise RemoteError(f"{self.where(key)}: {cause(exc)}") from None
                if attempt == limits.retries:
                    raise RemoteError(f"{self.where(key)}: {cause(exc)} (tried {limits.retries + 1} times; "
                                      f"retries are {RETRIES_VARIABLE})") from None
                await asyncio.sleep(limits.backoff_s * 2**attempt)

    def where(self, key: str) -> str:
        return f"{self.url}/{key}" if key else self.url

    async def get(self, key: str, prototype: BufferPrototype, byte_range: ByteRequest | None = None) -> Buffer | None:
        return await self._call(key, lambda: self._store.get(key, prototype, byte_range))

    async def get_partial_values(self, prototype: BufferPrototype,
                                 key_ranges: Iterable[tuple[str, ByteRequest | None]]) -> list[Buffer | None]:
        return list(await asyncio.gather(*(self.get(key, prototype, byte_range) for key, byte_range in key_ranges)))

    async def exists(self, key: str) -> bool:
        return await self._call(key, lambda: self._store.exists(key))

    async def set(self, key: str, value: Buffer) -> None:
        await self._call(key, lambda: self._store.set(key, value))  # the same bytes again: safe to retry

    async def delete(self, key: str) -> None:
        await self._call(key, lambda: self._store.delete(key))

    async def getsize(self, key: str) -> int:
        return await self._call(key, lambda: self._store.getsize(key))

    async def _listed(self, prefix: str, listing) -> AsyncIterator[str]:
        async def collect() -> list[str]:
            return [name async for name in listing()]

        for name in await self._call(prefix, collect):
            yield name

    def list(self) -> AsyncIterator[str]:
        return self._listed("", self._store.list)

    def list_prefix(self, prefix: str) -> AsyncIterator[str]:
        return self._listed(prefix, lambda: self._store.list_prefix(prefix))

    def list_dir(self, prefix: str) -> AsyncIterator[str]:
        return self._listed(prefix, lambda: self._store.list_dir(prefix))

    def __repr__(self) -> str:
        return f"BoundedRemote({self._store!r}, {self.limits})"
