"""Conformance checks of a SonarSet store against spec/FORMAT.md.

``validate_store`` never raises for a bad store: it returns one :class:`Problem` per finding,
so that ``sonarset validate`` can print them all, one line each.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Callable

import numpy as np
import zarr
from pydantic import ValidationError

from sonarset.format.arrays import (
    ARRAYS, array_meta_problems, coordinates_match, expected_shape, frame_interval_problem, in_unit_interval,
    nonfinite_frame, time_order_problem, unit_interval_problem,
)
from sonarset.errors import SonarSetError, one_line
from sonarset.store.integrity import ChunkChecker, chunk_coords
from sonarset.format.plausibility import store_problems
from sonarset.format.problems import Problem
from sonarset.format.attrs import NAMESPACE, RUN_NAME_RE, SUPPORTED_MAJOR, RunAttrs, StoreAttrs, parse_version, pydantic_problems
from sonarset.store.store import open_store
from sonarset.store.zarrio import child_names, is_url

__all__ = ["Problem", "ProgressFn", "validate_store"]


ProgressFn = Callable[[str, int, int], None]


def validate_store(location: str | os.PathLike, *, check_data: bool = True,
                   progress: ProgressFn | None = None, plausibility: bool = True) -> list[Problem]:
    """All problems of the store at ``location``; an empty list means it is valid.

    ``plausibility`` adds the rules of ``sonarset.format.plausibility`` (values no in-air sonar records),
    as ``Implausible`` problems.
    """
    loc = os.fspath(location)
    try:
        return _validate(loc, check_data, progress, plausibility)
    except Exception as exc:  # a check that is not guarded below: still a finding, never a crash
        return [Problem(loc, f"cannot be checked: {one_line(exc)}")]


def _validate(loc: str, check_data: bool, progress: ProgressFn | None, plausibility: bool) -> list[Problem]:
    local = not is_url(loc)
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
    problems += _guarded(loc, lambda: _check_store_attrs(loc, store.attrs))
    names, listing = _run_groups(loc, root)
    problems += listing
    if not names and not listing:
        return problems + [Problem(loc, "empty store: no run groups")]
    for name in names:
        problems += _guarded(f"{loc}/{name}", lambda: _check_run(store, name, check_data, progress))
    problems += _guarded(loc, lambda: _check_consolidated(loc, root, names))
    if plausibility:
        problems += _guarded(loc, lambda: store_problems(store, check_data))
    if not problems:
        problems += _guarded(loc, lambda: [] if store.runs() else [Problem(loc, "no complete run")])
    return problems


def _guarded(where: str, check: Callable[[], list[Problem]]) -> list[Problem]:
    """Run one check; an exception it raises is a finding about the store, never a crash."""
    try:
        return check()
    except Exception as exc:  # zarr and numpy raise many types on broken metadata or chunks
        return [Problem(where, f"cannot be checked: {one_line(exc)}")]


def _run_groups(loc: str, root: zarr.Group) -> tuple[list[str], list[Problem]]:
    """The root's child groups, and a problem for each child whose metadata zarr cannot parse
    (zarr's own listing fails as a whole on one broken child)."""
    try:
        return sorted(root.group_keys()), []
    except Exception:
        pass
    names, problems = [], []
    for name in child_names(root):
        try:
            node = root[name]
        except Exception as exc:
            problems.append(Problem(f"{loc}/{name}", f"unreadable zarr metadata ({one_line(exc)})"))
            continue
        if isinstance(node, zarr.Group):
            names.append(name)
    return names, problems


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
    attributes = doc.get("attributes")
    raw = attributes.get(NAMESPACE) if isinstance(attributes, dict) else None
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
    arrays = _conforming_arrays(where, group, attrs.n_frames, store.grid, out)
    for key, centres in (("range", store.grid.range_centres()), ("azimuth", store.grid.azimuth_centres())):
        if key in arrays:
            out += _coordinate_problems(f"{where}/{key}", arrays.pop(key), centres, "m" if key == "range" else "rad")
    if check_data:
        for key, arr in arrays.items():
            out += _guarded(f"{where}/{key}", lambda: _check_data(f"{where}/{key}", key, arr, progress,
                                                               store.attrs.frame_rate_hz))
    return out


def _conforming_arrays(where: str, group: zarr.Group, n_frames: int, grid, out: list[Problem]) -> dict[str, zarr.Array]:
    """The run's arrays whose metadata lets their values be read (dtype and shape as the spec says);
    a problem in ``out`` for every array missing, unreadable or not conforming."""
    try:
        present = set(group.array_keys())
    except Exception:  # one member's metadata is unreadable: open each below to say which
        present = set(child_names(group))
    arrays: dict[str, zarr.Array] = {}
    for key, spec in ARRAYS.items():
        if key not in present:
            if spec.required:
                out.append(Problem(where, f"missing required array {key!r}"))
            continue
        aw = f"{where}/{key}"
        try:
            arr = group[key]
            if not isinstance(arr, zarr.Array):
                out.append(Problem(aw, "is a group, not an array"))
                continue
            dims = tuple(arr.metadata.dimension_names or ())
            dtype, shape = str(arr.dtype), tuple(arr.shape)
        except Exception as exc:
            out.append(Problem(aw, f"unreadable zarr metadata ({one_line(exc)})"))
            continue
        found = array_meta_problems(key, dtype, dims, shape, expected_shape(key, n_frames, grid.shape))
        out += [Problem(aw, f"{line} (n_frames={n_frames}, grid {grid.shape[0]}x{grid.shape[1]})"
                        if line.startswith("shape") else line) for line in found]
        if not any(line.startswith(("dtype", "shape")) for line in found):
            arrays[key] = arr
    return arrays


def _coordinate_problems(aw: str, arr: zarr.Array, centres: np.ndarray, unit: str) -> list[Problem]:
    """A coordinate array's chunks, and its values against the store grid's bin centres."""
    damaged = _damaged_chunks(aw, arr)
    if damaged:
        return damaged
    try:
        values = arr[:]
    except Exception as exc:
        return [Problem(aw, f"unreadable ({one_line(exc)})")]
    if coordinates_match(values, centres):
        return []
    return [Problem(aw, f"coordinates do not match the store grid (got {values[0]:.6g}..{values[-1]:.6g} {unit}, "
                        f"grid {centres[0]:.6g}..{centres[-1]:.6g} {unit})")]


def _damaged_chunks(aw: str, arr: zarr.Array) -> list[Problem]:
    """Chunks missing from storage, and the first whose size disagrees with its header or shape
    (zarr would decode it from memory past its end); at most one line each."""
    checker = ChunkChecker(arr)
    missing, damaged = [], None
    for coords in chunk_coords(arr):
        problem = checker.problem(coords)
        if problem is None:
            continue
        if checker.is_missing(problem):
            missing.append(checker.key(coords))
        elif damaged is None:
            damaged = (checker.key(coords), problem)
    out = []
    if missing:
        out.append(Problem(aw, f"{len(missing)} chunk(s) missing from storage (deleted?), first: {missing[0]}"))
    if damaged is not None:
        out.append(Problem(aw, f"chunk {damaged[0]} {damaged[1]}"))
    return out


def _check_data(aw: str, key: str, arr: zarr.Array, progress: ProgressFn | None,
                frame_rate_hz: float) -> list[Problem]:
    out = _damaged_chunks(aw, arr)
    missing = any("chunk(s) missing from storage" in p.message for p in out)
    if len(out) > int(missing):
        return out  # a chunk that lies about its size decodes to garbage: its values say nothing
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
        # Images finite and in [0, 1], the common case, in one fast pass (float16 isfinite is ~30x slower).
        clean = key == "images" and in_unit_interval(block)
        nonfinite = None if clean else nonfinite_frame(block, start)
        bad_finite = nonfinite if bad_finite is None else bad_finite
        if key == "images" and bad_range is None and not clean:
            bad_range = unit_interval_problem(block, start)
        if key == "time" and nonfinite is None:
            line = time_order_problem(block, prev_t, start)
            if line is not None:
                out.append(Problem(aw, f"time is {line}"))
                return out
            prev_t = float(block[-1])
        if progress is not None:
            progress(aw, stop, T)
    if bad_finite is not None and not missing:
        out.append(Problem(aw, f"NaN or infinite values (first at frame {bad_finite})"))
    if bad_range is not None:
        out.append(Problem(aw, bad_range))
    if key == "time" and not out:
        line = frame_interval_problem(arr[:], frame_rate_hz)
        if line is not None:
            out.append(Problem(aw, line))
    return out


def _check_consolidated(loc: str, root: zarr.Group, names: list[str]) -> list[Problem]:
    """Consolidated metadata is optional, but when present it must match the store node for node:
    a URL reader trusts it instead of listing, so a run or array it lacks cannot be read there."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.core.sync import sync

    raw = sync(root.store.get(f"{root.path}/zarr.json" if root.path else "zarr.json", prototype=default_buffer_prototype()))
    doc = json.loads(raw.to_bytes()) if raw is not None else None
    if not isinstance(doc, dict) or doc.get("consolidated_metadata") is None:
        return []
    fix = "run `sonarset validate --consolidate`"
    try:
        cons = zarr.open_group(root.store, mode="r", use_consolidated=True)
        listed = cons.metadata.consolidated_metadata.flattened_metadata
    except Exception as exc:
        return [Problem(loc, f"consolidated metadata is unreadable ({one_line(exc)}); {fix}")]
    actual, unreadable = _node_metadata(root, names)
    # Compare runs and their arrays; what cannot be read is reported by the run checks already.
    listed = {k: v for k, v in listed.items()
              if k.count("/") <= 1 and k not in unreadable and k.split("/")[0] not in unreadable}

    def plain(meta) -> dict:
        d = meta.to_dict()
        d.pop("consolidated_metadata", None)  # nested snapshots are compared node by node
        return d

    lacks = sorted(set(actual) - set(listed))
    extra = sorted(set(listed) - set(actual))
    differ = sorted(k for k in set(actual) & set(listed) if plain(actual[k]) != plain(listed[k]))
    if not (lacks or extra or differ):
        return []
    if lacks:
        detail = f"it lacks {lacks[0]}" + (f" and {len(lacks) - 1} more node(s)" if len(lacks) > 1 else "")
    elif extra:
        detail = f"it lists {extra[0]}, which the store does not hold"
    else:
        detail = f"its copy of {differ[0]}'s metadata differs from the store's"
    return [Problem(loc, f"consolidated metadata is stale ({detail}; readers of URLs trust it); {fix}")]


def _node_metadata(root: zarr.Group, names: list[str]) -> tuple[dict, set[str]]:
    """The metadata of every readable node under the root's run groups (runs and their arrays),
    and the keys of those whose metadata zarr cannot parse (the run checks report them)."""
    actual, unreadable = {}, set()
    for name in names:
        try:
            group = root[name]
            actual[name] = group.metadata
        except Exception:
            unreadable.add(name)
            continue
        for child in child_names(group):
            key = f"{name}/{child}"
            try:
                actual[key] = root[key].metadata
            except Exception:
                unreadable.add(key)
    unreadable |= {n for n in child_names(root) if n not in names}  # children that are no group
    return actual, unreadable
