"""Zarr groups below the SonarSet layer: where a store lives, how a group is opened (a remote one
through the chunk cache), and its children as stored, listed without parsing their metadata."""

from __future__ import annotations

from typing import Any

import zarr

from sonarset.errors import FormatError, RemoteError


def is_url(location: str) -> bool:
    """An fsspec URL (``s3://``, ``memory://``...); ``file://`` paths are local."""
    return "://" in location and not location.startswith("file://")


def url_exists(url: str, storage_options: dict | None) -> bool:
    """Whether a store's root metadata exists at ``url``."""
    from zarr.core.sync import sync

    return sync(remote_store(url, storage_options, read_only=True).exists("zarr.json"))


def remote_store(url: str, storage_options: dict | None, *, read_only: bool, cache_bytes: int | None = 0,
                 limits=None):
    """The zarr store at ``url``, every request bounded in time and retried on transient failures
    (``sonarset.store.remote``); for reading (``cache_bytes`` not 0) behind an LRU chunk cache of
    ``cache_bytes`` (None: ``cache.DEFAULT_CACHE_BYTES``), so a reader fetches each chunk once,
    not once per window. Writers never cache: they must see the store as it is. ``limits`` (a
    ``remote.RemoteLimits``) default to the environment's."""
    from zarr.storage import FsspecStore

    from sonarset.store.cache import DEFAULT_CACHE_BYTES, ChunkCache
    from sonarset.store.remote import BoundedRemote

    try:
        remote = FsspecStore.from_url(url, storage_options=storage_options, read_only=read_only)
    except (ValueError, TypeError, ImportError) as exc:
        raise FormatError(f"{url}: cannot open: {exc}") from None
    bounded = BoundedRemote(remote, url, limits)
    if not read_only or cache_bytes == 0:
        return bounded
    return ChunkCache(bounded, cache_bytes or DEFAULT_CACHE_BYTES)


def open_group(location: Any, mode: str, storage_options: dict | None, consolidated: bool | None) -> zarr.Group:
    kwargs: dict[str, Any] = {"mode": mode}
    if storage_options:
        kwargs["storage_options"] = storage_options
    if mode == "r":
        kwargs["use_consolidated"] = consolidated
    else:
        # A writer must see the store as it is, never a stale consolidated snapshot.
        kwargs["use_consolidated"] = False
    return zarr.open_group(location, **kwargs)


def child_names(group: zarr.Group) -> list[str]:
    """Names of a group's children as stored (those with a ``zarr.json``), without parsing them."""
    from zarr.core.sync import sync

    store, base = group.store, group.path

    async def listing() -> list[str]:
        return [name async for name in store.list_dir(base)]

    prefix = f"{base}/" if base else ""
    names = []
    for name in sorted({n.rstrip("/") for n in sync(listing())}):  # HTTP listings end folders with '/'
        if not name or name == "zarr.json" or name.endswith(".partial"):
            continue
        if sync(store.exists(f"{prefix}{name}/zarr.json")):
            names.append(name)
    return names


def first_unreadable_node(root: zarr.Group) -> tuple[str, Exception] | None:
    """(path, error) of the first run group or array under ``root`` whose metadata zarr cannot parse."""
    for name in child_names(root):
        try:
            node = root[name]
        except RemoteError:  # the server failed, not the store: never a finding
            raise
        except Exception as exc:
            return name, exc
        if not isinstance(node, zarr.Group):
            continue
        for child in child_names(node):
            try:
                root[f"{name}/{child}"]
            except RemoteError:
                raise
            except Exception as exc:
                return f"{name}/{child}", exc
    return None


def release_event_loop(timeout_s: float = 1.0) -> None:
    """End zarr's I/O event loop now, quietly: for a process that exits on a signal.

    zarr runs its I/O on an event loop in a thread and closes it at exit (``zarr.core.sync``'s
    atexit ``cleanup_resources``). A command interrupted while that loop still has work (the
    main thread waited in ``sync`` for a listing or a read) then exits noisily: the hook shuts the
    executor down under the running tasks, each of which then fails and is logged ("Task
    exception was never retrieved", thousands of tracebacks), and it cannot close the loop that
    is still running ("RuntimeError: Cannot close a running event loop"). Here the tasks are
    cancelled and awaited inside the loop, the loop stopped and closed, and the hook left with
    nothing to do. A loop too busy to answer within ``timeout_s`` is left to die with the
    process (its thread is a daemon), its remaining complaints silenced.
    """
    import asyncio
    import sys

    from zarr.core import sync as zsync

    loop, thread = zsync.loop[0], zsync.iothread[0]
    executor, zsync._executor = zsync._executor, None
    zsync.loop[0] = zsync.iothread[0] = None  # cleanup_resources finds nothing to close
    if executor is not None:
        executor.shutdown(wait=False, cancel_futures=True)
    if loop is None or loop.is_closed():
        return
    loop.set_exception_handler(lambda loop, context: None)  # nothing a task says now is news

    async def cancel_all() -> None:
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)  # retrieved: none is logged

    running = thread is not None and thread.is_alive()
    if running:
        try:
            asyncio.run_coroutine_threadsafe(cancel_all(), loop).result(timeout_s)
            loop.call_soon_threadsafe(loop.stop)
            thread.join(timeout_s)
        except Exception:  # busy (a timeout) or already stopping: left to end with the process
            pass
    if not running or not thread.is_alive():
        loop.close()
    else:  # still running: coroutines it drops at exit would each print "Exception ignored in"
        sys.unraisablehook = lambda unraisable: None
