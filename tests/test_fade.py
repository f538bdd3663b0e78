"""The "no fade" check (issue 12): over 10-step rollouts the forecasts keep the targets' peak pixel
and echo energy (``models.evaluate.fade_summary``, the eval report's table and ``fade.png``)."""

import json
import math
from dataclasses import dataclass

import numpy as np
import pytest

from sonarset import open_store
from sonarset.models.eval.report import write_report
from sonarset.models.eval.evaluate import evaluate
from sonarset.models.eval.result import ECHO_FLOOR, FADE_TOLERANCE, EvalResult, fade_summary, peak_and_energy
from sonarset.format.attrs import SensorGrid
from sonarset.sim import generate
from sonarset.windows import N_IN

# The model's grid (as in test_echopt): 50 x 30 divides into the 25 x 5 patches.
TINY_GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                       azimuth_max_rad=math.pi / 2, n_azimuth=30)


@dataclass
class Fader:
    """Dims the last frame by 20% each step: the fade the check must catch."""

    grid: SensorGrid
    name: str = "fader"
    n_in: int = N_IN

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        return 0.8 * frames[:, -1]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A test run on the default 200 x 90 grid, ertis energyscapes (the defaults)."""
    path = tmp_path_factory.mktemp("fade") / "s.zarr"
    generate(path, runs=0, test_runs=1, minutes=0.5, seed=5, workers=1)
    return open_store(path)


@pytest.fixture(scope="module")
def result(store):
    return evaluate(store, ["persistence", "naive", "flow"], horizons=(1, 5, 10), samples=60, seed=1,
                    predictors={"fader": Fader(store.grid)}, ceiling=True)


def test_peak_and_energy():
    img = np.zeros((2, 4, 3), np.float32)
    img[0, 1, 1], img[0, 2, 2], img[0, 3, 0] = 0.9, 0.3, ECHO_FLOOR / 2  # the last is below the floor
    peak, energy = peak_and_energy(img)
    np.testing.assert_allclose(peak, [0.9, 0.0])
    np.testing.assert_allclose(energy, [1.2, 0.0], rtol=1e-6)


def test_ratio_of_means_leaves_out_windows_without_target_echo():
    N, H = 3, 2
    tp = np.array([[1.0, 1.0], [1.0, 0.0], [0.5, 1.0]])
    te = np.array([[10.0, 10.0], [10.0, 0.0], [5.0, 10.0]])  # window 1 has no echo at step 2
    pp = np.array([[1.0, 0.9], [1.0, 7.0], [0.5, 0.9]])
    pe = np.array([[9.0, 8.0], [9.0, 7.0], [4.5, 8.0]])
    res = EvalResult("s", "test", ["r"], [H], ["m", "ceiling"], np.arange(N), [("r", i) for i in range(N)], {},
                     step_peak={"m": pp}, step_energy={"m": pe}, target_peak=tp, target_energy=te)
    f = fade_summary(res)
    assert list(f) == ["m"]  # the noise ceiling has no entry
    np.testing.assert_allclose(f["m"]["peak_ratio"], [1.0, 0.9])  # window 1's 7.0 at step 2 is left out
    np.testing.assert_allclose(f["m"]["energy_ratio"], [22.5 / 25, 0.8])
    assert f["m"]["n_windows"] == [3, 2] and not f["m"]["within_15pct"] and f["m"]["first_out"] == 2
    assert fade_summary(res, tolerance=0.25)["m"]["within_15pct"]


def test_warping_baselines_keep_peak_and_energy(result):
    fade = fade_summary(result)
    assert set(fade) == {"fader", "persistence", "naive", "flow"}  # not the ceiling: no predictor
    for m, f in fade.items():
        assert len(f["peak_ratio"]) == len(f["energy_ratio"]) == 10
        assert np.all(np.isfinite(f["peak_ratio"])) and np.all(np.isfinite(f["energy_ratio"])), m
        assert f["n_windows"] == [60] * 10
    # persistence keeps every pixel; flow and naive move them, and sub-bin bilinear resampling
    # lowers peaks a little each step (more so on coarse grids), but not by 15% in 10 steps here
    for m in ("persistence", "flow", "naive"):
        assert fade[m]["within_15pct"] and fade[m]["first_out"] is None, (m, fade[m])
    np.testing.assert_allclose(fade["flow"]["peak_ratio"], 1.0, atol=0.1)
    # the scene's echo energy itself drifts over 10 frames; the warp keeps what copying keeps
    np.testing.assert_allclose(fade["flow"]["energy_ratio"], fade["persistence"]["energy_ratio"], atol=0.05)


def test_a_dimming_predictor_is_flagged_as_fading(result):
    f = fade_summary(result)["fader"]
    assert not f["within_15pct"] and f["first_out"] == 1
    np.testing.assert_allclose(f["peak_ratio"][:3], 0.8 ** np.arange(1, 4), rtol=0.03)
    np.testing.assert_allclose(f["energy_ratio"][0], 0.8, rtol=0.03)  # dimmed echoes stay above the floor
    assert f["energy_ratio"][4] < 0.5


def test_report_table_json_and_figure(result, tmp_path):
    write_report(result, tmp_path)
    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert set(doc["fade"]) == {"fader", "persistence", "naive", "flow"}
    assert doc["fade_definition"]["echo_floor"] == ECHO_FLOOR and doc["fade_definition"]["tolerance"] == FADE_TOLERANCE
    assert doc["fade_definition"]["steps"] == list(range(1, 11))
    for m, f in doc["fade"].items():
        assert all(isinstance(x, float) and math.isfinite(x) for x in f["peak_ratio"] + f["energy_ratio"]), m
    assert doc["fade"]["flow"]["within_15pct"] is True and doc["fade"]["fader"]["within_15pct"] is False
    report = (tmp_path / "report.md").read_text()
    section = report.split("## No fade", 1)[1].split("\n## ", 1)[0]
    assert "| fader |" in section and "fades from step 1" in section
    assert "| flow |" in section and "ceiling" not in section.split("| method |", 1)[1]
    assert (tmp_path / "fade.png").stat().st_size > 10_000 and "![fade](fade.png)" in report


def test_a_tiny_model_that_learned_a_moving_scene_does_not_fade(tmp_path):
    """A tiny EchoPT trained briefly on a simulated run (the robot moving through the lab) keeps its
    rollouts' peak and echo energy within 20% of the targets' over 10 steps. Measured on the dev VM:
    peak 1.00 -> 0.86, energy 1.00 -> 0.94 at step 10, so it meets the 15% criterion, but with too
    little margin to assert it across machines' floating point."""
    import torch

    from sonarset.models.echopt.train import train
    from sonarset.models.echopt.train_config import TrainConfig

    path = tmp_path / "tiny.zarr"
    generate(path, runs=3, test_runs=1, minutes=1.0, seed=3, workers=1, grid=TINY_GRID)
    store = open_store(path)
    torch.manual_seed(0)
    # weight_decay=0: Adam's L2 (coupled to the gradient) shrinks the layers behind the flow prior's
    # zero-initialised last convolution while their own gradients are still ~0, so with the default
    # 1e-4 these 300 steps learn nothing measurable (the model stays its prior, acoustic flow)
    cfg = TrainConfig(preset="tiny", batch_size=16, lr=1e-3, weight_decay=0.0, max_steps=300, eval_every=100,
                      n_val=50, device="cpu", test_samples=0, command="test")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a tiny model: one thread is as fast, and 10x faster when the CPUs are busy
    try:
        run = train(store, tmp_path / "run", cfg)
    finally:
        torch.set_num_threads(threads)
    first, last = run.history[0], run.history[-1]
    assert last["val_loss"] < first["val_loss"] and last["train_loss"] < first["train_loss"]  # it learned
    res = evaluate(store, ["persistence", "flow", f"echopt:{tmp_path / 'run' / 'model.safetensors'}"],
                   horizons=(1, 10), samples=80, seed=0)
    s = res.summary()
    assert s["echopt"]["1"]["cc"]["mean"] > s["persistence"]["1"]["cc"]["mean"] + 0.05  # it predicts the motion
    f = fade_summary(res)["echopt"]
    ratios = np.array(f["peak_ratio"] + f["energy_ratio"])
    assert np.all((ratios > 0.8) & (ratios < 1.2)), f
