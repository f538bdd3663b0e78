"""Zarr groups below the SonarSet layer: where a store lives, how a group is opened (a remote one
through the chunk cache), and its children as stored, listed without parsing their metadata."""

from __future__ import annotations

from typing import Any

import zarr

from sonarset.errors import FormatError


def is_url(location: str) -> bool:
    """An fsspec URL (``s3://``, ``memory://``...); ``file://`` paths are local."""
    return "://" in location and not location.startswith("file://")


def url_exists(url: str, storage_options: dict | None) -> bool:
    """Whether a store's root metadata exists at ``url``."""
    import fsspec

    fs, path = fsspec.core.url_to_fs(url, **(storage_options or {}))
    return fs.exists(f"{path.rstrip('/')}/zarr.json")


def cached_remote(url: str, storage_options: dict | None, cache_bytes: int | None):
    """The read-only zarr store at ``url`` behind an LRU chunk cache of ``cache_bytes`` (default
    ``cache.DEFAULT_CACHE_BYTES``): a reader then fetches each chunk once, not once per window."""
    from zarr.storage import FsspecStore

    from sonarset.store.cache import DEFAULT_CACHE_BYTES, ChunkCache

    try:
        remote = FsspecStore.from_url(url, storage_options=storage_options, read_only=True)
    except (ValueError, TypeError, ImportError) as exc:
        raise FormatError(f"{url}: cannot open: {exc}") from None
    return ChunkCache(remote, cache_bytes or DEFAULT_CACHE_BYTES)


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
        except Exception as exc:
            return name, exc
        if not isinstance(node, zarr.Group):
            continue
        for child in child_names(node):
            try:
                root[f"{name}/{child}"]
            except Exception as exc:
                return f"{name}/{child}", exc
    return None
