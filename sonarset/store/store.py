"""SonarSet stores: a Zarr v3 root group with one group per run (spec/FORMAT.md).

Writing is crash-safe by construction: a run group is created with ``complete: false``, its
arrays are written, and only then is ``complete`` set true and the root's consolidated metadata
rewritten. Readers list only complete runs, so a killed writer never leaves a run that looks
finished. One process writes one run group; never let two processes write one array.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

import numpy as np
import zarr
from pydantic import ValidationError

from sonarset.format.arrays import OPTIONAL_ARRAYS, check_run_arrays
from sonarset.errors import FormatError, GridMismatchError, InputValidationError, SonarSetError, one_line
from sonarset.store.run import Run, RunData
from sonarset.store.writer import DEFAULT_CHUNK_FRAMES, RunWriter
from sonarset.format.attrs import (
    FORMAT_VERSION, NAMESPACE, SUPPORTED_MAJOR, Processing, RobotRig, RunAttrs, SensorGrid,
    StoreAttrs, parse_version, pydantic_problems,
)
from sonarset.version import __version__
from sonarset.store.zarrio import cached_remote, child_names, first_unreadable_node, is_url, open_group, url_exists

__all__ = ["DEFAULT_CHUNK_FRAMES", "Run", "RunData", "RunWriter", "SonarStore", "create_store", "open_or_create_store",
           "open_store", "read_store_attrs"]

# Listing a group while another process writes into it atomically shows that writer's temp file
# ("zarr.<id>.partial"); it is not a node, zarr skips it, and the warning is noise.
# Other strays (a junk folder, a killed writer's leftovers) are not nodes either: readers ignore
# them, as the spec says of anything that is not a node.
warnings.filterwarnings("ignore", message=r"Object at .* is not recognized", category=UserWarning)
# zarr-python warns on every consolidation that consolidated metadata is not yet in the v3 spec;
# the spec (FORMAT.md §6) makes it optional and advisory, so the warning is noise to our users.
warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")


class SonarStore:
    """A SonarSet store opened for reading (``mode='r'``) or writing (``'r+'``)."""

    def __init__(self, group: zarr.Group, location: str, mode: str):
        self.group = group
        self.location = location
        self.mode = mode
        self.attrs = read_store_attrs(group, location)

    # ---- structure ------------------------------------------------------------------------
    @property
    def grid(self) -> SensorGrid:
        return self.attrs.grid

    @property
    def format_version(self) -> str:
        return self.attrs.format_version

    @property
    def processing(self) -> Processing:
        """How the images were made (format 1.1; a 1.0 store's images are 'raw')."""
        return self.attrs.processing

    @property
    def rig(self) -> RobotRig | None:
        """The robot geometry: the store's ``rig`` attribute (1.1), else None when unknown.

        Backward compatibility: a store without ``rig`` (format 1.0) whose complete runs were all
        made by the simulator gets the rig recorded in their provenance
        (:meth:`RobotRig.from_provenance`). This is the one place that reads geometry from the
        free-form ``source``.
        """
        if self.attrs.rig is not None:
            return self.attrs.rig
        if self.mode == "r":  # a reader's view does not change: read every run's provenance once
            if not hasattr(self, "_provenance_rig"):
                self._provenance_rig = self._rig_from_provenance()
            return self._provenance_rig
        return self._rig_from_provenance()

    def _rig_from_provenance(self) -> RobotRig | None:
        rigs = set()
        for name in self.runs():
            src = self.run(name).attrs.source
            rig = RobotRig.from_provenance(src) if src.get("kind") == "simulator" else None
            if rig is None:
                return None
            rigs.add(rig)
        return rigs.pop() if len(rigs) == 1 else None

    def run_attrs(self, name: str) -> RunAttrs | None:
        try:
            raw = self.group[name].attrs.get(NAMESPACE)
            return RunAttrs.model_validate(raw)
        except Exception:  # unparseable metadata or invalid attributes: not a usable run
            return None

    def _group_names(self) -> list[str]:
        """The child groups of the root, sorted.

        zarr lists children by parsing every child's metadata, so one broken ``zarr.json`` makes
        the whole listing raise. A reader then refuses the store, naming that child; a writer
        (``r+``) skips it, so that it can still replace or add runs.
        """
        try:
            return sorted(self.group.group_keys())
        except Exception:
            pass
        names = []
        for name in child_names(self.group):
            try:
                node = self.group[name]
            except Exception as exc:
                if self.mode == "r":
                    raise FormatError(f"{self.location}/{name}: unreadable zarr metadata ({one_line(exc)})") from None
                continue
            if isinstance(node, zarr.Group):
                names.append(name)
        return names

    def runs(self, split: str | None = None, include_incomplete: bool = False,
             worlds: Iterable[str] | None = None) -> list[str]:
        """Names of the runs (complete ones unless asked), sorted, optionally of one split and of
        the world families (or world files) ``worlds`` that their ``source.world`` names."""
        wanted = None if worlds is None else set(worlds)
        names = []
        for name in self._group_names():
            attrs = self.run_attrs(name)
            if attrs is None or not (attrs.complete or include_incomplete):
                continue
            if split is not None and attrs.split != split:
                continue
            if wanted is not None and (attrs.source or {}).get("world") not in wanted:
                continue
            names.append(name)
        return names

    def worlds(self, split: str | None = None) -> dict[str, list[str]]:
        """{world: its complete runs} of a split (or all), for the runs whose provenance names one."""
        out: dict[str, list[str]] = {}
        for name in self.runs(split):
            world = (self.run_attrs(name).source or {}).get("world")
            if world is not None:
                out.setdefault(str(world), []).append(name)
        return out

    def splits(self) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {}
        for name in self.runs():
            out.setdefault(self.run(name).split, []).append(name)
        return out

    def run(self, name: str) -> "Run":
        if name not in self._group_names():
            raise SonarSetError(f"{self.location}: no run named {name!r} (runs: {', '.join(self.runs()) or 'none'})")
        attrs = self.run_attrs(name)
        if attrs is None:
            raise FormatError(f"{self.location}/{name}: run attributes are missing or invalid")
        if not attrs.complete:
            raise FormatError(f"{self.location}/{name}: run is incomplete (its writer did not finish)")
        return Run(self, name, attrs)

    def check(self, runs: Iterable[str] | None = None, *, chunks: bool = True) -> "SonarStore":
        """The quick structural checks a reader makes before it trusts the store; returns self.

        Every run group's metadata must parse and its attributes validate (incomplete runs are
        skipped, as readers ignore them); each complete run (or each of ``runs``) must hold its
        arrays with the spec's dtypes, shapes and dimension names, coordinates matching the grid,
        and, with ``chunks``, every chunk of a local store present and as long as its header says
        (a remote store's chunks are checked as they are read). Raises
        FormatError naming the run, array and chunk of the first problem. Values are checked as
        they are loaded (``Run.read``).
        """
        rig = self.attrs.rig
        if rig is not None and abs(rig.frame_interval_s * self.attrs.frame_rate_hz - 1.0) > 1e-6:
            raise FormatError(f"{self.location}: rig.frame_interval_s {rig.frame_interval_s:g} s disagrees with "
                              f"frame_rate_hz {self.attrs.frame_rate_hz:g}")
        for name in self._group_names():
            try:
                raw = self.group[name].attrs.get(NAMESPACE)
            except Exception as exc:
                raise FormatError(f"{self.location}/{name}: unreadable zarr metadata ({one_line(exc)})") from None
            if not isinstance(raw, dict):
                raise FormatError(f"{self.location}/{name}: run attribute {NAMESPACE!r} is missing")
            try:
                RunAttrs.model_validate(raw)
            except ValidationError as exc:
                raise FormatError(f"{self.location}/{name}: {pydantic_problems(exc, f'{NAMESPACE}.')[0]}") from None
        for name in (self.runs() if runs is None else runs):
            self.run(name).check(chunks=chunks)
        return self

    def __iter__(self) -> Iterator["Run"]:
        return (self.run(n) for n in self.runs())

    def __len__(self) -> int:
        return len(self.runs())

    def __repr__(self) -> str:
        return f"SonarStore({self.location!r}, runs={len(self)}, grid={self.grid.describe()})"

    def n_frames(self, split: str | None = None) -> int:
        return sum(self.run(n).n_frames for n in self.runs(split))

    def nbytes_stored(self) -> int | None:
        """Bytes on disk for a local store; None where it cannot be measured cheaply."""
        if is_url(self.location):
            return None
        total = 0
        for dirpath, _, files in os.walk(self.location):
            total += sum(os.path.getsize(os.path.join(dirpath, f)) for f in files)
        return total

    # ---- writing --------------------------------------------------------------------------
    def _require_writable(self) -> None:
        if self.mode == "r":
            raise SonarSetError(f"{self.location}: store is open read-only")

    def run_writer(self, name: str, n_frames: int, **kwargs: Any) -> "RunWriter":
        self._require_writable()
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
    ) -> "Run":
        """Validate, then write a whole run in one go; it becomes visible only when complete."""
        arrays = {"images": images, "velocity": velocity, "time": time,
                  "pose": pose, "snr_db": snr_db, "slip": slip}
        arrays = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
        problems = check_run_arrays(self.grid, arrays)
        if problems:
            raise InputValidationError(f"run {name!r}", problems)
        T = arrays["images"].shape[0]
        optional = tuple(k for k in OPTIONAL_ARRAYS if k in arrays)
        image_dtype = "float16" if arrays["images"].dtype == np.float16 else "float32"
        with self.run_writer(name, T, split=split, source=source, optional=optional,
                             image_dtype=image_dtype, overwrite=overwrite,
                             consolidate=consolidate, chunk_frames=chunk_frames) as w:
            w.write(0, checked=True, **arrays)
            return w.commit()

    def delete_run(self, name: str) -> None:
        self._require_writable()
        if name in self.group.group_keys():
            del self.group[name]

    def consolidate(self) -> None:
        """Rewrite the root's consolidated metadata; call after runs were written elsewhere."""
        self._require_writable()
        try:
            zarr.consolidate_metadata(self.group.store)
        except OSError:
            raise
        except Exception as exc:  # zarr parses every node's metadata: one broken node stops it
            where = first_unreadable_node(self.group)
            raise FormatError(f"{self.location}{'/' + where[0] if where else ''}: unreadable zarr metadata "
                              f"({one_line(where[1] if where else exc)}); cannot consolidate") from None


def read_store_attrs(group: zarr.Group, location: str) -> StoreAttrs:
    raw = group.attrs.get(NAMESPACE)
    if not isinstance(raw, dict):
        raise FormatError(f"{location}: not a SonarSet store (root attribute {NAMESPACE!r} is missing)")
    version = raw.get("format_version")
    try:
        major, _ = parse_version(version)
    except ValueError as exc:
        raise FormatError(f"{location}: {exc}") from None
    if major != SUPPORTED_MAJOR:
        raise FormatError(
            f"{location}: SonarSet format version {version} is not supported "
            f"(this sonarset {__version__} reads {SUPPORTED_MAJOR}.x); upgrade sonarset"
        )
    try:
        return StoreAttrs.model_validate(raw)
    except ValidationError as exc:
        raise FormatError(f"{location}: {pydantic_problems(exc, 'sonarset.')[0]}") from None


def open_store(
    location: str | os.PathLike,
    mode: str = "r",
    *,
    storage_options: dict | None = None,
    consolidated: bool | None = None,
    cache_bytes: int | None = None,
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

    ``check=True`` (what ``eval``, ``train``, ``info`` and ``show`` use) also runs
    :meth:`SonarStore.check`: a store that fails it raises FormatError here.
    """
    if mode not in ("r", "r+"):
        raise ValueError("mode must be 'r' or 'r+' (use create_store to make a new store)")
    loc = os.fspath(location)
    if not is_url(loc):
        path = Path(loc.removeprefix("file://"))
        if not path.exists():
            raise FormatError(f"{loc}: no such file or directory")
        if path.is_file():
            raise FormatError(f"{loc}: not a zarr store (a file, not a directory)")
        if not (path / "zarr.json").is_file():
            if path.is_dir() and ((path / ".zgroup").exists() or (path / ".zarray").exists()):
                raise FormatError(f"{loc}: a Zarr v2 store; SonarSet requires Zarr v3")
            raise FormatError(f"{loc}: not a zarr store (no zarr.json at its root)")
        try:  # zarr's own message would not say which file
            json.loads((path / "zarr.json").read_bytes())
        except (UnicodeDecodeError, ValueError) as exc:
            raise FormatError(f"{path / 'zarr.json'}: unreadable JSON ({one_line(exc)})") from None
        loc = str(path)
        if consolidated is None:
            consolidated = False
    target: Any = loc
    if is_url(loc) and mode == "r" and cache_bytes != 0:
        target, storage_options = cached_remote(loc, storage_options, cache_bytes), None
    try:
        group = open_group(target, mode, storage_options, consolidated)
    except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError) as exc:
        raise FormatError(f"{loc}: not a zarr store ({type(exc).__name__})") from None
    except OSError:
        raise
    except Exception as exc:  # zarr's metadata errors are ValueError, TypeError, its own classes...
        raise FormatError(f"{loc}: cannot open as a zarr v3 group: {one_line(exc)}") from None
    store = SonarStore(group, loc, mode)
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
            raise SonarSetError(f"{loc}: already exists (pass overwrite to replace it)")
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
    if storage_options:
        kwargs["storage_options"] = storage_options
    try:
        group = zarr.open_group(loc, **kwargs)
    except (FileExistsError, zarr.errors.ContainsGroupError, zarr.errors.ContainsArrayError):
        raise SonarSetError(f"{loc}: already exists (pass overwrite to replace it)") from None
    zarr.consolidate_metadata(group.store)
    return SonarStore(zarr.open_group(loc, mode="r+", use_consolidated=False,
                                      **({"storage_options": storage_options} if storage_options else {})),
                      loc, "r+")


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
