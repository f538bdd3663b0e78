"""The evaluation engine: every method on the same seeded windows, the paper's metrics, statistics.

``evaluate`` is the library API behind ``sonarset eval``; it returns an :class:`EvalResult`, which
``models.eval_report`` renders (metrics.json, per_window.csv, report.md and the figures).
``fade_summary`` is the "no fade" check: whether the rollouts keep the targets' peak pixel and echo
energy at every step.
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import time
from dataclasses import dataclass, field
from itertools import combinations
from typing import Callable

import numpy as np

from sonarset.format.arrays import FRAME_INTERVAL_TOLERANCE
from sonarset.scoring.ceiling import CEILING, CEILINGS, OBSERVABLE
from sonarset.scoring.echoes import ECHO_METRICS, EchoMatching, echo_scores, find_echoes
from sonarset.errors import FormatError, SonarSetError
from sonarset.scoring.metrics import cc_and_nrmsd
from sonarset.report.numbers import horizon_name
from sonarset.format.attrs import RobotRig
from sonarset.scoring.stats import Comparison, compare, holm
from sonarset.store.store import SonarStore
from sonarset.windows import N_IN, FrameBank, WindowBatcher, WindowIndex

from sonarset.models.baselines import Predictor, rollout

IMAGE_METRICS = ("cc", "nrmsd")  # the paper's
#: Every per-window metric: the paper's, then the echo metrics (sonarset/echoes.py).
METRICS = IMAGE_METRICS + ECHO_METRICS
#: Echo energy counts the pixels above this value (images are in [0, 1]): what is left of an
#: echo, not the faint interpolation haze or residual noise a rollout can smear over the image.
ECHO_FLOOR = 0.05
#: "No fade": the mean prediction / target ratios of peak pixel and echo energy stay within this
#: fraction of 1 at every rollout step.
FADE_TOLERANCE = 0.15


@dataclass
class EvalResult:
    store: str
    split: str
    runs: list[str]
    horizons: list[int]
    methods: list[str]
    window_starts: np.ndarray  # (N,) global start frames in the bank
    window_ids: list[tuple[str, int]]  # (run, frame index) of each window
    per_window: dict[str, dict[int, dict[str, np.ndarray]]]  # method -> H -> metric -> (N,)
    comparisons: list[Comparison] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    examples: dict = field(default_factory=dict)  # data for the figures
    notes: list[str] = field(default_factory=list)  # one line each: what makes scores less comparable
    # ceiling=True: run -> one-line reason, for each run of the split it could not re-render
    ceiling_skipped: dict[str, str] = field(default_factory=dict)
    # the "no fade" data, at every rollout step 1..max(horizons), per window: (N, max horizon)
    # arrays of the peak pixel and the echo energy, per predicting method and for the targets
    step_peak: dict[str, np.ndarray] = field(default_factory=dict)
    step_energy: dict[str, np.ndarray] = field(default_factory=dict)
    target_peak: np.ndarray | None = None
    target_energy: np.ndarray | None = None
    n_in: int = N_IN  # input frames per window
    precision: dict[str, str] = field(default_factory=dict)  # learned method -> fp32 | bf16, as it ran
    echo_matching: EchoMatching = field(default_factory=EchoMatching)
    worlds: list[str] | None = None  # the world families the runs were restricted to

    @property
    def predictors(self) -> list[str]:
        """The methods that predict: every method but the noise ceiling."""
        return [m for m in self.methods if m not in CEILINGS]

    def gap_closed(self, reference: str = "flow", metrics: tuple[str, ...] = ("cc", "nrmsd", "echo_f1")) -> dict:
        """{method: {horizon: {metric: share}}}: the share of the gap between ``reference`` and the
        observable ceiling that each other predictor closes, (m - ref) / (observable - ref) on the
        means over the windows where all three are defined (1: as good as the context allows;
        0: no better than the reference). Empty without the observable ceiling or the reference."""
        if OBSERVABLE not in self.methods or reference not in self.methods:
            return {}
        out: dict = {}
        for m in self.predictors:
            if m == reference:
                continue
            for h in self.horizons:
                for k in metrics:
                    a, r, o = (self.per_window[x][h][k] for x in (m, reference, OBSERVABLE))
                    ok = np.isfinite(a) & np.isfinite(r) & np.isfinite(o)
                    gap = float(o[ok].mean() - r[ok].mean()) if ok.any() else float("nan")
                    share = float(a[ok].mean() - r[ok].mean()) / gap if ok.any() and abs(gap) > 1e-12 else None
                    out.setdefault(m, {}).setdefault(str(h), {})[k] = share
        return out

    def summary(self) -> dict:
        out: dict = {}
        for m in self.methods:
            out[m] = {}
            for h in self.horizons:
                entry = {}
                for k in METRICS:
                    x = self.per_window[m][h][k]
                    x = x[np.isfinite(x)]  # undefined windows: counted in the notes, never silently
                    entry[k] = ({"mean": float(x.mean()), "std": float(x.std(ddof=1)) if len(x) > 1 else 0.0}
                                if len(x) else {"mean": None, "std": None})
                    if k in ECHO_METRICS:  # defined for only some windows (module sonarset.scoring.echoes)
                        entry[k]["n"] = int(len(x))
                entry["n"] = int(np.isfinite(self.per_window[m][h]["cc"]).sum())
                out[m][str(h)] = entry
        return out


def peak_and_energy(images: np.ndarray, floor: float = ECHO_FLOOR) -> tuple[np.ndarray, np.ndarray]:
    """The peak pixel and the echo energy (the sum of the pixels above ``floor``) of each image of
    ``images`` (..., R, A); two arrays of shape (...)."""
    x = np.asarray(images, dtype=np.float32)
    peak = x.max(axis=(-2, -1)).astype(np.float64)
    energy = x.sum(axis=(-2, -1), where=x > floor, dtype=np.float64)  # a byte mask, no float copy
    return peak, energy


def _ratio_of_means(pred: np.ndarray, target: np.ndarray, keep: np.ndarray) -> float:
    if not keep.any():
        return float("nan")
    return float(pred[keep].mean() / target[keep].mean())


def fade_summary(res: EvalResult, tolerance: float = FADE_TOLERANCE) -> dict:
    """The "no fade" check of every predicting method (the noise ceiling is none).

    Returns {method: {"peak_ratio": [...], "energy_ratio": [...], "n_windows": [...],
    "within_15pct": bool, "first_out": step or None}}, lists over rollout steps 1..max horizon.
    Each ratio is a ratio of means over the windows whose target has echo energy at that step
    (``FADE_MEANING``); ``within_15pct`` is True when both ratios are within ``tolerance`` of 1
    at every step (a step with no usable window fails it); ``first_out`` is the first step where
    one is not. Empty when the result carries no step data.
    """
    if res.target_peak is None or res.target_energy is None:
        return {}
    keep = res.target_energy > 0  # (N, H)
    out = {}
    for m in res.predictors:
        if m not in res.step_peak:
            continue
        H = keep.shape[1]
        peak = [_ratio_of_means(res.step_peak[m][:, h], res.target_peak[:, h], keep[:, h]) for h in range(H)]
        energy = [_ratio_of_means(res.step_energy[m][:, h], res.target_energy[:, h], keep[:, h]) for h in range(H)]
        ok = [bool(np.isfinite(p) and np.isfinite(e) and abs(p - 1) <= tolerance and abs(e - 1) <= tolerance)
              for p, e in zip(peak, energy)]
        out[m] = {"peak_ratio": peak, "energy_ratio": energy, "n_windows": [int(k) for k in keep.sum(axis=0)],
                  "within_15pct": all(ok), "first_out": next((h + 1 for h, g in enumerate(ok) if not g), None)}
    return out


def baseline_rig(store: SonarStore, bank: FrameBank) -> tuple[RobotRig, str | None]:
    """The robot the baselines turn commands into image motion with, and a note when it is assumed.

    Its frame interval is the median spacing of the evaluated runs' time stamps, which the spec
    makes normative; the declared interval (the rig's, else 1 / frame rate) must agree with it
    within FRAME_INTERVAL_TOLERANCE, or the store is refused: naive and flow would warp every frame
    by the wrong step, silently. Without a rig the sensor is assumed on the wheel axle, with a note.
    """
    rig = store.rig
    declared = rig.frame_interval_s if rig is not None else 1.0 / store.attrs.frame_rate_hz
    measured = bank.frame_interval_s
    if measured is not None and abs(measured - declared) > FRAME_INTERVAL_TOLERANCE * declared:
        what = "rig.frame_interval_s" if rig is not None else f"frame_rate_hz {store.attrs.frame_rate_hz:g}"
        raise FormatError(f"{store.location}: the time stamps of runs {', '.join(bank.run_names)} are "
                          f"{measured:.6g} s apart (median), but the store declares {declared:g} s frames "
                          f"({what}); fix the store's frame rate or its time stamps")
    dt = measured if measured is not None else declared
    if rig is not None:
        return rig.model_copy(update={"frame_interval_s": dt}), None
    return RobotRig(frame_interval_s=dt, sensor_offset_m=0.0), (
        f"note: the store records no robot rig: naive and flow use the time stamps' {dt:.6g} s "
        "frames and assume the sensor on the wheel axle")


def undefined_counts(res: "EvalResult") -> dict[str, dict[int, dict[str, int]]]:
    """Per method, horizon and metric: how many windows have no value (NaN), e.g. CC of a
    constant target or prediction, NRMSD of an all-zero target. Only non-zero entries."""
    out: dict = {}
    for m in res.methods:
        for h in res.horizons:
            for k in METRICS:
                x = res.per_window[m][h][k]
                skipped = np.zeros(len(x), bool)
                if m in CEILINGS and res.ceiling_skipped:  # runs not re-rendered are not "undefined"
                    skipped = np.isin([r for r, _ in res.window_ids], list(res.ceiling_skipped))
                n = int(np.sum(~np.isfinite(x) & ~skipped))
                if n:
                    out.setdefault(m, {}).setdefault(h, {})[k] = n
    return out


def _undefined_notes(res: "EvalResult") -> list[str]:
    """One line per metric saying for how many windows it is undefined, and why."""
    counts = undefined_counts(res)
    n = len(res.window_ids)
    notes = []
    why = {"cc": "CC is undefined where the target frame or the prediction is constant",
           "nrmsd": "NRMSD is undefined where the target frame is all zero"}
    for k in IMAGE_METRICS:  # the echo metrics' defined windows are the n of the echo table
        parts = []
        for h in res.horizons:
            per = {m: counts.get(m, {}).get(h, {}).get(k, 0) for m in res.methods}
            if not any(per.values()):
                continue
            if len(set(per.values())) == 1:
                parts.append(f"{next(iter(per.values()))} of {n} windows at {horizon_name(h)}")
            else:
                parts.append(f"at {horizon_name(h)} " + ", ".join(f"{m} {c}" for m, c in per.items() if c) + f" of {n} windows")
        if parts:
            notes.append(f"note: {why[k]}: {'; '.join(parts)}; those windows are left out of its means, "
                         "stds and tests")
    return notes


def evaluate(
    store: SonarStore,
    model_specs: list[str],
    *,
    horizons: tuple[int, ...] = (1, 3, 5, 10),
    samples: int = 1000,
    split: str = "test",
    seed: int = 0,
    batch_size: int = 64,
    device: str = "cpu",
    precision: str = "auto",
    predictors: dict[str, Predictor] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    ceiling: bool = False,
    worlds: list[str] | None = None,
    echo_matching: EchoMatching | None = None,
) -> EvalResult:
    """Evaluate every model on the same ``samples`` windows of ``split``, for every horizon.

    Windows are drawn once (seeded) among those with room for the longest horizon, so every
    method and horizon sees the same starting points; each method is rolled out once to the
    longest horizon and scored at every requested one. ``worlds`` keeps only the runs of those
    world families (``source.world``).

    With ``ceiling``, the target frames of simulated runs are also re-rendered from their recorded
    world and poses with an independent noise draw (seeded by ``seed``) and scored as the method
    ``"ceiling"``: the noise ceiling, how much of a frame is predictable at all; and re-rendered
    from only the reflectors each window's context frames heard, as ``"observable"``: how much
    of it the context could know (``sonarset.scoring.ceiling``). Runs they cannot re-render get NaN there,
    a reason in ``ceiling_skipped`` and a line in ``notes``; with none, the rows are omitted.

    Every method is also scored on the echoes it draws (``echo_matching``, default
    ``EchoMatching()``): detection precision, recall and F1, and the position error of matched echoes.
    """
    horizons = tuple(sorted(set(int(h) for h in horizons)))
    if not horizons or horizons[0] < 1:
        raise SonarSetError("horizons must be positive integers")
    echo_matching = echo_matching or EchoMatching()
    bank = FrameBank.from_store(store, split=split, image_dtype=np.float32, worlds=worlds)
    rig, note = baseline_rig(store, bank)
    notes = [note] if note else []
    preds, model_notes = _predictors(store, model_specs, rig, device, precision, predictors)
    notes += model_notes
    index = _windows(store, bank, split, window_frames(preds), horizons[-1], samples, seed)
    ids = [(bank.run_names[j], k) for j, k in (index.locate(i) for i in range(len(index)))]
    scores = _Scores.of(preds, len(index), horizons, store.grid, echo_matching)
    skipped: dict[str, str] = {}
    with cf.ThreadPoolExecutor(1) as helper:
        # The ceiling renders (compiled, GIL released) beside the rollouts: it shares nothing with
        # them, and it fills the cycles a learned model's threads leave idle.
        ceiling_job = helper.submit(_ceiling_scores, store, bank, index, ids, horizons, seed, batch_size,
                                    echo_matching, progress) if ceiling else None
        examples = scores.roll_out(WindowBatcher.of(bank), index, preds, batch_size, progress)
        examples["window"] = ids[0]
    if ceiling_job is not None:
        ceiling_scores, ceiling_seconds, skipped = ceiling_job.result()
        notes += [f"ceiling: run {r} not re-rendered: {why}" for r, why in skipped.items()]
        if ceiling_scores is None:
            notes.append(f"ceiling: no run of split {split!r} can be re-rendered; the ceiling rows are omitted")
        else:
            for name, rows in ceiling_scores.items():
                scores.per_window[name] = rows
                scores.seconds[name] = ceiling_seconds[name]
    result = EvalResult(store.location, split, bank.run_names, list(horizons), list(scores.per_window),
                        index.starts, ids, scores.per_window, seconds=scores.seconds, examples=examples, notes=notes,
                        ceiling_skipped=skipped, step_peak=scores.step_peak, step_energy=scores.step_energy,
                        target_peak=scores.target_peak, target_energy=scores.target_energy, n_in=index.n_in,
                        precision={m: p.precision for m, p in preds.items() if isinstance(getattr(p, "precision", None), str)},
                        echo_matching=echo_matching, worlds=list(worlds) if worlds else None)
    result.notes += _undefined_notes(result)
    result.comparisons = _compare_all(result, seed)
    return result


def _predictors(store: SonarStore, model_specs: list[str], rig: RobotRig, device: str, precision: str,
                given: dict[str, Predictor] | None) -> tuple[dict[str, Predictor], list[str]]:
    """The predictors by name (``given`` first, then ``model_specs``), and notes on learned models
    meeting other images than they were trained on."""
    from sonarset.models.echopt.cards import training_notices
    from sonarset.models.registry import make_predictor

    preds: dict[str, Predictor] = dict(given or {})
    for spec in model_specs:
        p = make_predictor(spec, store.grid, rig, device=device, precision=precision)
        if p.name in preds:  # several checkpoints: each under its own label (echopt RUN/model)
            p.name = getattr(p, "label", spec)
            if p.name in preds:
                p.name = spec
        preds[p.name] = p
    notes = []
    for p in preds.values():
        if isinstance(getattr(p, "card", None), dict):
            notes += training_notices(getattr(p, "label", p.name), p.card, store.processing, store.rig)
    if not preds:
        raise SonarSetError("no models to evaluate")
    return preds, notes


def window_frames(preds: dict[str, Predictor]) -> int:
    """Input frames per window: the one count all predictors were built for (a learned model's is
    in its config); predictors that read only the last frame take any."""
    counts = {p.n_in for p in preds.values() if not getattr(p, "any_context", False)}
    if not counts:
        return N_IN
    if len(counts) != 1:
        raise SonarSetError("the models take different numbers of input frames ("
                            + ", ".join(f"{name} {p.n_in}" for name, p in preds.items()) + "); evaluate them apart")
    return counts.pop()


def _windows(store: SonarStore, bank: FrameBank, split: str, n_in: int, horizon: int, samples: int,
             seed: int) -> WindowIndex:
    """``samples`` windows (seeded) among those with room for ``horizon`` targets."""
    index = WindowIndex.build(bank, n_in, horizon)
    if len(index) == 0:
        raise SonarSetError(f"{store.location}: split {split!r} has no run long enough for horizon {horizon} "
                            f"(needs {index.span} frames)")
    return index.sample(samples, seed)


@dataclass
class _Scores:
    """Per-window scores of the predicting methods, filled batch by batch (N windows, H steps)."""

    per_window: dict[str, dict[int, dict[str, np.ndarray]]]  # method -> horizon -> metric -> (N,)
    seconds: dict[str, float]
    step_peak: dict[str, np.ndarray]  # method -> (N, H)
    step_energy: dict[str, np.ndarray]
    target_peak: np.ndarray  # (N, H)
    target_energy: np.ndarray
    grid: object  # SensorGrid: echo positions in metres and degrees
    matching: EchoMatching

    @classmethod
    def of(cls, preds: dict[str, Predictor], n: int, horizons: tuple[int, ...], grid,
           matching: EchoMatching) -> "_Scores":
        H = horizons[-1]
        return cls({m: {h: {k: np.empty(n) for k in METRICS} for h in horizons} for m in preds},
                   dict.fromkeys(preds, 0.0), {m: np.empty((n, H)) for m in preds}, {m: np.empty((n, H)) for m in preds},
                   np.empty((n, H)), np.empty((n, H)), grid, matching)

    def roll_out(self, batcher: WindowBatcher, index: WindowIndex, preds: dict[str, Predictor], batch_size: int,
                 progress: Callable[[str, int, int], None] | None) -> dict:
        """Roll every method out over every window, batch by batch, and score it; returns the first
        window's frames, targets and predictions (the figures' example)."""
        H = index.horizon
        examples: dict = {"methods": {}}
        for lo in range(0, len(index), batch_size):
            sl = slice(lo, min(len(index), lo + batch_size))
            batch = batcher.gather(index, np.arange(sl.start, sl.stop))  # once for every method
            if lo == 0:
                examples["frames"], examples["targets"] = batch.frames[0], batch.targets[0]
            self.target_peak[sl], self.target_energy[sl] = peak_and_energy(batch.targets[:, :H])
            horizons = list(next(iter(self.per_window.values())))
            target_echoes = {h: find_echoes(batch.targets[:, h - 1], self.grid, self.matching) for h in horizons}
            for name, predictor in preds.items():
                t0 = time.perf_counter()
                pred = rollout(predictor, batch.frames, batch.commands, H)
                self.seconds[name] += time.perf_counter() - t0  # the prediction's time, not the scoring's
                for h, metrics in self.per_window[name].items():
                    for k, v in score_images(pred[:, h - 1], batch.targets[:, h - 1], self.grid, self.matching,
                                             target_echoes[h]).items():
                        metrics[k][sl] = v
                self.step_peak[name][sl], self.step_energy[name][sl] = peak_and_energy(pred)
                if lo == 0:
                    examples["methods"][name] = pred[0]
                if progress:
                    progress(name, sl.stop, len(index))
        return examples


def score_images(pred: np.ndarray, target: np.ndarray, grid, matching: EchoMatching,
                 target_echoes=None) -> dict[str, np.ndarray]:
    """{metric in METRICS: (N,) per-image values} of predictions against targets, both (N, R, A)."""
    cc, nrmsd = cc_and_nrmsd(pred, target)
    return {"cc": cc, "nrmsd": nrmsd, **echo_scores(pred, target, grid, matching, target_echoes)}


def _ceiling_scores(store: SonarStore, bank: FrameBank, index: WindowIndex, ids: list[tuple[str, int]],
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


def _compare_all(res: EvalResult, seed: int) -> list[Comparison]:
    pairs = [(h, a, b, k) for h in res.horizons for a, b in combinations(res.predictors, 2)  # ceilings: no predictors
             for k in METRICS]

    def one(pair: tuple) -> Comparison:
        h, a, b, k = pair
        return compare(res.per_window[a][h][k], res.per_window[b][h][k], metric=k, horizon=h, names=(a, b), seed=seed)

    # the bootstraps (168 in the demo) spend their time in NumPy, which releases the GIL; each is
    # seeded on its own, so the threads change no value
    with cf.ThreadPoolExecutor(min(4, os.cpu_count() or 1)) as pool:
        comps = list(pool.map(one, pairs))
    for c, p in zip(comps, holm([c.t_paired_p for c in comps])):
        c.p_holm = p
    return comps
