from __future__ import annotations

import os

# Each xdist worker gets its share of the cores. Torch's OpenMP pool defaults to every core, so
# two workers on two cores ran four spinning threads: the suite took 7 min 24 s on the 2-core Xeon
# VM, 5 min 38 s with one thread a worker. Set before anything here imports torch (a plugin may have
# imported numpy already, whose BLAS pool this does not reach); a value the caller chose wins, and
# subprocesses inherit it.
_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _workers > 1:
    _cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, _cores // _workers)))

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from sonarset.format.attrs import SensorGrid  # noqa: E402
from sonarset.store.store import create_store  # noqa: E402

TINY = SensorGrid(range_min_m=0.5, range_max_m=2.5, n_range=8, azimuth_min_rad=-1.2, azimuth_max_rad=1.2, n_azimuth=6)


def make_run(T: int, seed: int = 0, dtype: str = "float32", grid: SensorGrid = TINY) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "images": rng.random((T, *grid.shape)).astype(dtype),
        "velocity": np.c_[rng.uniform(-0.3, 0.3, T), rng.uniform(-1, 1, T)].astype(np.float32),
        "time": np.arange(T) * 0.2,
    }


@pytest.fixture
def grid() -> SensorGrid:
    return TINY


@pytest.fixture
def store(tmp_path):
    s = create_store(tmp_path / "s.zarr", TINY)
    s.write_run("run_000", **make_run(30, 0), chunk_frames=8)
    s.write_run("run_001", **make_run(25, 1), chunk_frames=8)
    s.write_run("test_000", **make_run(20, 2), split="test", chunk_frames=8)
    return s
