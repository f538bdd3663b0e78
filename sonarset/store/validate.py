"""Conformance checks of a SonarSet store against spec/FORMAT.md.

``validate_store`` never raises for a bad store: it returns one :class:`Problem` per finding,
so that ``sonarset validate`` can print them all, one line each. It walks the store with the same
helpers the readers use (``store.root``, ``store.run``, ``store.integrity``), applying the same
rules (``sonarset.format.rules``, ``sonarset.format.arrays``): where a reader raises the first
problem, this lists them all.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, ClassVar

import numpy as np
import zarr

from sonarset.errors import RemoteError, SonarSetError, one_line
from sonarset.format.arrays import (
    ARRAYS, checksum_problems, coordinate_problems, frame_interval_problems, in_unit_interval, nonfinite_problems,
    recorded_gap_frames, time_order_problems, unit_interval_problems,
)
from sonarset.format.plausibility import Implausible, store_problems
from sonarset.format.problems import Problem
from sonarset.format.rules import command_limit_problems, run_state_problems, store_attrs_problems
from sonarset.store.integrity import ChunkChecker
from sonarset.store.root import (child_groups, consolidated_staleness, local_root_problems, open_root,
                                 run_group_attrs, store_attrs)
from sonarset.store.run import decode_problems, open_array, run_members
from sonarset.store.store import SonarStore
from sonarset.store.zarrio import is_url

__all__ = ["Problem", "ProgressFn", "Stale", "validate_store"]


ProgressFn = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Stale(Problem):
    """Consolidated metadata that does not match the store (spec/FORMAT.md §6). Only readers that
    trust the snapshot (those of URLs) are misled, and they cannot tell without listing the store,
    which the snapshot exists to avoid; readers of local stores list it. So only ``validate``
    reports it."""

    refused_by_readers: ClassVar[bool] = False


def validate_store(location: str | os.PathLike, *, check_data: bool = True,
                   progress: ProgressFn | None = None, plausibility: bool = True) -> list[Problem]:
    """All problems of the store at ``location``; an empty list means it is valid.

    ``plausibility`` adds the rules of ``sonarset.format.plausibility`` (values no in-air sonar records),
    as ``Implausible`` problems.
    """
    loc = os.fspath(location)
    try:
        return _validate(loc, check_data, progress, plausibility)
    except RemoteError:
        raise
    except Exception as exc:  # a check that is not guarded below: still a finding, never a crash
        return [Problem(loc, f"cannot be checked: {one_line(exc)}")]


def _validate(loc: str, check_data: bool, progress: ProgressFn | None, plausibility: bool) -> list[Problem]:
    local = not is_url(loc)
    if local:
        early = local_root_problems(Path(loc))
        if early:
            return early
    # Validation must see what is really there, not a consolidated snapshot.
    try:
        root, loc = open_root(loc, "r", consolidated=False, root_checked=local)
    except RemoteError:
        raise
    except SonarSetError as exc:
        return [Problem("", str(exc))]
    attrs, problems = store_attrs(root, loc)
    if attrs is None:
        return problems
    store = SonarStore(root, loc, "r")
    problems += [p.at(loc) for p in store_attrs_problems(attrs)]
    nodes, listing = child_groups(root, loc)
    problems += listing
    if not nodes and not listing:
        return problems + [Problem(loc, "empty store: no run groups")]
    complete: list[str] = []
    for name, node in nodes.items():
        problems += _guarded(f"{loc}/{name}",
                             lambda name=name, node=node: _check_run(store, name, node, check_data, progress, complete))
    problems += _guarded(loc, lambda: _check_consolidated(loc, root, list(nodes)))
    if plausibility:
        # A value the format refuses is not also implausible: the format problem says it. Nor are
        # the commands of a run whose velocity the format refused read for it: their declared
        # length may be absurd (a shape edited to 1e9 frames would be read as that many fill values).
        refused = {p.where for p in problems}
        sound = [n for n in complete if not {f"{loc}/{n}", f"{loc}/{n}/velocity"} & refused]
        problems += [p for p in _guarded(loc, lambda: store_problems(store, check_data, sound))
                     if not (isinstance(p, Implausible) and p.where in refused)]
    if not problems and not complete:
        problems.append(Problem(loc, "no complete run"))
    return problems


def _guarded(where: str, check: Callable[[], list[Problem]]) -> list[Problem]:
    """Run one check; an exception it raises is a finding about the store, never a crash."""
    try:
        return check()
    except RemoteError:
        raise
    except Exception as exc:  # zarr and numpy raise many types on broken metadata or chunks
        return [Problem(where, f"cannot be checked: {one_line(exc)}")]


def _check_run(store: SonarStore, name: str, group: zarr.Group, check_data: bool, progress: ProgressFn | None,
               complete: list[str]) -> list[Problem]:
    """The problems of run group ``name`` (opened: ``group``); appends it to ``complete`` if it is."""
    where = f"{store.location}/{name}"
    attrs, out = run_group_attrs(store.group, store.location, name, group)
    if attrs is None:
        return out
    out += [p.at(where) for p in run_state_problems(attrs)]
    if not attrs.complete:
        return out
    complete.append(name)
    present = run_members(group)
    for key, spec in ARRAYS.items():
        if key not in present and not spec.required:
            continue
        arr, found = open_array(group, key, where, attrs.n_frames, store.grid.shape, present)
        out += found
        if arr is not None:  # from format 1.2 every chunk carries a checksum
            codecs = [codec.to_dict() for codec in arr.metadata.codecs]
            out += [p.at(where) for p in checksum_problems(key, codecs, store.attrs.format_version)]
        if arr is not None and not check_data:  # what a reader refuses at open, even in a quick pass
            out += [p.at(f"{where}/{key}") for p in ChunkChecker(arr).beyond_storage()]
        # The coordinates are checked even in a quick pass: they say whether the run is on the grid.
        if arr is not None and (check_data or key in ("range", "azimuth")):
            gaps = recorded_gap_frames((attrs.model_extra or {}).get("gaps", []))
            out += _guarded(f"{where}/{key}",
                            lambda key=key, arr=arr, gaps=gaps: _data_problems(where, key, arr, progress, store, gaps))
    return out


def _data_problems(run: str, key: str, arr: zarr.Array, progress: ProgressFn | None,
                   store: SonarStore, gap_frames: np.ndarray | None = None) -> list[Problem]:
    """The chunks and values of array ``key`` of the run at ``run``, as ``Run.read`` checks them,
    all of them reported."""
    aw = f"{run}/{key}"
    checker = ChunkChecker(arr)
    beyond = checker.beyond_storage()
    if beyond:  # a length far beyond storage: its values are fill, and visiting them could take hours
        return [p.at(aw) for p in beyond]
    missing, damaged = checker.damage()
    out = [p.at(aw) for p in missing + damaged]
    if damaged:
        return out  # a chunk that lies about its size decodes to garbage: its values say nothing
    step = arr.metadata.chunk_grid.chunk_shape[0]
    T = arr.shape[0]
    bad_finite: list[Problem] = []
    bad_range: list[Problem] = []
    prev_t = -np.inf
    for start in range(0, T, step):
        stop = min(T, start + step)
        try:
            block = arr[start:stop]
        except RemoteError:
            raise
        except Exception as exc:
            return out + [p.at(aw) for p in decode_problems(arr, start, stop, exc)]
        # Images finite and in [0, 1], the common case, in one fast pass (float16 isfinite is ~30x slower).
        clean = key == "images" and in_unit_interval(block)
        nonfinite = [] if clean else nonfinite_problems(key, block, start)
        bad_finite = bad_finite or nonfinite
        if key == "images" and not bad_range and not clean:
            bad_range = unit_interval_problems(key, block, start)
        if key == "time" and not nonfinite:
            order = time_order_problems(block, prev_t, start)
            if order:
                return out + [p.at(run) for p in order]
            prev_t = float(block[-1])
        if progress is not None:
            progress(aw, stop, T)
    if not missing:  # a missing chunk reads as the fill value, NaN: the missing chunk says it
        out += [p.at(run) for p in bad_finite]
    out += [p.at(run) for p in bad_range]
    if out:
        return out
    values = arr[:]
    if key == "time":
        out += [p.at(run) for p in frame_interval_problems(values, store.attrs.frame_rate_hz, gap_frames)]
    elif key == "velocity":
        out += [p.at(run) for p in command_limit_problems(values)]
    elif key in ("range", "azimuth"):
        out += [p.at(run) for p in coordinate_problems(key, values, store.grid)]
    return out


def _check_consolidated(loc: str, root: zarr.Group, names: list[str]) -> list[Problem]:
    """Consolidated metadata is optional, but when present it must match the store node for node:
    a URL reader trusts it instead of listing, so a run or array it lacks cannot be read there."""
    stale = consolidated_staleness(root, names)
    if stale is None:
        return []
    return [Stale(loc, f"consolidated metadata is {stale}; consolidate the store again")]
