"""Where an import writes: one run, into a new store or an existing one, built aside and moved in.

A new store is built beside its destination and renamed into place; a run for an existing local
store is built in a store beside it and renamed into the store, or swapped in atomically for the
run it replaces. An object store has no rename: there the run writer keeps the run invisible until
it is complete. An import that fails (a full disk) or is killed therefore never leaves a partial
run behind, and never loses the run it replaces. ``sonarset import`` and ``sonarset import-raw``
both write through :class:`ImportTarget`.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sonarset.format.arrays import median_interval
from sonarset.store.atomic import aside_dir, exchange, settle_zarr_writes
from sonarset.errors import SonarSetError, first_os_error, os_error_reason
from sonarset.store.run import Run
from sonarset.format.attrs import Processing, RobotRig, SensorGrid, run_name_problems, split_problems
from sonarset.store.store import SonarStore, create_store, open_or_create_store, open_store
from sonarset.store.lock import writer_lock
from sonarset.store.zarrio import is_url

#: Writes the imported run into ``store``; ``replace``: over a run of the same name. It must not
#: consolidate: the target does, once the run is where it belongs.
WriteRun = Callable[[SonarStore, bool], None]


def check_run_options(name: str | None, split: str | None) -> None:
    """One-line errors for a bad run ``name`` or ``split`` (the format's rules), before any file is read."""
    for problem in [] if name is None else run_name_problems(name):
        raise SonarSetError(f"name: {problem.message}", parameter="name")
    for problem in [] if split is None else split_problems(split):
        raise SonarSetError(f"split {split!r}: {problem.message}", parameter="split")


def run_name_for(src: str | os.PathLike, name: str | None, declared: str | None) -> str:
    """The run's name: ``name``, else the metadata's, else the file's stem; it must be valid."""
    run_name = name or declared or Path(src).stem
    for problem in run_name_problems(run_name):
        raise SonarSetError(f"{src}: {problem.message}; give the run a name", parameter="name")
    return run_name


def nominal_frame_rate(time: np.ndarray, rig: RobotRig | None) -> float:
    """A new store's frame rate: the rig's, else the recording's median time step, else the default."""
    if rig is not None:
        return 1.0 / rig.frame_interval_s
    dt = median_interval(time)
    if dt is not None and dt > 0:
        return float(f"{1.0 / dt:.3g}")  # nominal: jitter must not give 4.9975 Hz
    return 1.0 / RobotRig().frame_interval_s


@dataclass(frozen=True)
class ImportTarget:
    """The store an import writes to: ``existing`` (opened for reading) or None for a new one."""

    location: str
    existing: SonarStore | None

    @classmethod
    def at(cls, out: str | os.PathLike) -> "ImportTarget":
        loc = os.fspath(out).removeprefix("file://")  # a local path: renamed into, not written through fsspec
        exists = is_url(loc) or (Path(loc) / "zarr.json").exists()
        return cls(loc, open_store(loc) if exists else None)

    def write(self, run_name: str, write: WriteRun, *, overwrite: bool, grid: SensorGrid,
              processing: Processing | None, rig: RobotRig | None, new_store: Mapping[str, Any]) -> Run:
        """Write the run ``run_name`` with ``write``; returns it, read back.

        An existing store must have ``grid`` and, where given, make the same images
        (``processing``) on the same ``rig``; a new one is made by ``create_store`` with ``grid``,
        ``rig`` and ``new_store``'s keywords.
        """
        with writer_lock(self.location):  # one writer at a time; what exists is decided under the lock
            return self._write_locked(run_name, write, overwrite=overwrite, grid=grid, processing=processing,
                                      rig=rig, new_store=new_store)

    def write_runs(self, writers: Sequence[tuple[str, WriteRun]], *, overwrite: bool, grid: SensorGrid,
                   processing: Processing | None, rig: RobotRig | None, new_store: Mapping[str, Any]) -> list[Run]:
        """Write several runs (``(name, write)`` pairs) as one import; returns them, read back.

        A recording that splits into many runs (a drive with lost pings) must not be left half
        imported: a new store is built aside whole and renamed into place; into an existing local
        store all the runs are built aside, then renamed in together and consolidated once. An
        import killed or failed while it builds leaves the store as it was, so the same command
        can simply be run again. (An object store has no rename: there runs go in one by one.)
        """
        if len(writers) == 1:
            [(name, write)] = writers
            return [self.write(name, write, overwrite=overwrite, grid=grid, processing=processing, rig=rig,
                               new_store=new_store)]
        names = [name for name, _ in writers]
        with writer_lock(self.location):
            loc = self.location
            existing = self.existing
            if existing is None and (Path(loc) / "zarr.json").exists():
                existing = open_store(loc)  # another writer made the store since ``at`` looked
            if existing is None:
                def write_all(store: SonarStore) -> None:
                    for _, write in writers:
                        write(store, False)

                dest = write_new_store(loc, names[0], write_all, grid=grid, rig=rig, **new_store)
                store = open_store(dest)
                return [store.run(name) for name in names]
            store = open_or_create_store(loc, grid, processing=processing, rig=rig)
            taken = [name for name in names if name in store.runs()]
            if taken and not overwrite:
                raise SonarSetError(f"{loc}: run(s) {_listing(taken)} already exist (overwrite them, or give another "
                                    "name)", parameter="overwrite")
            if is_url(loc):
                for name, write in writers:
                    replaced = overwrite and name in store.group.group_keys()
                    with write_failure(loc, name, "the run it replaced is gone" if replaced else "the runs before it "
                                       "were written"):
                        write(store, overwrite)
                store.consolidate()
            else:
                move_runs_in(store, names, lambda side: [write(side, False) for _, write in writers])
            store = open_store(loc)
            return [store.run(name) for name in names]

    def _write_locked(self, run_name: str, write: WriteRun, *, overwrite: bool, grid: SensorGrid,
                      processing: Processing | None, rig: RobotRig | None, new_store: Mapping[str, Any]) -> Run:
        loc = self.location
        existing = self.existing
        if existing is None and (Path(loc) / "zarr.json").exists():
            existing = open_store(loc)  # another writer made the store since ``at`` looked
        if existing is None:
            dest = write_new_store(loc, run_name, lambda store: write(store, False), grid=grid, rig=rig, **new_store)
            return open_store(dest).run(run_name)
        store = open_or_create_store(loc, grid, processing=processing, rig=rig)
        if run_name in store.runs() and not overwrite:
            raise SonarSetError(f"{loc}: run {run_name!r} already exists (overwrite it, or give another name)",
                                parameter="overwrite")
        if is_url(loc):  # object stores have no rename: the run writer keeps it invisible until complete
            replaced = overwrite and run_name in store.group.group_keys()
            with write_failure(loc, run_name, "the run it replaced is gone" if replaced else "nothing was changed"):
                write(store, overwrite)
                store.consolidate()
        else:
            move_run_in(store, run_name, lambda side: write(side, False))
        return open_store(loc).run(run_name)


def write_new_store(out_s: str, run_name: str, write: Callable[[SonarStore], None], **create) -> Path:
    """A new store at ``out_s`` holding the run ``write(store)`` writes, made by ``create_store(**create)``
    beside it and renamed into place: a failed or killed import leaves nothing that looks like a store."""
    dest = Path(out_s)
    dest = dest.resolve() if dest.is_symlink() else dest  # the store goes where the link points
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise SonarSetError(f"{out_s}: exists and is not a SonarSet store")
    tmp = aside_dir(dest)
    try:
        with write_failure(out_s, run_name):
            store = create_store(tmp / "store.zarr", **create)
            write(store)
            store.consolidate()
        if dest.exists():
            dest.rmdir()  # an empty directory, checked above
        os.replace(tmp / "store.zarr", dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


def move_run_in(store: SonarStore, run_name: str, write: Callable[[SonarStore], None]) -> None:
    """Build the run in a store beside ``store``, then rename it in, or swap it for the run it replaces."""
    move_runs_in(store, [run_name], write)


def move_runs_in(store: SonarStore, run_names: Sequence[str], write: Callable[[SonarStore], None]) -> None:
    """Build the runs ``run_names`` in a store beside ``store`` (``write`` writes them all), then
    rename each in, or swap it for the run it replaces, and consolidate once."""
    root = Path(store.location)
    tmp = aside_dir(root)
    label = run_names[0] if len(run_names) == 1 else f"{run_names[0]}..{run_names[-1]}"
    moved: list[tuple[Path, Path, bool]] = []
    try:
        with write_failure(store.location, label):
            side = create_store(tmp / "store.zarr", store.grid, processing=store.processing, rig=store.attrs.rig,
                                frame_rate_hz=store.attrs.frame_rate_hz)
            write(side)
        try:
            for run_name in run_names:
                new, target = tmp / "store.zarr" / run_name, root / run_name
                # Anything at the run's path (the run replaced, or what a killed writer left) is
                # swapped out whole and deleted with the aside directory.
                swapped = target.exists() or target.is_symlink()
                if swapped:
                    exchange(new, target)
                else:
                    os.rename(new, target)
                moved.append((new, target, swapped))
            with write_failure(store.location, label):
                store.consolidate()
        except BaseException:
            # Without its consolidated metadata the store would list other runs than it holds:
            # put back what was there.
            for new, target, swapped in reversed(moved):
                if swapped:
                    exchange(new, target)
                else:
                    os.rename(target, new)
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _listing(names: Sequence[str], most: int = 5) -> str:
    shown = ", ".join(repr(n) for n in names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


class write_failure:
    """Turn a write failure (a full disk, a read-only file system) into one line naming the store."""

    def __init__(self, where: str, run_name: str, outcome: str = "nothing was changed"):
        self.where, self.run_name, self.outcome = where, run_name, outcome

    def __enter__(self) -> None:
        return None

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            settle_zarr_writes()
        if exc_type is not None and issubclass(exc_type, OSError) and not isinstance(exc, SonarSetError):
            why = os_error_reason(first_os_error(exc))
            raise SonarSetError(f"{self.where}: cannot write run {self.run_name!r}: {why} ({self.outcome})") from None
        return False
