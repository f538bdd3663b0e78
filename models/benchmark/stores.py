"""The protocol's stores: simulated on first use into a cache folder, checked and reused after.

Generation is deterministic from the recipe's seed (``sonarset.sim.generate``), and resumable:
a killed generation leaves complete runs and incomplete ones that readers ignore, and the next
benchmark completes them. A cached store is reused only when every planned run is complete,
readable and made with the plan's settings (world, seeds, frames, images and simulator version,
from each run's provenance) on the protocol's grid; the recipe is recorded in the store's root
attributes under ``MARKER``, which also marks the store as the benchmark's own, the only kind it
ever discards (a store of older settings is regenerated).
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Callable

from sonarset.errors import FormatError, SonarSetError
from sonarset.store.atomic import aside_dir
from sonarset.store.lock import writer_lock
from sonarset.store.store import SonarStore, open_store

from sonarset.models.benchmark.protocol import Protocol, StoreRecipe

#: The root attribute that records which benchmark recipe made a store.
MARKER = "sonarset_benchmark"


def cache_dir(protocol: Protocol, cache: str | os.PathLike | None = None) -> Path:
    """Where the protocol's stores live: ``cache``, else ``$SONARSET_CACHE/benchmark/VERSION``,
    else ``~/.cache/sonarset/benchmark/VERSION``."""
    if cache:
        return Path(cache).expanduser()
    root = os.environ.get("SONARSET_CACHE") or Path.home() / ".cache" / "sonarset"
    return Path(root).expanduser() / "benchmark" / protocol.version


def marker(recipe: StoreRecipe, protocol: Protocol) -> dict:
    return {"protocol": protocol.name, "version": protocol.version, "store": recipe.name, **recipe.to_dict()}


def cache_problem(path: Path, recipe: StoreRecipe, protocol: Protocol) -> tuple[str, bool] | None:
    """None when the store at ``path`` can be used as it is; else why not, and whether it must be
    discarded (other settings) rather than completed (runs missing or broken)."""
    from sonarset.sim.runs import plan_runs

    if not (path / "zarr.json").exists():
        empty = not path.exists() or (path.is_dir() and not any(path.iterdir()))
        return ("not generated yet", False) if empty else ("not a SonarSet store", True)
    spec = recipe.spec(protocol)
    try:
        store = open_store(path)
        if not store.grid.matches(spec.grid) or not store.processing.same_images(spec.processing):
            return f"grid {store.grid.describe()}, images {store.processing.describe()}", True
        complete = set(store.runs())
        plans = plan_runs(spec)
        extra = complete - {p.name for p in plans}
        if extra:
            return f"runs {', '.join(sorted(extra))} are not the recipe's", True
        for plan in plans:
            if plan.name not in complete:
                return f"run {plan.name} is incomplete", False
            run = store.run(plan.name)
            have = {k: (run.attrs.source or {}).get(k) for k in plan.source()}
            if have != plan.source():
                differ = sorted(k for k in have if have[k] != plan.source()[k])
                return f"run {plan.name} was made with other settings ({', '.join(differ)})", True
            try:
                run.check(chunks=True)
            except FormatError as exc:
                return f"run {plan.name} is broken ({exc})", False
    except (SonarSetError, OSError, ValueError) as exc:
        return f"unreadable ({exc})", True
    if store.group.attrs.get(MARKER) != marker(recipe, protocol):
        return UNMARKED, False
    return None


#: What ``cache_problem`` says of a store whose runs are all the recipe's but whose mark is another
#: protocol's (a variant that changes only how many windows are scored): marked, not simulated.
UNMARKED = "not marked as the recipe's store"


def _mark(path: Path, recipe: StoreRecipe, protocol: Protocol) -> None:
    with writer_lock(path):
        store = open_store(path, "r+")
        store.group.attrs[MARKER] = marker(recipe, protocol)
        store.consolidate()


def ensure_store(recipe: StoreRecipe, protocol: Protocol, folder: Path, *,
                 progress: Callable[[str, int, int], None] | None = None,
                 log: Callable[[str], None] | None = None) -> tuple[SonarStore, dict]:
    """The recipe's store in ``folder``, generated or completed where needed; and what was done:
    {"file" (its name in the cache: a results file names no directory of the machine), "generated" (bool),
    "reason" (why it was generated, or None), "seconds"}."""
    from sonarset.sim import generate

    path = folder / f"{recipe.name}.zarr"
    t0 = time.perf_counter()
    problem = cache_problem(path, recipe, protocol)
    if problem == (UNMARKED, False):
        _mark(path, recipe, protocol)
        problem = None
    if problem is not None:
        reason, discard = problem
        if discard:
            _discard(path, reason)
        if log:
            log(f"simulating {recipe.name} ({recipe.world}, {recipe.minutes:g} min, seed {recipe.seed}) -> {path}: "
                f"{reason}")
        folder.mkdir(parents=True, exist_ok=True)
        generate(path, recipe.spec(protocol), progress=progress)
        _mark(path, recipe, protocol)
        left = cache_problem(path, recipe, protocol)
        if left is not None:
            raise SonarSetError(f"{path}: the benchmark's store is still not usable after generating it: {left[0]}")
    info = {"file": path.name, "generated": problem is not None, "reason": problem and problem[0],
            "seconds": time.perf_counter() - t0}
    return open_store(path), info


def _discard(path: Path, reason: str) -> None:
    """Remove a store of other settings, if it is the benchmark's own (it carries ``MARKER``):
    moved aside first, so that a kill leaves no half-deleted store at ``path``."""
    try:
        ours = MARKER in open_store(path).group.attrs
    except (SonarSetError, OSError, ValueError):
        ours = False
    if not ours:
        raise SonarSetError(f"{path}: {reason}, and it is not a store the benchmark made; remove it or use "
                            "another cache folder", parameter="cache")
    aside = aside_dir(path)
    os.replace(path, aside / path.name)
    shutil.rmtree(aside, ignore_errors=True)
