"""Generate SonarSet stores of simulated runs: parallel, deterministic, resumable.

The runs are planned from the master seed (``runs``), then simulated by a local process pool
(``local_pool``) or a Dask cluster (``distributed``), each task writing its own run group. Re-running
the same command keeps every complete run (the plan recorded in its ``source`` must match) and
redoes the others.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable

from sonarset.store.atomic import aside_dir, remove_stale_asides, settle_zarr_writes
from sonarset.errors import FormatError, SonarSetError, first_os_error, os_error_reason
from sonarset.store.store import SonarStore, create_store, open_or_create_store
from sonarset.version import __version__
from sonarset.store.lock import writer_lock
from sonarset.store.zarrio import is_url
from sonarset.sim.families import load_world
from sonarset.sim.spec import GenerationSpec
from sonarset.sim.runs import RunPlan, RunTarget, plan_runs, simulator_rig

DESCRIPTION = f"simulated by sonarset {__version__}"


def generate(
    out: str | os.PathLike,
    spec: GenerationSpec | None = None,
    *,
    workers: int | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    scheduler=None,
    storage_options: dict | None = None,
    **settings,
) -> list[str]:
    """Simulate the runs into the store ``out`` (a path or any fsspec URL); returns the names of the
    runs written now.

    Runs go to a local process pool, or, with ``scheduler``, to a Dask distributed cluster: an
    address (``tcp://host:8786``), ``"local"`` for a ``LocalCluster`` of ``workers`` processes, or a
    ``distributed.Client``. Each task writes its own run group to ``out``, which every worker must
    reach (a shared file system or object storage). The arrays are the same either way.

    What the store holds is ``spec``, or a ``GenerationSpec`` made of ``settings`` (its fields, with
    its defaults: ``generate(out, runs=2, minutes=1.0)``). ``world`` is a world family or file with
    ``runs`` training runs (default ``DEFAULT_RUNS``), or a mix that counts each world's runs,
    ``"lab:4,orchard:2,warehouse:2,rooms:2"`` (``runs`` then stays None); each world also gets
    ``test_runs`` test runs. Each run records its world and the variant's seed in its ``source``.

    ``processing`` is a profile name (``ertis``, the default, or ``raw``) or ``Processing`` settings;
    the store records it, with the robot's rig, in its attributes.
    """
    if spec is None:
        if settings.get("grid", ...) is None:  # None: the default grid, as for every other setting
            del settings["grid"]
        spec = GenerationSpec(**settings)
    elif settings:
        raise TypeError(f"generate takes a spec or its settings, not both (got {', '.join(settings)})")
    for name, _ in spec.world_mix():
        load_world(name, 0)  # fail fast on a bad world name or file, before any process starts
    plans = plan_runs(spec)
    loc = os.fspath(out).removeprefix("file://")  # a local path: the store is created aside and renamed
    with writer_lock(loc):  # one writer at a time: a second generate is refused, not interleaved
        if not is_url(loc):
            _prepare_local(Path(loc), spec, [p.name for p in plans])
        store = open_or_create_store(loc, spec.grid, description=DESCRIPTION, storage_options=storage_options,
                                     processing=spec.processing, rig=simulator_rig())
        todo = _runs_to_do(store, plans)
        try:
            _simulate_into(store, RunTarget(loc, spec.grid, storage_options), todo, workers, progress, scheduler)
        except OSError as exc:
            settle_zarr_writes()
            exc = first_os_error(exc)  # the run writer's clean-up failed too: report the cause
            raise SonarSetError(f"{loc}: cannot write {exc.filename or 'the store'}: {os_error_reason(exc)} (complete "
                                "runs are kept; re-run the same command to resume)") from None
        # Success is said only of runs readers accept: each kept run was checked above, and each
        # written one by its commit (RunWriter.commit verifies storage before the complete flag).
        return [p.name for p in todo]


def _runs_to_do(store: SonarStore, plans: list[RunPlan]) -> list[RunPlan]:
    """The plans whose run is not complete yet, or is flagged complete but broken (an array or
    chunk missing or cut short: re-simulated, the simulation is deterministic); a complete run
    made with other settings is an error."""
    todo = []
    complete = set(store.runs())  # listing reads every run's attributes: once, not once per plan
    for plan in plans:
        if plan.name in complete:
            run = store.run(plan.name)
            have = {"processing": "raw", **run.attrs.source}  # 1.0 runs were raw
            if {k: have.get(k) for k in plan.source()} != plan.source():
                raise SonarSetError(f"{store.location}: run {plan.name} was generated with other settings; "
                                    "use a new output or the same options")
            try:
                run.check(chunks=True)  # a stat per chunk: cheap next to simulating the run again
                continue
            except FormatError:
                pass
        todo.append(plan)
    return todo


def _simulate_into(store: SonarStore, target: RunTarget, todo: list[RunPlan], workers: int | None, progress,
                   scheduler) -> None:
    if todo and scheduler is not None:
        from sonarset.sim.distributed import run_on_dask  # Dask is an optional dependency

        run_on_dask(scheduler, target, todo, workers, progress, store)
    elif todo:
        from sonarset.sim.local_pool import run_locally

        run_locally(target, todo, workers, progress, store)
    store.consolidate()


def _prepare_local(dest: Path, spec: GenerationSpec, runs: list[str]) -> None:
    """Clear what a killed generate left at ``dest``'s root, and create the store if it is missing.

    A folder of one of ``runs`` without ``zarr.json`` (its group's first write never landed) is not
    a zarr node: zarr would warn about it on every listing, so it goes before the first one.

    The store is created aside and renamed into place: a kill during its first metadata writes
    leaves no folder without ``zarr.json`` that the same command would then refuse.
    """
    dest = dest.resolve() if dest.is_symlink() else dest  # the store goes where the link points
    remove_stale_asides(dest)
    if dest.is_dir():
        # zarr writes each file as zarr.<id>.partial, then renames it; a kill in between leaves
        # the temp file. No worker has started yet: nothing else is writing here.
        for debris in dest.glob("zarr.*.partial"):
            debris.unlink(missing_ok=True)
        for name in runs:
            if (dest / name).is_dir() and not (dest / name / "zarr.json").exists():
                shutil.rmtree(dest / name, ignore_errors=True)
    if (dest / "zarr.json").exists():
        return
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise SonarSetError(f"{dest}: exists and is not a SonarSet store (no zarr.json); choose another output")
    tmp = aside_dir(dest)
    try:
        create_store(tmp / "store.zarr", spec.grid, description=DESCRIPTION, processing=spec.processing,
                     rig=simulator_rig())
        try:
            os.replace(tmp / "store.zarr", dest)  # onto nothing or an empty directory
        except OSError:
            if not (dest / "zarr.json").exists():  # else another process created it first
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
