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


def test_a_loss_that_is_no_number_stops_training_in_one_line_keeping_the_last_good_weights(store, tmp_path,
                                                                                          monkeypatch):

    import sonarset.models.echopt.train as train_module

    out = tmp_path / "run"
    step = train_module._Run.optimizer_step

    def diverging(self, i, windows, k):
        loss = step(self, i, windows, k)
        return loss if i < 2 else loss * float("nan")  # as bf16 on a too narrow U-Net level did

    monkeypatch.setattr(train_module._Run, "optimizer_step", diverging)
    with pytest.raises(SonarSetError, match=r"^step 3: the training loss is nan \(not finite\); the weights kept, if any, "
                                            r"are those of the best validation before it; try .*a lower lr$"):
        train(store, out, cfg(max_steps=6))
    assert (out / "model.safetensors").is_file()  # step 2's validation


def test_too_few_windows_for_the_validation_set_names_the_store(store, tmp_path):
    with pytest.raises(SonarSetError, match=r"s\.zarr: its training runs hold \d+ windows, too few to hold out "
                                            r"n_val 100000 for validation") as refused:
        train(store, tmp_path / "run", cfg(n_val=100000))
    assert refused.value.parameter == "n_val"


def test_a_store_without_a_rig_trains_at_its_own_frame_rate(tmp_path):
    """Not at the simulator's 0.2 s frames and sensor offset: one step is one of the store's frames,
    and the sensor is where eval's baselines put it, or, for a fine-tune, where the model had it."""
    import numpy as np

    from sonarset.models.echopt.train_model import build_model
    from sonarset.store.store import create_store

    s = create_store(tmp_path / "rigless.zarr", GRID, frame_rate_hz=10.0)
    rng = np.random.default_rng(0)
    T = 60
    s.write_run("train_000", images=rng.random((T, *GRID.shape)).astype("float32"),
                velocity=np.c_[rng.uniform(0, 0.3, T), rng.uniform(-1, 1, T)].astype("float32"),
                time=np.arange(T) * 0.1, split="train")
    assert s.rig is None
    model, _ = build_model(s, cfg(model="echowarp"), "cpu")
    assert (model.cfg.dt, model.cfg.sensor_offset) == (0.1, 0.0)
    # a run begun when such a store made the simulator's robot is not resumed as another model
    import json

    out = tmp_path / "run"
    train(s, out, cfg(model="echowarp", max_steps=2))
    card = json.loads((out / "model.json").read_text())
    card["config"]["dt"] = 0.2
    (out / "model.json").write_text(json.dumps(card))
    with pytest.raises(SonarSetError, match=r"run: the run's model has dt 0\.2, this store makes 0\.1; start a new run"):
        train(s, out, cfg(model="echowarp", max_steps=2), resume=True)


def test_a_fine_tune_takes_grid_edges_equal_to_float32s_rounding(store):
    """A store imported from a bag has its edges as float32 bin centres made them: the same grid."""
    from types import SimpleNamespace

    from sonarset.models.echopt.networks import build
    from sonarset.models.echopt.train_model import init_from

    edges = dict(range_edges=(0.5, 5.0), azimuth_edges=(-math.pi / 2, math.pi / 2))
    trained = build("echowarp", "tiny", *GRID.shape, **edges)
    near = build("echowarp", "tiny", *GRID.shape, range_edges=(0.500000019169333, 4.999999980830667),
                 azimuth_edges=(-1.5707963267948968, 1.5707963267948968))
    card = {"processing": store.processing.model_dump(mode="json")}
    init_from(near, "pretrained", trained, card, SimpleNamespace(processing=store.processing, location="bag.zarr"))
    far = build("echowarp", "tiny", *GRID.shape, range_edges=(0.5, 5.01), azimuth_edges=edges["azimuth_edges"])
    with pytest.raises(SonarSetError, match=r"range_edges: \(0\.5, 5\.0\) vs \(0\.5, 5\.01\)"):
        init_from(far, "pretrained", trained, card, SimpleNamespace(processing=store.processing, location="bag.zarr"))
