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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

import numpy as np
import zarr
from pydantic import ValidationError
from zarr.codecs import BloscCodec

from . import __version__

# Listing a group while another process writes into it atomically shows that writer's temp file
# ("zarr.<id>.partial"); it is not a node, zarr skips it, and the warning is noise.
# Other strays (a junk folder, a killed writer's leftovers) are not nodes either: readers ignore
# them, as the spec says of anything that is not a node.
warnings.filterwarnings("ignore", message=r"Object at .* is not recognized", category=UserWarning)
from .errors import FormatError, GridMismatchError, InputValidationError, SonarSetError
from .arrays import (
    ARRAYS, OPTIONAL_ARRAYS, array_meta_problems, check_run_arrays, expected_shape, frame_interval_problem,
    value_problem,
)
from .integrity import ChunkChecker, chunk_coords
from .schema import (
    FORMAT_VERSION, NAMESPACE, RUN_NAME_RE, SUPPORTED_MAJOR, Processing, RobotRig, RunAttrs, SensorGrid,
    StoreAttrs, parse_version, pydantic_problems,
)

# zarr-python warns on every consolidation that consolidated metadata is not yet in the v3 spec;
# the spec (FORMAT.md §6) makes it optional and advisory, so the warning is noise to our users.
warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")


DEFAULT_CHUNK_FRAMES = 64  # 64 x 200 x 90 float16 = 2.3 MB: large enough to stream, small to cache


def _compressor(dtype: np.dtype, sparse: bool = False) -> BloscCodec:
    # lz4: raw energyscapes carry a noise floor that no codec squeezes much (zstd-3 gives 1.5x, lz4
    # with bitshuffle 1.3x), so speed wins: 3x faster writes and reads (bench/bench_generate.py).
    # Post-processed energyscapes are mostly exact zeros: without a shuffle lz4 packs them 5x, and
    # 4x faster than with bitshuffle (2.1x).
    return BloscCodec(cname="lz4", clevel=1, shuffle="noshuffle" if sparse else "bitshuffle",
                      typesize=np.dtype(dtype).itemsize)


def _is_url(location: str) -> bool:
    return "://" in location and not location.startswith("file://")


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
        made by the simulator gets the rig recorded in their provenance (``dt``, ``sensor_offset_m``,
        ``wheel_base_m``; speed limits: the defaults). This is the one place that reads geometry
        from the free-form ``source``.
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
            if src.get("kind") != "simulator":
                return None
            try:
                rigs.add(RobotRig(frame_interval_s=float(src["dt"]), sensor_offset_m=float(src["sensor_offset_m"]),
                                  wheel_base_m=float(src["wheel_base_m"])))
            except (KeyError, TypeError, ValueError):  # pydantic's ValidationError is a ValueError
                return None
        return rigs.pop() if len(rigs) == 1 else None

    def _run_attrs(self, name: str) -> RunAttrs | None:
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
        for name in _child_names(self.group):
            try:
                node = self.group[name]
            except Exception as exc:
                if self.mode == "r":
                    raise FormatError(f"{self.location}/{name}: unreadable zarr metadata ({_one_line(exc)})") from None
                continue
            if isinstance(node, zarr.Group):
                names.append(name)
        return names

    def runs(self, split: str | None = None, include_incomplete: bool = False) -> list[str]:
        """Names of the runs (complete ones unless asked), sorted, optionally of one split."""
        names = []
        for name in self._group_names():
            attrs = self._run_attrs(name)
            if attrs is None or not (attrs.complete or include_incomplete):
                continue
            if split is not None and attrs.split != split:
                continue
            names.append(name)
        return names

    def splits(self) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {}
        for name in self.runs():
            out.setdefault(self.run(name).split, []).append(name)
        return out

    def run(self, name: str) -> "Run":
        if name not in self._group_names():
            raise SonarSetError(f"{self.location}: no run named {name!r} (runs: {', '.join(self.runs()) or 'none'})")
        attrs = self._run_attrs(name)
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
                raise FormatError(f"{self.location}/{name}: unreadable zarr metadata ({_one_line(exc)})") from None
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
        if _is_url(self.location):
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
            w.write(0, _checked=True, **arrays)
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
            where = _first_unreadable_node(self.group)
            raise FormatError(f"{self.location}{'/' + where[0] if where else ''}: unreadable zarr metadata "
                              f"({_one_line(where[1] if where else exc)}); cannot consolidate") from None


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


def _open_group(location: Any, mode: str, storage_options: dict | None, consolidated: bool | None) -> zarr.Group:
    kwargs: dict[str, Any] = {"mode": mode}
    if storage_options:
        kwargs["storage_options"] = storage_options
    if mode == "r":
        kwargs["use_consolidated"] = consolidated
    else:
        # A writer must see the store as it is, never a stale consolidated snapshot.
        kwargs["use_consolidated"] = False
    return zarr.open_group(location, **kwargs)


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
    (default 512 MiB, ``0`` for none; ``sonarset.cache``), so chunks are fetched once, not once
    per window.

    ``check=True`` (what ``eval``, ``train``, ``info`` and ``show`` use) also runs
    :meth:`SonarStore.check`: a store that fails it raises FormatError here.
    """
    if mode not in ("r", "r+"):
        raise ValueError("mode must be 'r' or 'r+' (use create_store to make a new store)")
    loc = os.fspath(location)
    if not _is_url(loc):
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
            raise FormatError(f"{path / 'zarr.json'}: unreadable JSON ({_one_line(exc)})") from None
        loc = str(path)
        if consolidated is None:
            consolidated = False
    target: Any = loc
    if _is_url(loc) and mode == "r" and cache_bytes != 0:
        from zarr.storage import FsspecStore

        from .cache import DEFAULT_CACHE_BYTES, ChunkCache

        try:
            remote = FsspecStore.from_url(loc, storage_options=storage_options, read_only=True)
        except (ValueError, TypeError, ImportError) as exc:
            raise FormatError(f"{loc}: cannot open: {exc}") from None
        target, storage_options = ChunkCache(remote, cache_bytes or DEFAULT_CACHE_BYTES), None
    try:
        group = _open_group(target, mode, storage_options, consolidated)
    except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError) as exc:
        raise FormatError(f"{loc}: not a zarr store ({type(exc).__name__})") from None
    except OSError:
        raise
    except Exception as exc:  # zarr's metadata errors are ValueError, TypeError, its own classes...
        raise FormatError(f"{loc}: cannot open as a zarr v3 group: {_one_line(exc)}") from None
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
    if not _is_url(loc):
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
    exists = (Path(loc) / "zarr.json").exists() if not _is_url(loc) else _url_exists(loc, kwargs.get("storage_options"))
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


def _url_exists(url: str, storage_options: dict | None) -> bool:
    import fsspec

    fs, path = fsspec.core.url_to_fs(url, **(storage_options or {}))
    return fs.exists(f"{path.rstrip('/')}/zarr.json")


class RunWriter:
    """Writes one run group block by block; ``commit()`` makes it visible.

    Use as a context manager: an exception inside deletes the half-written group. A killed
    process leaves it with ``complete: false``, which readers ignore and the next writer of the
    same name replaces.
    """

    def __init__(
        self,
        store: SonarStore,
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
        if not RUN_NAME_RE.match(name):
            raise SonarSetError(f"invalid run name {name!r}: use letters, digits, '_', '.', '-'")
        unknown = set(optional) - set(OPTIONAL_ARRAYS)
        if unknown:
            raise SonarSetError(f"unknown optional arrays: {', '.join(sorted(unknown))}")
        if image_dtype not in ARRAYS["images"].dtypes:
            raise SonarSetError(f"image dtype must be float16 or float32, got {image_dtype}")
        if n_frames < 1:
            raise SonarSetError(f"run {name!r}: needs at least one frame")
        self.store, self.name, self.n_frames = store, name, int(n_frames)
        self.consolidate = consolidate
        self.attrs = RunAttrs(complete=False, n_frames=self.n_frames, split=split, source=dict(source or {}))
        root = store.group
        if name in root.group_keys() or name in root.array_keys():
            existing = store._run_attrs(name)
            if existing is not None and existing.complete and not overwrite:
                raise SonarSetError(f"{store.location}: run {name!r} already exists (pass overwrite to replace it)")
            del root[name]
        self.group = root.create_group(name, attributes={NAMESPACE: self.attrs.model_dump(mode="json")})
        T, (R, A) = self.n_frames, store.grid.shape
        cf = max(1, min(chunk_frames, T))
        self.arrays: dict[str, zarr.Array] = {}
        sparse = store.attrs.processing.clip_at_zero  # images mostly exact zeros
        for key in ("images", "velocity", "time", *optional):
            spec = ARRAYS[key]
            dtype = image_dtype if key == "images" else spec.write_dtype
            shape = expected_shape(key, T, (R, A))
            chunks = (cf, R, A) if key == "images" else shape
            self.arrays[key] = self.group.create_array(
                key, shape=shape, chunks=chunks, dtype=dtype, dimension_names=spec.dims,
                compressors=_compressor(np.dtype(dtype), sparse and key == "images"),
                fill_value=np.nan,
                attributes={"units": spec.units, "description": spec.description},
            )
        for key, values in (("range", store.grid.range_centres()), ("azimuth", store.grid.azimuth_centres())):
            spec = ARRAYS[key]
            arr = self.group.create_array(
                key, shape=values.shape, chunks=values.shape, dtype=spec.write_dtype, dimension_names=spec.dims,
                compressors=None, fill_value=np.nan,
                attributes={"units": spec.units, "description": spec.description},
            )
            arr[:] = values
        self._written = np.zeros(T, dtype=bool)
        # Per-frame vectors are one chunk each: written block by block, every block would rewrite
        # (decompress and compress) the whole chunk. They are a few bytes a frame, so they are
        # kept here and written once, at commit, before the completion flag.
        self._small = {k: np.full(a.shape, np.nan, a.dtype) for k, a in self.arrays.items() if k != "images"}

    def write(self, start: int, _checked: bool = False, **blocks: np.ndarray | None) -> None:
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
        problems = [] if _checked else check_run_arrays(self.store.grid, blocks)
        if problems:
            raise InputValidationError(f"run {self.name!r} frames {start}..{start + n - 1}", problems)
        for key, values in blocks.items():
            if key in self._small:
                self._small[key][start:start + n] = values
            else:
                self.arrays[key][start:start + n] = values.astype(self.arrays[key].dtype, copy=False)
        self._written[start:start + n] = True

    def commit(self) -> "Run":
        if not self._written.all():
            missing = int(np.flatnonzero(~self._written)[0])
            raise SonarSetError(f"run {self.name!r}: frame {missing} was never written")
        t = self._small["time"]
        if t.size > 1 and np.any(np.diff(t) <= 0):
            raise SonarSetError(f"run {self.name!r}: time is not strictly increasing across blocks")
        for key, values in self._small.items():
            self.arrays[key][:] = values
        attrs = self.attrs.model_copy(update={"complete": True})
        # The completion flag is the run's last write: everything before it is already durable.
        self.group.attrs.update({NAMESPACE: attrs.model_dump(mode="json")})
        if self.consolidate:
            self.store.consolidate()
        self._committed = True
        return Run(self.store, self.name, attrs)

    def abort(self) -> None:
        self.store.delete_run(self.name)

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None and not getattr(self, "_committed", False):
            self.abort()


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

    def __init__(self, store: SonarStore, name: str, attrs: RunAttrs):
        self.store, self.name, self.attrs = store, name, attrs
        self.where = f"{store.location}/{name}"
        try:
            self.group = store.group[name]
        except Exception as exc:
            raise FormatError(f"{self.where}: unreadable zarr metadata ({_one_line(exc)})") from None
        self._members: set[str] | None = None
        self._arrays: dict[str, zarr.Array] = {}
        self._checkers: dict[str, ChunkChecker] = {}
        self._time: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return self.attrs.n_frames

    @property
    def split(self) -> str:
        return self.attrs.split

    def _member_names(self) -> set[str]:
        if self._members is None:
            try:
                self._members = set(self.group.array_keys())
            except Exception:  # a member's metadata is unreadable: array() names it
                self._members = set(_child_names(self.group))
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
            raise FormatError(f"{where}: unreadable zarr metadata ({_one_line(exc)})") from None
        if not isinstance(arr, zarr.Array):
            raise FormatError(f"{where}: is a group, not an array")
        try:
            dims = tuple(arr.metadata.dimension_names or ())
            problems = array_meta_problems(key, str(arr.dtype), dims, tuple(arr.shape),
                                           expected_shape(key, self.n_frames, self.store.grid.shape))
        except Exception as exc:  # metadata zarr accepted but we cannot interpret
            raise FormatError(f"{where}: unusable zarr metadata ({_one_line(exc)})") from None
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
            tol = 1e-6 * max(1.0, float(np.max(np.abs(centres))))
            if not np.allclose(values, centres, rtol=0, atol=tol):
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
            from .plausibility import command_problems  # it imports validate, which imports this module

            # Only commands no ground robot could follow are unreadable; commands beyond this rig's
            # declared limits are implausible, which validate reports and --allow-implausible accepts.
            lines = command_problems(block, None)
            if lines:
                raise FormatError(f"{where}: {lines[0].split(': ', 1)[1]}")
        if key == "time" and start == 0 and stop == n:
            bad_steps = np.flatnonzero(np.diff(block) <= 0)
            if bad_steps.size:
                raise FormatError(f"{where}: not strictly increasing (first at frame {int(bad_steps[0]) + 1})")
            line = frame_interval_problem(block, self.store.attrs.frame_rate_hz)
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
                                   f"decoded ({_one_line(one)})")
        return FormatError(f"{self.where}/{key}: frames {start}..{stop - 1} cannot be read ({_one_line(exc)})")

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


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if len(text) > 200:
        text = text[:197] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _child_names(group: zarr.Group) -> list[str]:
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


def _first_unreadable_node(root: zarr.Group) -> tuple[str, Exception] | None:
    """(path, error) of the first run group or array under ``root`` whose metadata zarr cannot parse."""
    for name in _child_names(root):
        try:
            node = root[name]
        except Exception as exc:
            return name, exc
        if not isinstance(node, zarr.Group):
            continue
        for child in _child_names(node):
            try:
                root[f"{name}/{child}"]
            except Exception as exc:
                return f"{name}/{child}", exc
    return None
