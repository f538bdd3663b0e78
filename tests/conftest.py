from __future__ import annotations

import numpy as np
import pytest

from sonarset.format.attrs import SensorGrid
from sonarset.store.store import create_store

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
