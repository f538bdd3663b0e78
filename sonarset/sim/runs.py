"""Simulated runs: their plans (names, splits, seeds), the simulated robot's rig, and the
simulation of one run, block by block, into its own run group.

Each run has its own seed, spawned from the master seed with numpy's SeedSequence, and is
simulated start to finish by one worker that writes only its own run group. The arrays therefore
do not depend on the number of workers or on their scheduling.
"""

from __future__ import annotations

import concurrent.futures as cf
from dataclasses import asdict, dataclass, field
from typing import Iterator

import numpy as np

from sonarset.store.writer import DEFAULT_CHUNK_FRAMES
from sonarset.format.attrs import Processing, RobotRig, SensorGrid
from sonarset.store.store import open_store
from sonarset.version import __version__
from sonarset.sim.robot import SENSOR_OFFSET, V_MAX, W_MAX, WHEEL_BASE, ExplorationPolicy, apply_slip, integrate
from sonarset.sim.sonar import SonarModel
from sonarset.sim.spec import DT, GenerationSpec
from sonarset.sim.families import load_world



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
        return {"kind": "simulator", "simulator": f"sonarset {__version__}", **plan, **simulator_rig().provenance()}


def spawn_seeds(seed: int, n: int) -> list[int]:
    """``n`` independent seeds (non-negative int64) spawned from ``seed`` by NumPy's SeedSequence:
    one per run, trial or episode, so results do not depend on how tasks are scheduled."""
    return [int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1)) for ss in np.random.SeedSequence(seed).spawn(n)]


def world_seed(seed: int) -> int:
    """The seed of the world-family variant a run (or trial) seeded ``seed`` drives in: one rule for
    generated runs and the experiments, so a seed names the same world in both."""
    return seed % 1_000_003


def plan_runs(spec: GenerationSpec) -> list[RunPlan]:
    """The runs of a store: every world's training runs in the order given, then ``test_runs``
    test runs of each world. Run k's seed is the k-th spawned from ``seed``, so one world's plans
    do not depend on how the runs are scheduled."""
    mix = spec.world_mix()
    n_train = sum(n for _, n in mix)
    worlds = [w for w, n in mix for _ in range(n)] + [w for w, _ in mix for _ in range(spec.test_runs)]
    plans = []
    for k, (s, w) in enumerate(zip(spawn_seeds(spec.seed, len(worlds)), worlds)):
        name, split = (f"run_{k:03d}", "train") if k < n_train else (f"test_{k - n_train:03d}", "test")
        # Every run gets its own variant of a world family; a world file is the same for all.
        plans.append(RunPlan(name, split, s, w, world_seed(s), spec.n_frames, float(spec.snr_db), spec.psf,
                             spec.processing))
    return plans


@dataclass(frozen=True)
class RunTarget:
    """Where a generation task writes its run: the store at ``location`` (a path or fsspec URL,
    opened with ``storage_options``) and its grid. A process pool or a Dask cluster ships it to
    every task."""

    location: str
    grid: SensorGrid
    storage_options: dict | None = None


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


def write_run(target: RunTarget, plan: RunPlan, queue=None, spare_core=None) -> str:
    """Simulate ``plan`` into its run group of the store ``target``: one task of a local pool or of
    a Dask cluster. ``queue`` receives (run name, frames) as blocks are written."""
    store = open_store(target.location, "r+", storage_options=target.storage_options)
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
        for start, arrays in simulate_blocks(plan, target.grid, spare_core=spare_core):
            if pending is not None:
                pending.result()
            pending = writer.submit(w.write, start, **arrays)
            if queue is not None:
                queue.put((plan.name, len(arrays["time"])))
        if pending is not None:
            pending.result()
        w.commit()
    return plan.name
