"""SonarSet stores: a Zarr v3 root group with one group per run (spec/FORMAT.md).

Writing is crash-safe by construction: a run group is created with ``complete: false``, its
arrays are written, and only then is ``complete`` set true and the root's consolidated metadata
rewritten. Readers list only complete runs, so a killed writer never leaves a run that looks
finished. One process writes one run group; never let two processes write one array.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

import numpy as np
import zarr

from sonarset.errors import GridMismatchError, InputValidationError, SonarSetError
from sonarset.format.arrays import OPTIONAL_ARRAYS, run_array_problems
from sonarset.format.attrs import FORMAT_VERSION, NAMESPACE, Processing, RobotRig, SensorGrid, StoreAttrs
from sonarset.format.problems import raise_first
from sonarset.format.rules import run_state_problems, store_attrs_problems
from sonarset.store.root import StoreRoot, open_root, run_group_attrs, run_tree
from sonarset.store.run import Run
from sonarset.store.remote import RemoteLimits
from sonarset.store.writer import DEFAULT_CHUNK_FRAMES, RunWriter
from sonarset.store.zarrio import is_url, remote_store, url_exists
from sonarset.version import __version__

__all__ = ["SonarStore", "create_store", "open_or_create_store", "open_store"]


class SonarStore(StoreRoot):
    """A SonarSet store opened for reading (``mode='r'``) or writing (``'r+'``)."""

    def __init__(self, group: zarr.Group, location: str, mode: str):
        super().__init__(group, location, mode)
        #: The runs ``check`` vetted in a read-only store: ``run`` hands them out again while their
        #: folders stay, so a reader that checks a store and then reads it opens each run once.
        self._checked: dict[str, Run] = {}

    def worlds(self, split: str | None = None) -> dict[str, list[str]]:
        """{world: its complete runs} of a split (or all), for the runs whose provenance names one."""
        out: dict[str, list[str]] = {}
        for name, attrs in self.listed_runs().items():
            world = (attrs.source or {}).get("world")
            if world is not None and (split is None or attrs.split == split):
                out.setdefault(str(world), []).append(name)
        return out

    def splits(self) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {}
        for name, attrs in self.listed_runs().items():
            out.setdefault(attrs.split, []).append(name)
        return out

    def run(self, name: str) -> Run:
        checked = self._checked.get(name)
        if checked is not None and not checked.replaced():
            return checked
        node = self.child_group(name)
        if node is None:
            raise SonarSetError(f"{self.location}: no run named {name!r} (runs: {', '.join(self.runs()) or 'none'})")
        return self._run(name, node)

    def _run(self, name: str, node: zarr.Group, members: dict[str, zarr.Array] | None = None) -> Run:
        attrs, problems = run_group_attrs(self.group, self.location, name, node)
        raise_first(problems)
        raise_first([p.at(f"{self.location}/{name}") for p in run_state_problems(attrs)])
        return Run(self, name, attrs, node, members)

    def check(self, runs: Iterable[str] | None = None, *, chunks: bool = True) -> "SonarStore":
        """The quick structural checks a reader makes before it trusts the store; returns self.

        The root attributes must agree with each other; every run group must be named as the spec
        says, its metadata parse and its attributes validate (incomplete runs' arrays are
        skipped, as readers ignore them); each complete run (or each of ``runs``) must hold its
        arrays with the spec's dtypes, shapes and dimension names, coordinates matching the grid,
        and, with ``chunks``, every chunk of a local store present and as long as its header says
        (a remote store's chunks are checked as they are read). Raises
        FormatError naming the run, array and chunk of the first problem. Values are checked as
        they are loaded (``Run.read``).
        """
        raise_first([p.at(self.location) for p in store_attrs_problems(self.attrs)])
        # One listing opens every run group and its arrays, not one (or one per run) per check.
        tree = run_tree(self.group) or {name: (node, None) for name, node in self.run_groups().items()}
        complete = []
        for name, (node, _) in tree.items():
            attrs, problems = run_group_attrs(self.group, self.location, name, node)
            raise_first(problems)
            if attrs.complete:
                complete.append(name)
        for name in (complete if runs is None else runs):
            run = self._run(name, *tree[name]) if name in tree else self.run(name)
            run.check(chunks=chunks)
            if self.mode == "r":
                self._checked[name] = run
        return self

    def __iter__(self) -> Iterator["Run"]:
        return (self.run(n) for n in self.runs())

    def __len__(self) -> int:
        return len(self.runs())

    def __repr__(self) -> str:
        return f"SonarStore({self.location!r}, runs={len(self)}, grid={self.grid.describe()})"

    def n_frames(self, split: str | None = None) -> int:
        return sum(attrs.n_frames for attrs in self.listed_runs().values() if split is None or attrs.split == split)

    def nbytes_stored(self) -> int | None:
        """Bytes on disk for a local store; None where it cannot be measured cheaply."""
        if is_url(self.location):
            return None
        total = 0
        for dirpath, _, files in os.walk(self.location):
            total += sum(os.path.getsize(os.path.join(dirpath, f)) for f in files)
        return total

    # ---- writing --------------------------------------------------------------------------
    def run_writer(self, name: str, n_frames: int, **kwargs: Any) -> RunWriter:
        self.require_writable()
        return RunWriter(self, name, n_frames, **kwargs)

    def write_run(
        self,
        name: str,
        images: np.ndarray,
        velocity: np.ndarray,
        time: np.ndarray,
        *,
        pose: np.ndarray | None = None,
        snr_db: np.ndarray | None = None,
        slip: np.ndarray | None = None,
        split: str = "train",
        source: Mapping[str, Any] | None = None,
        overwrite: bool = False,
        consolidate: bool = True,
        chunk_frames: int = DEFAULT_CHUNK_FRAMES,
    ) -> Run:
        """Validate, then write a whole run in one go; it becomes visible only when complete."""
        arrays = {"images": images, "velocity": velocity, "time": time,
                  "pose": pose, "snr_db": snr_db, "slip": slip}
        arrays = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
        problems = run_array_problems(self.grid, arrays)
        if problems:
            raise InputValidationError(f"run {name!r}", problems)
        T = arrays["images"].shape[0]
        optional = tuple(k for k in OPTIONAL_ARRAYS if k in arrays)
        image_dtype = "float16" if arrays["images"].dtype == np.float16 else "float32"
        with self.run_writer(name, T, split=split, source=source, optional=optional,
                             image_dtype=image_dtype, overwrite=overwrite,
                             consolidate=consolidate, chunk_frames=chunk_frames) as w:
            w.write(0, checked=True, **arrays)
            return Run(self, name, w.commit())


def open_store(
    location: str | os.PathLike,
    mode: str = "r",
    *,
    storage_options: dict | None = None,
    consolidated: bool | None = None,
    cache_bytes: int | None = None,
    remote_limits: RemoteLimits | None = None,
    check: bool = False,
) -> SonarStore:
    """Open a SonarSet store from a local path or any fsspec URL (``s3://``, ``https://``,
    ``memory://``...).

    ``consolidated=None`` uses the root's consolidated metadata for URLs, where it saves a request
    per node, and lists local stores directly, where listing is cheap and never stale (a writer
    killed before re-consolidating leaves the snapshot behind). ``True``/``False`` force either.

    A URL opened for reading goes through an in-memory LRU chunk cache of ``cache_bytes``
    (default 512 MiB, ``0`` for none; ``sonarset.store.cache``), so chunks are fetched once, not once
    per window.

    Every request to a URL ends within ``remote_limits.timeout_s`` (default 20 s, or
    ``SONARSET_REMOTE_TIMEOUT``) and transient server failures are retried with backoff
    (``sonarset.store.remote``); what still fails raises RemoteError naming the URL.

    ``check=True`` (what ``eval``, ``train``, ``info`` and ``show`` use) also runs
    :meth:`SonarStore.check`: a store that fails it raises FormatError here.
    """
    if mode not in ("r", "r+"):
        raise ValueError("mode must be 'r' or 'r+' (use create_store to make a new store)")
    group, loc = open_root(os.fspath(location), mode, storage_options=storage_options, consolidated=consolidated,
                           cache_bytes=cache_bytes, remote_limits=remote_limits)
    store = SonarStore(group, loc, mode)
    # how it was opened, for processes that open it again (streaming DataLoader workers)
    store.open_options = {"storage_options": storage_options, "remote_limits": remote_limits}
    return store.check() if check else store


def create_store(
    location: str | os.PathLike,
    grid: SensorGrid | None = None,
    *,
    overwrite: bool = False,
    frame_rate_hz: float = 5.0,
    description: str = "",
    storage_options: dict | None = None,
    processing: Processing | None = None,
    rig: RobotRig | None = None,
) -> SonarStore:
    """Create an empty store with a sensor grid (default: the eRTIS-like 200 x 90 grid).

    ``processing`` says how its images are made (default: 'raw', delay-and-sum without
    post-processing); ``rig`` is the robot geometry (default: unknown, not recorded).
    """
    loc = os.fspath(location)
    if not is_url(loc):
        path = Path(loc)
        if path.exists() and not overwrite and (path.is_file() or any(path.iterdir())):
            raise SonarSetError(f"{loc}: already exists; overwrite replaces it", parameter="overwrite")
    attrs = StoreAttrs(
        format_version=FORMAT_VERSION, grid=grid or SensorGrid.default(),
        frame_rate_hz=frame_rate_hz, created_by=f"sonarset {__version__}", description=description,
        processing=processing or Processing.raw(), rig=rig,
    )
    doc = attrs.model_dump(mode="json")
    if doc.get("rig") is None:
        doc.pop("rig", None)  # unknown: absent, as in a 1.0 store
    kwargs: dict[str, Any] = {"mode": "w" if overwrite else "w-", "zarr_format": 3,
                              "attributes": {NAMESPACE: doc}}
    target: Any = remote_store(loc, storage_options, read_only=False) if is_url(loc) else loc
    try:
        group = zarr.open_group(target, **kwargs)
    except (FileExistsError, zarr.errors.ContainsGroupError, zarr.errors.ContainsArrayError):
        raise SonarSetError(f"{loc}: already exists; overwrite replaces it", parameter="overwrite") from None
    zarr.consolidate_metadata(group.store)
    return SonarStore(zarr.open_group(group.store, mode="r+", use_consolidated=False), loc, "r+")


def open_or_create_store(
    location: str | os.PathLike,
    grid: SensorGrid,
    *,
    processing: Processing | None = None,
    rig: RobotRig | None = None,
    **kwargs: Any,
) -> SonarStore:
    """Open an existing store for writing or create a new one (``create_store``'s keywords).

    An existing store must have the same ``grid`` and, where given, make the same images
    (``processing``, per ``Processing.same_images``) on the same ``rig``; None skips that check.
    """
    loc = os.fspath(location)
    exists = (Path(loc) / "zarr.json").exists() if not is_url(loc) else url_exists(loc, kwargs.get("storage_options"))
    if exists:
        store = open_store(loc, "r+", storage_options=kwargs.get("storage_options"))
        if not store.grid.matches(grid):
            raise GridMismatchError(
                f"{loc}: store grid {store.grid.describe()} differs from the data's {grid.describe()}"
            )
        if processing is not None and not store.processing.same_images(processing):
            raise SonarSetError(f"{loc}: store images are {store.processing.describe()}, the data's are "
                                f"{processing.describe()}; write them to another store")
        if rig is not None and store.rig != rig:
            have = store.rig.describe() if store.rig is not None else "not recorded"
            raise SonarSetError(f"{loc}: store robot rig is {have}, the data's is {rig.describe()}; "
                                "write them to another store")
        return store
    return create_store(loc, grid, processing=processing, rig=rig, **kwargs)
