"""Conformance checks of a SonarSet store against spec/FORMAT.md.

``validate_store`` never raises for a bad store: it returns one :class:`Problem` per finding,
so that ``sonarset validate`` can print them all, one line each.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import zarr
from pydantic import ValidationError

from .errors import SonarSetError
from .schema import NAMESPACE, RUN_NAME_RE, SUPPORTED_MAJOR, RunAttrs, StoreAttrs, parse_version, pydantic_problems
from .arrays import ARRAYS, expected_shape
from .store import _is_url, open_store


@dataclass(frozen=True)
class Problem:
    where: str
    message: str

    def __str__(self) -> str:
        return f"{self.where}: {self.message}"


ProgressFn = Callable[[str, int, int], None]


def validate_store(location: str | os.PathLike, *, check_data: bool = True,
                   progress: ProgressFn | None = None) -> list[Problem]:
    """All problems of the store at ``location``; an empty list means it is valid."""
    loc = os.fspath(location)
    local = not _is_url(loc)
    problems: list[Problem] = []
    if local:
        early = _check_local_root(Path(loc))
        if early:
            return [early]
    # Validation must see what is really there, not a consolidated snapshot.
    try:
        store = open_store(loc, "r", consolidated=False)
    except SonarSetError as exc:
        msg = str(exc)
        prefix = f"{loc}: "
        return [Problem(loc, msg[len(prefix):] if msg.startswith(prefix) else msg)]
    except Exception as exc:  # a store so broken that zarr itself cannot parse it
        return [Problem(loc, f"cannot be opened as a zarr v3 group ({type(exc).__name__}: {exc})")]

    root = store.group
    problems += _check_store_attrs(loc, store.attrs)
    names = sorted(root.group_keys())
    if not names:
        return problems + [Problem(loc, "empty store: no run groups")]
    for name in names:
        problems += _check_run(store, name, check_data, progress)
    problems += _check_consolidated(loc, root, names)
    if not store.runs() and not problems:
        problems.append(Problem(loc, "no complete run"))
    return problems


def _check_local_root(path: Path) -> Problem | None:
    where = str(path)
    if not path.exists():
        return Problem(where, "no such file or directory")
    if not path.is_dir():
        return Problem(where, "not a zarr store (a file, not a directory)")
    meta = path / "zarr.json"
    if not meta.is_file():
        if (path / ".zgroup").exists():
            return Problem(where, "a Zarr v2 store; SonarSet requires Zarr v3")
        return Problem(where, "not a zarr store (no zarr.json at its root)")
    try:
        doc = json.loads(meta.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        return Problem(str(meta), f"unreadable JSON ({exc})")
    if not isinstance(doc, dict) or doc.get("zarr_format") != 3:
        return Problem(str(meta), "not Zarr v3 metadata (zarr_format must be 3)")
    if doc.get("node_type") != "group":
        return Problem(where, "root is a zarr array; a SonarSet store is a group")
    raw = (doc.get("attributes") or {}).get(NAMESPACE)
    if not isinstance(raw, dict):
        return Problem(where, f"missing root attribute {NAMESPACE!r}: not a SonarSet store")
    try:
        major, _ = parse_version(raw.get("format_version"))
    except ValueError as exc:
        return Problem(where, f"attributes.{NAMESPACE}.{exc}")
    if major != SUPPORTED_MAJOR:
        return Problem(where, f"unknown major format version {raw.get('format_version')} "
                              f"(this reader supports {SUPPORTED_MAJOR}.x)")
    try:
        StoreAttrs.model_validate(raw)
    except ValidationError as exc:
        return Problem(where, "; ".join(pydantic_problems(exc, f"attributes.{NAMESPACE}.")))
    return None


def _check_store_attrs(loc: str, attrs: StoreAttrs) -> list[Problem]:
    """What the schema alone cannot say about the root attributes (format 1.1)."""
    rig = attrs.rig
    if rig is not None and not math.isclose(rig.frame_interval_s * attrs.frame_rate_hz, 1.0, rel_tol=1e-6):
        return [Problem(loc, f"attributes.{NAMESPACE}.rig.frame_interval_s {rig.frame_interval_s:g} s disagrees "
                             f"with frame_rate_hz {attrs.frame_rate_hz:g} (1/{attrs.frame_rate_hz:g} = "
                             f"{1 / attrs.frame_rate_hz:g} s)")]
    return []


def _check_run(store, name: str, check_data: bool, progress: ProgressFn | None) -> list[Problem]:
    where = f"{store.location}/{name}"
    out: list[Problem] = []
    if not RUN_NAME_RE.match(name):
        out.append(Problem(where, "invalid run name (letters, digits, '_', '.', '-')"))
    group = store.group[name]
    raw = group.attrs.get(NAMESPACE)
    if not isinstance(raw, dict):
        return out + [Problem(where, f"missing run attribute {NAMESPACE!r}")]
    try:
        attrs = RunAttrs.model_validate(raw)
    except ValidationError as exc:
        return out + [Problem(where, line) for line in pydantic_problems(exc, f"attributes.{NAMESPACE}.")]
    if not attrs.complete:
        return out + [Problem(where, "incomplete run: its writer did not finish (re-run it or delete the group)")]

    grid = store.grid
    T = attrs.n_frames
    present = set(group.array_keys())
    arrays: dict[str, zarr.Array] = {}
    for key, spec in ARRAYS.items():
        if key not in present:
            if spec.required:
                out.append(Problem(where, f"missing required array {key!r}"))
            continue
        arr = group[key]
        aw = f"{where}/{key}"
        ok = True
        if str(arr.dtype) not in spec.dtypes:
            out.append(Problem(aw, f"dtype {arr.dtype} not allowed (expected {' or '.join(spec.dtypes)})"))
            ok = False
        dims = tuple(arr.metadata.dimension_names or ())
        if dims != spec.dims:
            out.append(Problem(aw, f"dimension_names {list(dims) or None} must be {list(spec.dims)}"))
        expected = expected_shape(key, T, grid.shape)
        if arr.shape != expected:
            out.append(Problem(aw, f"shape {arr.shape} does not match {expected} "
                                   f"(n_frames={T}, grid {grid.shape[0]}x{grid.shape[1]})"))
            ok = False
        if ok:
            arrays[key] = arr
    for key, centres in (("range", grid.range_centres()), ("azimuth", grid.azimuth_centres())):
        if key in arrays:
            try:
                values = arrays.pop(key)[:]
            except Exception as exc:
                out.append(Problem(f"{where}/{key}", f"unreadable ({type(exc).__name__})"))
                continue
            tol = 1e-6 * max(1.0, float(np.max(np.abs(centres))))
            if not np.allclose(values, centres, rtol=0, atol=tol):
                unit = "m" if key == "range" else "rad"
                out.append(Problem(f"{where}/{key}",
                                   f"coordinates do not match the store grid (got {values[0]:.6g}..{values[-1]:.6g} {unit}, "
                                   f"grid {centres[0]:.6g}..{centres[-1]:.6g} {unit})"))
    if check_data:
        for key, arr in arrays.items():
            out += _check_data(f"{where}/{key}", key, arr, progress)
    return out


def _storage_chunk_keys(arr: zarr.Array) -> Iterable[tuple[tuple[int, ...], str]]:
    chunk_shape = arr.metadata.chunk_grid.chunk_shape  # outer (shard) chunks when sharded
    grid = [range(math.ceil(s / c)) for s, c in zip(arr.shape, chunk_shape)]
    for coords in itertools.product(*grid):
        yield coords, arr.metadata.encode_chunk_key(coords)


def _missing_chunks(arr: zarr.Array) -> list[str]:
    from zarr.core.sync import sync

    if arr.nchunks_initialized >= arr.nchunks:
        return []
    store, base = arr.store_path.store, arr.store_path.path
    return [key for _, key in _storage_chunk_keys(arr) if not sync(store.exists(f"{base}/{key}"))]


def _check_data(aw: str, key: str, arr: zarr.Array, progress: ProgressFn | None) -> list[Problem]:
    out: list[Problem] = []
    missing = _missing_chunks(arr)
    if missing:
        out.append(Problem(aw, f"{len(missing)} chunk(s) missing from storage (deleted?), first: {missing[0]}"))
    step = arr.metadata.chunk_grid.chunk_shape[0]
    T = arr.shape[0]
    bad_finite = bad_range = None
    prev_t = -np.inf
    for start in range(0, T, step):
        stop = min(T, start + step)
        try:
            block = arr[start:stop]
        except Exception as exc:
            key0 = arr.metadata.encode_chunk_key((start // step,) + (0,) * (arr.ndim - 1))
            out.append(Problem(aw, f"chunk {key0} is corrupt or truncated ({type(exc).__name__})"))
            return out
        finite = np.isfinite(block)
        if bad_finite is None and not finite.all():
            bad_finite = start + int(np.argwhere(~finite)[0][0])
        if key == "images" and bad_range is None:
            vals = block[finite]
            if vals.size and (vals.min() < 0 or vals.max() > 1):
                bad_range = (float(vals.min()), float(vals.max()))
        if key == "time" and finite.all():
            seq = np.concatenate([[prev_t], block.astype(np.float64)])
            d = np.diff(seq)
            if np.any(d <= 0):
                out.append(Problem(aw, f"time is not strictly increasing (first at frame {start + int(np.argmax(d <= 0))})"))
                return out
            prev_t = float(block[-1])
        if progress is not None:
            progress(aw, stop, T)
    if bad_finite is not None and not missing:
        out.append(Problem(aw, f"NaN or infinite values (first at frame {bad_finite})"))
    if bad_range is not None:
        out.append(Problem(aw, f"values outside [0, 1] ({bad_range[0]:g}..{bad_range[1]:g})"))
    return out


def _check_consolidated(loc: str, root: zarr.Group, names: list[str]) -> list[Problem]:
    """Consolidated metadata is optional, but when present it must match the store."""
    try:
        cons = zarr.open_group(root.store, mode="r", use_consolidated=True)
    except Exception:
        return []
    meta = cons.metadata.consolidated_metadata
    if meta is None:
        return []
    listed = {k for k, v in meta.metadata.items() if "/" not in k and v.node_type == "group"}
    actual = {n: (root[n].attrs.get(NAMESPACE) or {}).get("complete") for n in names}
    stale = set(actual) != listed or any(
        (meta.metadata[n].attributes.get(NAMESPACE) or {}).get("complete") != c
        for n, c in actual.items() if n in meta.metadata
    )
    if stale:
        return [Problem(loc, "consolidated metadata is stale (lists other runs than the store holds); "
                             "run `sonarset validate --consolidate`")]
    return []
