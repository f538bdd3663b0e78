"""The note on undefined metrics blames the model, not the target, when the prediction is NaN."""

from __future__ import annotations

import numpy as np

from sonarset.models.eval.result import METRICS, EvalResult, undefined_notes


def result(peak_bad: np.ndarray, target_zero: np.ndarray) -> EvalResult:
    n = len(peak_bad)
    good = {k: np.where(target_zero, np.nan, 0.5) for k in METRICS}
    bad = {k: np.where(peak_bad | target_zero, np.nan, 0.5) for k in METRICS}
    return EvalResult(store="s", split="test", runs=["r"], horizons=[1], methods=["naive", "nan_model"],
                      window_starts=np.arange(n), window_ids=[("r", i) for i in range(n)],
                      per_window={"naive": {1: good}, "nan_model": {1: bad}},
                      step_peak={"naive": np.full((n, 1), 0.8), "nan_model": np.where(peak_bad, np.nan, 0.8)[:, None]})


def test_a_nan_prediction_is_named_and_not_called_an_all_zero_target():
    notes = undefined_notes(result(np.array([True, True, False, False]), np.zeros(4, bool)))
    assert len(notes) == 1 and "prediction is NaN" in notes[0] and "nan_model 2 of 4 windows" in notes[0], notes
    assert not any("all zero" in note for note in notes)


def test_an_all_zero_target_keeps_its_note():
    notes = undefined_notes(result(np.array([True, False, False, False]), np.array([False, False, False, True])))
    assert any("prediction is NaN" in note and "nan_model 1 of 4" in note for note in notes), notes
    assert any("all zero" in note and "1 of 4 windows" in note for note in notes), notes


def test_evaluating_a_model_that_outputs_nan_says_so(tmp_path):
    import math

    from sonarset import open_store
    from sonarset.format.attrs import SensorGrid
    from sonarset.models.eval.evaluate import evaluate
    from sonarset.sim import generate

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=40, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=18)
    generate(tmp_path / "s.zarr", runs=0, test_runs=1, minutes=0.2, seed=1, grid=grid, workers=1)

    class NaNModel:
        name, n_in = "nan_model", 3

        def predict(self, frames, commands):
            return np.full((frames.shape[0], *frames.shape[2:]), np.nan, np.float32)

    res = evaluate(open_store(tmp_path / "s.zarr"), ["naive"], horizons=(1,), samples=6,
                   predictors={"nan_model": NaNModel()})
    assert any("prediction is NaN" in n and "nan_model 6 of 6 windows" in n for n in res.notes), res.notes
    assert not any("all zero" in n for n in res.notes), res.notes
