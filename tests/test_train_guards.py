"""train's run directory: one training at a time (a lock), and a full disk as one line that keeps
the previous checkpoint."""

from __future__ import annotations

import errno
import fcntl
import math
import os

import pytest

from sonarset import SonarSetError, open_store
from sonarset.format.attrs import SensorGrid
from sonarset.models.echopt.train import train
from sonarset.models.echopt.train_config import TrainConfig
from sonarset.sim import generate

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("guards") / "s.zarr"
    generate(path, runs=1, test_runs=0, minutes=0.3, seed=3, workers=1, grid=GRID)
    return open_store(path)


def cfg(**kw):
    return TrainConfig(**{**dict(preset="tiny", epochs=1, batch_size=8, lr=1e-3, n_val=8, eval_every=2,
                                 device="cpu", test_samples=0, command="test"), **kw})


def test_a_second_training_in_a_locked_run_is_refused_naming_the_holder(store, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    held = os.open(out / ".lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
    os.write(held, b"4242\n")
    try:
        with pytest.raises(SonarSetError, match=r"run: another training is running in it \(pid 4242\)"):
            train(store, out, cfg(max_steps=2), resume=True)
    finally:
        os.close(held)
    assert train(store, out, cfg(max_steps=2), resume=True).steps == 2  # the lock gone, it runs
    assert train(store, out, cfg(max_steps=2), resume=True).steps == 2  # and its own lock was released


def test_a_full_disk_while_saving_is_one_line_and_keeps_the_previous_checkpoint(store, tmp_path, monkeypatch):
    import sonarset.models.echopt.checkpoint as checkpoint
    import sonarset.models.echopt.train_state as train_state

    out = tmp_path / "run"
    assert train(store, out, cfg(max_steps=4, max_minutes=1e-9)).steps == 1  # stops at once, saved
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(checkpoint, "save_file", full_disk)
    monkeypatch.setattr(train_state, "save_file", full_disk)
    with pytest.raises(SonarSetError, match=r"(model|state)\.safetensors: cannot write the (checkpoint|training "
                                            r"state): no space left on the device") as refused:
        train(store, out, cfg(max_steps=4), resume=True)
    assert "\n" not in str(refused.value)
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert after == before  # nothing half-written, nothing lost, no temporary file left
