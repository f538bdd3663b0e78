"""Generate SonarSet stores of simulated runs: parallel, deterministic, resumable.

Each run has its own seed, spawned from the master seed with numpy's SeedSequence, and is
simulated start to finish by one worker that writes only its own run group. The arrays therefore
do not depend on the number of workers or on their scheduling. Re-running the same command keeps
every complete run (the plan recorded in its ``source`` must match) and redoes the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import errno
import multiprocessing as mp
import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .. import __version__
from ..errors import SonarSetError
from ..atomic import aside_dir, remove_stale_asides, settle_zarr_writes
from ..perf import keep_freed_memory
from ..schema import Processing, RobotRig, SensorGrid
from ..runwriter import DEFAULT_CHUNK_FRAMES
from ..store import create_store, open_or_create_store, open_store
from ..zarrio import is_url
from .robot import SENSOR_OFFSET, V_MAX, W_MAX, WHEEL_BASE, ExplorationPolicy, apply_slip, integrate
from .sonar import SonarModel, check_psf
from .world import load_world

DT = 0.2  # s, 5 Hz frames


def simulator_rig() -> RobotRig:
    """The simulated robot's geometry, as stores record it."""
    return RobotRig(frame_interval_s=DT, sensor_offset_m=SENSOR_OFFSET, wheel_base_m=WHEEL_BASE,
                    v_max_m_s=V_MAX, omega_max_rad_s=W_MAX)


@dataclass(frozen=True)
class RunPlan:
    name: str
    split: str
    seed: int  # the run's own seed (from SeedSequence.spawn of the master seed)
    world: str
    world_seed: int
    n_frames: int
    snr_db: float
    psf: str = "array"
    processing: Processing = field(default_factory=Processing.ertis)  # the store records it in full

    def source(self) -> dict:
        plan = {**asdict(self), "processing": self.processing.profile}
        return {"kind": "simulator", "simulator": f"sonarset {__version__}", **plan, "dt": DT,
                "sensor_offset_m": SENSOR_OFFSET, "wheel_base_m": WHEEL_BASE}


def spawn_seeds(seed: int, n: int) -> list[int]:
    """``n`` independent seeds (non-negative int64) spawned from ``seed`` by NumPy's SeedSequence:
    one per run, trial or episode, so results do not depend on how tasks are scheduled."""
    return [int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1)) for ss in np.random.SeedSequence(seed).spawn(n)]


def plan_runs(runs: int = 10, test_runs: int = 1, minutes: float = 25.0, seed: int = 0,
              world: str = "lab", snr_db: float = 5.0, psf: str = "array",
              processing: Processing | None = None) -> list[RunPlan]:
    n_frames = int(round(minutes * 60 / DT))
    if n_frames < 1:
        raise SonarSetError(f"--minutes {minutes} gives no frames at 5 Hz")
    if runs < 0 or test_runs < 0 or runs + test_runs < 1:
        raise SonarSetError("need at least one run")
    plans = []
    for k, s in enumerate(spawn_seeds(seed, runs + test_runs)):
        name, split = (f"run_{k:03d}", "train") if k < runs else (f"test_{k - runs:03d}", "test")
        # Every run gets its own variant of a procedural world; a fixed world is the same for all.
        plans.append(RunPlan(name, split, s, world, s % 1_000_003, n_frames, float(snr_db), psf,
                             processing or Processing.ertis()))
    return plans


def simulate_blocks(plan: RunPlan, grid: SensorGrid, block: int = DEFAULT_CHUNK_FRAMES,
                    spare_core=None) -> Iterator[tuple[int, dict]]:
    """(start, arrays) blocks of a run, in order; velocity[k] is the command that moved the robot
    into frame k.

    The policy sees the world, not the images, so each block's trajectory is driven first and its
    frames are rendered as one batch. Each block draws its sensor noise from its own seed (the
    run's noise seed spawned by block index): any block can be rendered on its own, in any order.
    While ``spare_core`` (an event) is set, two blocks are rendered at a time, one in a helper
    thread: a pool's last runs then use the cores that runs already finished have freed.
    """
    world = load_world(plan.world, plan.world_seed)
    motion_ss, noise_ss = np.random.SeedSequence(plan.seed).spawn(2)
    motion_rng = np.random.default_rng(motion_ss)
    policy = ExplorationPolicy(world, motion_rng, dt=DT)
    model = SonarModel(grid, snr_db=plan.snr_db, psf=plan.psf, processing=plan.processing)
    pose = world.sample_spawn(motion_rng)
    R, A = grid.shape

    def drive(start: int) -> dict:
        nonlocal pose
        n = min(block, plan.n_frames - start)
        out = {"images": np.empty((n, R, A), np.float16), "velocity": np.empty((n, 2), np.float32),
               "time": (start + np.arange(n)) * DT, "pose": np.empty((n, 3)),
               "snr_db": np.full(n, plan.snr_db, np.float32), "slip": np.ones((n, 2), np.float32)}
        for j in range(n):
            v, w = policy(pose)
            pose = integrate(pose, *apply_slip(v, w, (1.0, 1.0)), DT)
            out["velocity"][j] = (v, w)
            out["pose"][j] = pose
        return out

    def render(start: int, out: dict) -> tuple[int, dict]:
        # SFC64: the noise needs 36,000 normals a frame, the largest single cost of a frame, and
        # it draws them ~10% faster than the default PCG64.
        noise_rng = np.random.Generator(np.random.SFC64(
            np.random.SeedSequence(noise_ss.entropy, spawn_key=(*noise_ss.spawn_key, start // block))))
        out["snr_db"][:] = model.render_batch(world, out["pose"], noise_rng, out=out["images"])[1]
        return start, out

    starts = iter(range(0, plan.n_frames, block))
    with cf.ThreadPoolExecutor(1) as helper:
        for start in starts:
            out = drive(start)
            nxt = next(starts, None) if spare_core is not None and spare_core.is_set() else None
            if nxt is None:
                yield render(start, out)
                continue
            later = helper.submit(render, nxt, drive(nxt))  # the heavy parts release the GIL
            yield render(start, out)
            yield later.result()


def _write_run(location: str, plan: RunPlan, grid: SensorGrid, queue=None, storage_options: dict | None = None,
               spare_core=None) -> str:
    store = open_store(location, "r+", storage_options=storage_options)
    # Whatever a killed writer left of this run goes, including a group folder whose zarr.json was
    # never renamed into place (zarr does not see it as a node, so the writer would not replace it)
    # and the zarr.<id>.partial temp files of its last writes.
    from zarr.core.sync import sync

    sync(store.group.store.delete_dir(plan.name))
    with store.run_writer(plan.name, plan.n_frames, split=plan.split, source=plan.source(),
                          optional=("pose", "snr_db", "slip"), consolidate=False) as w, \
            cf.ThreadPoolExecutor(1) as writer:
        # Block k is compressed and written (GIL released) while block k+1 is simulated.
        pending = None
        for start, arrays in simulate_blocks(plan, grid, spare_core=spare_core):
            if pending is not None:
                pending.result()
            pending = writer.submit(w.write, start, **arrays)
            if queue is not None:
                queue.put((plan.name, len(arrays["time"])))
        if pending is not None:
            pending.result()
        w.commit()
    return plan.name


def generate(
    out: str | os.PathLike,
    *,
    runs: int = 10,
    test_runs: int = 1,
    minutes: float = 25.0,
    seed: int = 0,
    world: str = "lab",
    snr_db: float = 5.0,
    psf: str = "array",
    processing: Processing | str = "ertis",
    workers: int | None = None,
    grid: SensorGrid | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    scheduler=None,
    storage_options: dict | None = None,
) -> list[str]:
    """Simulate the runs into the store ``out`` (a path or any fsspec URL); returns the names of the
    runs written now.

    Runs go to a local process pool, or, with ``scheduler``, to a Dask distributed cluster: an
    address (``tcp://host:8786``), ``"local"`` for a ``LocalCluster`` of ``workers`` processes, or a
    ``distributed.Client``. Each task writes its own run group to ``out``, which every worker must
    reach (a shared file system or object storage). The arrays are the same either way.

    ``processing`` is a profile name (``ertis``, the default, or ``raw``) or ``Processing`` settings;
    the store records it, with the robot's rig, in its attributes.
    """
    grid = grid or SensorGrid.default()
    load_world(world, 0)  # fail fast on a bad world name or file, before any process starts
    if isinstance(processing, str):
        try:
            processing = Processing.named(processing)
        except ValueError as exc:
            raise SonarSetError(f"--processing: {exc}") from None
    try:
        check_psf(psf, processing)
    except ValueError as exc:
        raise SonarSetError(f"--psf: {exc}") from None
    plans = plan_runs(runs, test_runs, minutes, seed, world, snr_db, psf, processing)
    loc = os.fspath(out).removeprefix("file://")  # a local path: the store is created aside and renamed
    if not is_url(loc):
        _prepare_local(Path(loc), grid, processing, [p.name for p in plans])
    store = open_or_create_store(loc, grid, description=f"simulated by sonarset {__version__}",
                                 storage_options=storage_options, processing=processing, rig=simulator_rig())
    todo = []
    for plan in plans:
        if plan.name in store.runs():
            have = {"processing": "raw", **store.run(plan.name).attrs.source}  # 1.0 runs were raw
            if {k: have.get(k) for k in plan.source()} != plan.source():
                raise SonarSetError(f"{loc}: run {plan.name} was generated with other settings; "
                                    "use a new output or the same options")
            continue
        todo.append(plan)
    try:
        _simulate_into(store, loc, todo, grid, workers, progress, scheduler, storage_options)
    except OSError as exc:
        settle_zarr_writes()
        while isinstance(exc.__context__, OSError):  # the run writer's clean-up failed too: report the cause
            exc = exc.__context__
        why = "no space left on device" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
        raise SonarSetError(f"{loc}: cannot write {exc.filename or 'the store'}: {why} (complete runs are kept; "
                            "re-run the same command to resume)") from None
    return [p.name for p in todo]


def _simulate_into(store, loc: str, todo: list[RunPlan], grid: SensorGrid, workers: int | None, progress,
                   scheduler, storage_options: dict | None) -> None:
    total = {p.name: p.n_frames for p in todo}
    if todo and scheduler is not None:
        from .distributed import run_on_dask

        run_on_dask(scheduler, loc, todo, grid, workers, storage_options, progress, store)
    elif todo:
        workers = max(1, min(workers or os.cpu_count() or 1, len(todo)))
        if workers == 1:
            for plan in todo:
                _write_run(loc, plan, grid, _Direct(progress, total), storage_options)
                store.consolidate()
        else:
            ctx = mp.get_context("spawn")  # no fork: zarr's event loop thread must not be copied
            # One BLAS/OpenMP thread per worker: the workers already fill the cores.
            saved = {k: os.environ.get(k) for k in _THREAD_VARS}
            os.environ.update({k: "1" for k in _THREAD_VARS if k not in os.environ})
            try:
                _run_pool(ctx, loc, todo, grid, workers, total, progress, store, storage_options)
            finally:
                for k, v in saved.items():
                    if v is None:
                        os.environ.pop(k, None)
    store.consolidate()


def _prepare_local(dest: Path, grid: SensorGrid, processing: Processing, runs: list[str]) -> None:
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
        create_store(tmp / "store.zarr", grid, description=f"simulated by sonarset {__version__}",
                     processing=processing, rig=simulator_rig())
        try:
            os.replace(tmp / "store.zarr", dest)  # onto nothing or an empty directory
        except OSError:
            if not (dest / "zarr.json").exists():  # else another process created it first
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _run_pool(ctx, loc: str, todo: list[RunPlan], grid: SensorGrid, workers: int, total: dict,
              progress, store, storage_options: dict | None = None) -> None:
    """One task per run in a process pool; progress arrives through a managed queue."""
    with ctx.Manager() as manager:
        queue = manager.Queue()
        spare = manager.Event()  # set once fewer runs remain than workers: a core is free
        with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=keep_freed_memory) as pool:
            pending = {pool.submit(_write_run, loc, p, grid, queue, storage_options, spare) for p in todo}
            done = {p.name: 0 for p in todo}
            while pending:
                if len(pending) < workers:
                    spare.set()
                finished, pending = cf.wait(pending, timeout=0.2)
                while not queue.empty():
                    name, n = queue.get()
                    done[name] += n
                    if progress:
                        progress(name, done[name], total[name])
                for f in finished:
                    f.result()  # re-raise a worker's error here
                if finished:
                    # Only this process writes root metadata; zarr writes it atomically.
                    store.consolidate()


class _Direct:
    """Queue stand-in for the single-process path: reports progress straight away."""

    def __init__(self, progress, total):
        self.progress, self.total, self.done = progress, total, {}

    def put(self, item) -> None:
        name, n = item
        self.done[name] = self.done.get(name, 0) + n
        if self.progress:
            self.progress(name, self.done[name], self.total[name])
