"""The scoring machinery of an evaluation: every predictor rolled out over the windows batch by batch
and scored at every horizon (:class:`Scores`), and the two ceilings re-rendered beside them
(:func:`score_ceilings`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from sonarset.scoring.ceiling import CEILING, CEILINGS, OBSERVABLE
from sonarset.scoring.echoes import EchoMatching, echo_scores, find_echoes
from sonarset.scoring.metrics import cc_and_nrmsd
from sonarset.store.store import SonarStore
from sonarset.windows import FrameBank, WindowBatcher, WindowIndex

from sonarset.models.predictor import CheckedPredictor
from sonarset.models.eval.result import METRICS, peak_and_energy


@dataclass
class Scores:
    """Per-window scores of the predicting methods, filled batch by batch (N windows, H steps)."""

    per_window: dict[str, dict[int, dict[str, np.ndarray]]]  # method -> horizon -> metric -> (N,)
    seconds: dict[str, float]
    step_peak: dict[str, np.ndarray]  # method -> (N, H); a direct forecaster's at the scored horizons, NaN between
    step_energy: dict[str, np.ndarray]
    target_peak: np.ndarray  # (N, H)
    target_energy: np.ndarray
    grid: object  # SensorGrid: echo positions in metres and degrees
    matching: EchoMatching
    outside_unit: dict[str, int] = field(default_factory=dict)  # method -> forecast images with a pixel outside [0, 1]

    @classmethod
    def of(cls, preds: dict[str, CheckedPredictor], n: int, horizons: tuple[int, ...], grid,
           matching: EchoMatching) -> "Scores":
        H = horizons[-1]
        return cls({m: {h: {k: np.empty(n) for k in METRICS} for h in horizons} for m in preds},
                   dict.fromkeys(preds, 0.0), {m: np.full((n, H), np.nan) for m in preds},
                   {m: np.full((n, H), np.nan) for m in preds}, np.empty((n, H)), np.empty((n, H)), grid, matching)

    def roll_out(self, batcher: WindowBatcher, index: WindowIndex, preds: dict[str, CheckedPredictor], batch_size: int,
                 progress: Callable[[str, int, int], None] | None) -> dict:
        """Forecast every window's scored horizons by every method (a checked predictor,
        models/predictor.py), batch by batch, and score them; returns the first window's frames,
        targets and predictions at every step (the figures' example). A method that forecasts each
        horizon directly (``forecast_at``) computes the scored horizons alone; any other is rolled
        out step by step to the longest."""
        H = index.horizon
        horizons = tuple(next(iter(self.per_window.values())))
        steps = [h - 1 for h in horizons]
        examples: dict = {"methods": {}}
        for lo in range(0, len(index), batch_size):
            sl = slice(lo, min(len(index), lo + batch_size))
            batch = batcher.gather(index, np.arange(sl.start, sl.stop))  # once for every method
            if lo == 0:
                # copies: a view would pin the whole first batch for the rest of the evaluation
                examples["frames"], examples["targets"] = batch.frames[0].copy(), batch.targets[0].copy()
            self.target_peak[sl], self.target_energy[sl] = peak_and_energy(batch.targets[:, :H])
            target_echoes = {h: find_echoes(batch.targets[:, h - 1], self.grid, self.matching) for h in horizons}
            for name, predictor in preds.items():
                t0 = time.perf_counter()
                if predictor.forecasts_directly:
                    pred = predictor.forecast_at(batch.frames, batch.commands, horizons)
                    self.seconds[name] += time.perf_counter() - t0  # the prediction's time, not the scoring's
                    self.step_peak[name][sl, steps], self.step_energy[name][sl, steps] = peak_and_energy(pred)
                    if lo == 0:
                        examples["methods"][name] = predictor.rollout(batch.frames[:1], batch.commands[:1], H)[0]
                else:
                    rolled = predictor.rollout(batch.frames, batch.commands, H)
                    self.seconds[name] += time.perf_counter() - t0
                    pred = rolled[:, steps]
                    self.step_peak[name][sl], self.step_energy[name][sl] = peak_and_energy(rolled)
                    if lo == 0:
                        examples["methods"][name] = rolled[0].copy()  # not a view of the whole batch's rollout
                self.outside_unit[name] = self.outside_unit.get(name, 0) + int(((pred < 0) | (pred > 1)).any((-2, -1)).sum())
                for i, (h, metrics) in enumerate(self.per_window[name].items()):
                    for k, v in score_images(pred[:, i], batch.targets[:, h - 1], self.grid, self.matching,
                                             target_echoes[h]).items():
                        metrics[k][sl] = v
                if progress:
                    progress(name, sl.stop, len(index))
        return examples


def score_images(pred: np.ndarray, target: np.ndarray, grid, matching: EchoMatching,
                 target_echoes=None) -> dict[str, np.ndarray]:
    """{metric in METRICS: (N,) per-image values} of predictions against targets, both (N, R, A)."""
    cc, nrmsd = cc_and_nrmsd(pred, target)
    return {"cc": cc, "nrmsd": nrmsd, **echo_scores(pred, target, grid, matching, target_echoes)}


def score_ceilings(store: SonarStore, bank: FrameBank, index: WindowIndex, ids: list[tuple[str, int]],
                   horizons: tuple[int, ...], seed: int, batch_size: int, matching: EchoMatching, progress=None):
    """({"ceiling": scores, "observable": scores}, {name: seconds}) of the two ceilings (per-window
    scores, NaN for windows of runs they cannot re-render), or (None, None) when no run can be
    re-rendered; the third item is {run: reason} for the runs skipped.

    At horizon h, window w's target is frame k_w + n_in + h - 1 of its run. The noise ceiling
    renders each such frame once, in batches; the observable ceiling renders each window's targets
    from the reflectors its own context frames k_w .. k_w + n_in - 1 heard.
    """
    from sonarset.scoring.ceiling import OBSERVABLE_STREAM, CeilingUnavailable, RunRenderer

    n_in = index.n_in
    run_of = np.array([r for r, _ in ids])
    first = np.array([k for _, k in ids], np.int64)
    hs = np.asarray(horizons, np.int64)
    skipped: dict[str, str] = {}
    todo = []
    for name in bank.run_names:
        try:
            r = RunRenderer(store, name, seed)
            todo.append((r, r.with_stream(OBSERVABLE_STREAM)))
        except CeilingUnavailable as exc:
            skipped[name] = str(exc)
    if not todo:
        return None, None, skipped
    scores = {m: {h: {k: np.full(len(ids), np.nan) for k in METRICS} for h in horizons} for m in CEILINGS}
    seconds = dict.fromkeys(CEILINGS, 0.0)

    def put(method: str, w: np.ndarray, h: np.ndarray, pred: np.ndarray) -> None:
        target = bank.images[index.starts[w] + n_in + h - 1]
        for k, vals in score_images(pred, target, store.grid, matching).items():
            for hz in horizons:
                scores[method][hz][k][w[h == hz]] = vals[h == hz]

    windows = sum(int((run_of == r.name).sum()) for r, _ in todo)
    total, done = 0, 0
    plans = []
    for r, obs in todo:
        w = np.flatnonzero(run_of == r.name)
        # (window, horizon) pairs of this run and their target frames, each frame rendered once
        ww, hh = np.repeat(w, len(hs)), np.tile(hs, len(w))
        frames, which = np.unique(first[ww] + n_in + hh - 1, return_inverse=True)
        plans.append((r, obs, w, ww, hh, frames, which))
        total += len(frames)
    total += windows
    step = max(1, batch_size)
    for r, obs, w_run, ww, hh, frames, which in plans:
        t0 = time.perf_counter()
        for lo in range(0, len(frames), step):
            hi = min(len(frames), lo + step)
            images = r.render(frames[lo:hi])
            sel = np.flatnonzero((which >= lo) & (which < hi))
            put(CEILING, ww[sel], hh[sel], images[which[sel] - lo])
            done += hi - lo
            if progress:
                progress(CEILING, done, total)
        t1 = time.perf_counter()
        seconds[CEILING] += t1 - t0
        for lo in range(0, len(w_run), step):
            chunk = w_run[lo:lo + step]
            pred = np.concatenate([obs.render_observed(first[w] + np.arange(n_in), first[w] + n_in + hs - 1)
                                   for w in chunk])
            put(OBSERVABLE, np.repeat(chunk, len(hs)), np.tile(hs, len(chunk)), pred)
            done += len(chunk)
            if progress:
                progress(CEILING, done, total)
        seconds[OBSERVABLE] += time.perf_counter() - t1
    return scores, seconds, skipped
