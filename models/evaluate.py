"""The evaluation engine: every method on the same seeded windows, the paper's metrics, statistics.

``evaluate`` is the library API behind ``sonarset eval``; ``write_report`` writes metrics.json,
per_window.csv, report.md and the figures. ``fade_summary`` is the "no fade" check: whether the
rollouts keep the targets' peak pixel and echo energy at every step.
"""

from __future__ import annotations

import csv
import json
import os
import time
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Callable

import numpy as np

from sonarset.report import format_p, horizon_name
from sonarset.atomic import atomic_text, atomic_write
from sonarset.ceiling import CEILING
from sonarset.arrays import FRAME_INTERVAL_TOLERANCE
from sonarset.errors import FormatError, SonarSetError
from sonarset.metrics import cc, nrmsd
from sonarset.stats import Comparison, compare, holm
from sonarset.store import SonarStore
from sonarset.windows import FrameBank, WindowIndex, gather

from .baselines import Predictor, rollout

#: The paper's Table 1: mean CC and NRMSD on 1000 test windows (one-shot, AR-3, AR-5, AR-10).
PAPER = {
    "naive": {"cc": {1: 0.85, 3: 0.66, 5: 0.56, 10: 0.38}, "nrmsd": {1: 0.42, 3: 0.76, 5: 0.83, 10: 1.34}},
    "flow": {"cc": {1: 0.86, 3: 0.73, 5: 0.69, 10: 0.56}, "nrmsd": {1: 0.38, 3: 0.62, 5: 0.65, 10: 0.99}},
    "echopt": {"cc": {1: 0.97, 3: 0.83, 5: 0.80, 10: 0.69}, "nrmsd": {1: 0.15, 3: 0.46, 5: 0.52, 10: 0.80}},
}
METRICS = ("cc", "nrmsd")
LOWER_IS_BETTER = {"cc": False, "nrmsd": True}
#: Echo energy counts the pixels above this value (images are in [0, 1]): what is left of an
#: echo, not the faint interpolation haze or residual noise a rollout can smear over the image.
ECHO_FLOOR = 0.05
#: "No fade": the mean prediction / target ratios of peak pixel and echo energy stay within this
#: fraction of 1 at every rollout step.
FADE_TOLERANCE = 0.15
FADE_MEANING = (f"Per rollout step h (1 .. longest horizon), for each method: peak = the brightest pixel "
                f"of the image, echo energy = the sum of the pixels above {ECHO_FLOOR} (ECHO_FLOOR), for "
                "the prediction and for the target of each window. Ratio = mean over windows of the "
                "prediction's value / mean over the same windows of the target's (a ratio of means, "
                "not a mean of per-window ratios, so that windows with little echo cannot dominate); "
                "windows whose target has no echo energy at that step are left out. 'within_15pct': "
                f"both ratios stay within {FADE_TOLERANCE:.0%} of 1 at every step (no fade, no "
                "brightening). The noise ceiling is not a predictor and has no entry.")
CEILING_MEANING = ("noise ceiling: each target frame re-rendered from its run's recorded world and poses "
                   "with an independent noise draw, scored against the recorded frame; it shows how much "
                   "of a frame is predictable at all (the same scene, only the noise differs).")


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

    @property
    def predictors(self) -> list[str]:
        """The methods that predict: every method but the noise ceiling."""
        return [m for m in self.methods if m != CEILING]

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


def _robot_geometry(store: SonarStore, bank: FrameBank) -> tuple[float, float, str | None]:
    """(dt, sensor offset, note) for the baselines.

    dt is the median spacing of the evaluated runs' time stamps, which the spec makes normative;
    the declared interval (the rig's, else 1 / frame rate) must agree with it within
    FRAME_INTERVAL_TOLERANCE, or the store is refused: naive and flow would warp every frame by
    the wrong step, silently. Without a rig the sensor is assumed on the wheel axle, with a note.
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
        return dt, rig.sensor_offset_m, None
    return dt, 0.0, (f"note: the store records no robot rig: naive and flow use the time stamps' {dt:.6g} s "
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
                if m == CEILING and res.ceiling_skipped:  # runs not re-rendered are not "undefined"
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
    for k in METRICS:
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
    batch_size: int = 250,
    device: str = "cpu",
    predictors: dict[str, Predictor] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    ceiling: bool = False,
) -> EvalResult:
    """Evaluate every model on the same ``samples`` windows of ``split``, for every horizon.

    Windows are drawn once (seeded) among those with room for the longest horizon, so every
    method and horizon sees the same starting points; each method is rolled out once to the
    longest horizon and scored at every requested one.

    With ``ceiling``, the target frames of simulated runs are also re-rendered from their recorded
    world and poses with an independent noise draw (seeded by ``seed``) and scored as the method
    ``"ceiling"``: the noise ceiling, how much of a frame is predictable at all. Runs it cannot
    re-render get NaN there, a reason in ``ceiling_skipped`` and a line in ``notes``; with none,
    the row is omitted.
    """
    from .cards import training_notices
    from .registry import make_predictor

    horizons = tuple(sorted(set(int(h) for h in horizons)))
    if not horizons or horizons[0] < 1:
        raise SonarSetError("horizons must be positive integers")
    bank = FrameBank.from_store(store, split=split, image_dtype=np.float32)
    dt, offset, note = _robot_geometry(store, bank)
    notes = [note] if note else []
    preds: dict[str, Predictor] = dict(predictors or {})
    for spec in model_specs:
        p = make_predictor(spec, store.grid, dt=dt, sensor_offset=offset, device=device)
        if p.name in preds:  # several checkpoints: each under its own label (echopt RUN/model)
            p.name = getattr(p, "label", spec)
            if p.name in preds:
                p.name = spec
        preds[p.name] = p
    for p in preds.values():  # a learned model meeting other images than it was trained on
        if isinstance(getattr(p, "card", None), dict):
            notes += training_notices(getattr(p, "label", p.name), p.card, store.processing, store.rig)
    if not preds:
        raise SonarSetError("no models to evaluate")
    H = horizons[-1]
    index = WindowIndex.build(bank, 3, H)
    if len(index) == 0:
        raise SonarSetError(f"{store.location}: split {split!r} has no run long enough for horizon {H} "
                            f"(needs {3 + H} frames)")
    index = index.sample(samples, seed)
    ids = [(bank.run_names[j], k) for j, k in (index.locate(i) for i in range(len(index)))]
    per_window = {m: {h: {k: np.empty(len(index)) for k in METRICS} for h in horizons} for m in preds}
    seconds = dict.fromkeys(preds, 0.0)
    step_peak = {m: np.empty((len(index), H)) for m in preds}
    step_energy = {m: np.empty((len(index), H)) for m in preds}
    target_peak, target_energy = np.empty((len(index), H)), np.empty((len(index), H))
    examples: dict = {"window": ids[0], "methods": {}}
    for lo in range(0, len(index), batch_size):
        sl = slice(lo, min(len(index), lo + batch_size))
        batch = gather(bank, index, np.arange(sl.start, sl.stop))  # once for every method
        if lo == 0:
            examples["frames"], examples["targets"] = batch.frames[0], batch.targets[0]
        target_peak[sl], target_energy[sl] = peak_and_energy(batch.targets[:, :H])
        for name, predictor in preds.items():
            t0 = time.perf_counter()
            pred = rollout(predictor, batch.frames, batch.commands, H)
            for h in horizons:
                per_window[name][h]["cc"][sl] = cc(pred[:, h - 1], batch.targets[:, h - 1])
                per_window[name][h]["nrmsd"][sl] = nrmsd(pred[:, h - 1], batch.targets[:, h - 1])
            seconds[name] += time.perf_counter() - t0
            step_peak[name][sl], step_energy[name][sl] = peak_and_energy(pred)
            if lo == 0:
                examples["methods"][name] = pred[0]
            if progress:
                progress(name, sl.stop, len(index))
    skipped: dict[str, str] = {}
    if ceiling:
        t0 = time.perf_counter()
        scores, skipped = _ceiling_scores(store, bank, index, ids, horizons, seed, batch_size, progress)
        notes += [f"ceiling: run {r} not re-rendered: {why}" for r, why in skipped.items()]
        if scores is None:
            notes.append(f"ceiling: no run of split {split!r} can be re-rendered; the ceiling row is omitted")
        else:
            per_window[CEILING] = scores
            seconds[CEILING] = time.perf_counter() - t0
    result = EvalResult(store.location, split, bank.run_names, list(horizons), list(per_window),
                        index.starts, ids, per_window, seconds=seconds, examples=examples, notes=notes,
                        ceiling_skipped=skipped, step_peak=step_peak, step_energy=step_energy,
                        target_peak=target_peak, target_energy=target_energy)
    result.notes += _undefined_notes(result)
    result.comparisons = _compare_all(result, seed)
    return result


def _ceiling_scores(store: SonarStore, bank: FrameBank, index: WindowIndex, ids: list[tuple[str, int]],
                    horizons: tuple[int, ...], seed: int, batch_size: int, progress=None):
    """Per-window scores of the noise ceiling (NaN for windows of runs it cannot re-render), or
    None when it can re-render no run; and {run: reason} for the runs it skipped.

    The ceiling's prediction of a target frame is that frame re-rendered: at horizon h, window w's
    target is frame k_w + n_in + h - 1 of its run. Only those frames are rendered, in batches.
    """
    from sonarset.ceiling import CeilingUnavailable, RunRenderer

    n_in = index.n_in
    scores = {h: {k: np.full(len(ids), np.nan) for k in METRICS} for h in horizons}
    run_of = np.array([r for r, _ in ids])
    first = np.array([k for _, k in ids], np.int64)
    hs = np.asarray(horizons, np.int64)
    skipped: dict[str, str] = {}
    todo = []
    for name in bank.run_names:
        try:
            todo.append(RunRenderer(store, name, seed))
        except CeilingUnavailable as exc:
            skipped[name] = str(exc)
    if not todo:
        return None, skipped
    plans = []
    for r in todo:
        w = np.flatnonzero(run_of == r.name)
        # (window, horizon) pairs of this run and their target frames, each frame rendered once
        ww, hh = np.repeat(w, len(hs)), np.tile(hs, len(w))
        frames, which = np.unique(first[ww] + n_in + hh - 1, return_inverse=True)
        plans.append((r, ww, hh, frames, which))
    total, done = sum(len(p[3]) for p in plans), 0
    step = max(1, batch_size)
    for r, ww, hh, frames, which in plans:
        for lo in range(0, len(frames), step):
            hi = min(len(frames), lo + step)
            images = r.render(frames[lo:hi])
            sel = np.flatnonzero((which >= lo) & (which < hi))
            w, h = ww[sel], hh[sel]
            pred = images[which[sel] - lo]
            target = bank.images[index.starts[w] + n_in + h - 1]
            for k, metric in (("cc", cc), ("nrmsd", nrmsd)):
                vals = metric(pred, target)
                for hz in horizons:
                    scores[hz][k][w[h == hz]] = vals[h == hz]
            done += hi - lo
            if progress:
                progress(CEILING, done, total)
    return scores, skipped


def _compare_all(res: EvalResult, seed: int) -> list[Comparison]:
    comps = []
    for h in res.horizons:
        for a, b in combinations(res.predictors, 2):  # the noise ceiling is no predictor
            for k in METRICS:
                comps.append(compare(res.per_window[a][h][k], res.per_window[b][h][k], metric=k,
                                     horizon=h, names=(a, b), seed=seed))
    for c, p in zip(comps, holm([c.t_paired_p for c in comps])):
        c.p_holm = p
    return comps


# ---- outputs -------------------------------------------------------------------------------------

def write_report(res: EvalResult, out: str | os.PathLike, *, figures: bool = True) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = res.summary()
    fade = fade_summary(res)
    doc = {
        "results": summary,
        "tests": [c.to_dict() for c in res.comparisons],
        "store": res.store,
        "split": res.split,
        "runs": res.runs,
        "windows": {"n": len(res.window_ids), "n_in": 3, "horizons": res.horizons,
                    "ids": [[r, k] for r, k in res.window_ids]},
        "seconds": res.seconds,
        "notes": res.notes,
        "undefined_windows": {m: {str(h): v for h, v in d.items()} for m, d in undefined_counts(res).items()},
        **({"ceiling": {"method": CEILING, "meaning": CEILING_MEANING, "skipped_runs": res.ceiling_skipped}}
           if CEILING in res.methods or res.ceiling_skipped else {}),
        **({"fade": _json_finite(fade),
            "fade_definition": {"echo_floor": ECHO_FLOOR, "tolerance": FADE_TOLERANCE,
                                "steps": list(range(1, len(next(iter(fade.values()))["peak_ratio"]) + 1)),
                                "meaning": FADE_MEANING}} if fade else {}),
        "paper": {m: {k: {str(h): v for h, v in d.items()} for k, d in t.items()} for m, t in PAPER.items()},
    }
    atomic_text(out / "metrics.json", json.dumps(doc, indent=2) + "\n")
    rows = [(m, h, f"{r}:{k}", float(res.per_window[m][h]["cc"][i]), float(res.per_window[m][h]["nrmsd"][i]))
            for m in res.methods for h in res.horizons for i, (r, k) in enumerate(res.window_ids)
            if m != CEILING or r not in res.ceiling_skipped]  # the ceiling has no row for runs it skipped
    def write_csv(path: Path) -> None:
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["method", "horizon", "window", "cc", "nrmsd"])
            w.writerows(rows)

    atomic_write(out / "per_window.csv", write_csv)
    figs = []
    if figures:
        from .figures import write_figures

        figs = write_figures(res, out)
    atomic_text(out / "report.md", render_report(res, figs))
    return out


def _json_finite(x):
    """``x`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(x, dict):
        return {k: _json_finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_json_finite(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def fade_table(res: EvalResult, fade: dict | None = None) -> str:
    """The "no fade" table: per method, the range of its peak and echo-energy ratios over the
    rollout steps, and the verdict."""
    fade = fade_summary(res) if fade is None else fade
    lines = ["| method | peak ratio min | peak ratio max | energy ratio min | energy ratio max | verdict |",
             "|---|---|---|---|---|---|"]

    def rng(v):
        v = np.asarray(v, float)
        v = v[np.isfinite(v)]
        return (f"{v.min():.3f}", f"{v.max():.3f}") if len(v) else ("n/a", "n/a")

    for m, f in fade.items():
        if f["within_15pct"]:
            verdict = f"no fade (within {FADE_TOLERANCE:.0%} at every step)"
        else:
            h = f["first_out"]
            p, e = f["peak_ratio"][h - 1], f["energy_ratio"][h - 1]
            if np.isfinite(p) and np.isfinite(e):
                kind = "fades" if max((p, e), key=lambda r: abs(r - 1)) < 1 else "brightens"
            else:
                kind = "no window with echo energy"
            verdict = f"{kind} from step {h}"
        lines.append(f"| {m} | " + " | ".join([*rng(f["peak_ratio"]), *rng(f["energy_ratio"])]) + f" | {verdict} |")
    return "\n".join(lines)


def results_table(res: EvalResult, with_paper: bool = True) -> str:
    s = res.summary()
    head = "| method | " + " | ".join(f"CC {horizon_name(h)}" for h in res.horizons) + " | " + \
           " | ".join(f"NRMSD {horizon_name(h)}" for h in res.horizons) + " |"
    lines = [head, "|---" * (1 + 2 * len(res.horizons)) + "|"]
    for m in res.methods:
        cells = [_cell(s[m][str(h)][k]) for k in METRICS for h in res.horizons]
        label = f"*{m} (noise ceiling, not a predictor)*" if m == CEILING else m
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
        if with_paper and m in PAPER:
            p = PAPER[m]
            cells = [f"{p['cc'].get(h, float('nan')):.2f}" if h in p["cc"] else "-" for h in res.horizons]
            cells += [f"{p['nrmsd'].get(h, float('nan')):.2f}" if h in p["nrmsd"] else "-" for h in res.horizons]
            lines.append(f"| *{m} (paper)* | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _cell(entry: dict) -> str:
    if entry["mean"] is None:
        return "undefined"
    return f"{entry['mean']:.3f} ({entry['std']:.3f})"


def render_report(res: EvalResult, figures: list[str]) -> str:
    n = len(res.window_ids)
    parts = [
        "# Evaluation report",
        "",
        f"Store `{res.store}`, split `{res.split}` ({', '.join(res.runs)}); {n} windows drawn once "
        f"(seeded) and shared by every method and horizon. Mean (std) over windows; the paper's "
        "Table 1 values in italics below ours (its simulator differs: compare orderings and gaps, "
        "not absolute values). CC higher is better; NRMSD lower is better.",
        "",
        *[f"> {n}\n" for n in res.notes],
        results_table(res),
        *(["", f"*{CEILING}* is the {CEILING_MEANING} It is not a predictor and is left out of the "
               "statistics below."] if CEILING in res.methods else []),
        "",
        "## Statistics",
        "",
        "Per horizon and metric, each pair of methods on the same windows: mean difference (a - b) "
        "with a bootstrap 95% CI (BCa, 2000 resamples); the paper's two-sample t-test (Welch); the "
        "paired t-test and Wilcoxon signed-rank test on per-window differences; the paired t-test's "
        f"p adjusted by Holm over all {len(res.comparisons)} comparisons.",
        "",
        "| horizon | metric | a | b | mean(a-b) | 95% CI | 2-sample t p | paired t p | Wilcoxon p | Holm p | better |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in res.comparisons:
        better = "-"
        if c.p_holm is not None and np.isfinite(c.p_holm) and c.p_holm < 0.05:
            a_better = (c.mean_diff < 0) if LOWER_IS_BETTER[c.metric] else (c.mean_diff > 0)
            better = c.a if a_better else c.b
        parts.append(f"| {horizon_name(c.horizon)} | {c.metric} | {c.a} | {c.b} | {c.mean_diff:+.4f} | "
                     f"[{c.ci_low:+.4f}, {c.ci_high:+.4f}] | {format_p(c.t_two_sample_p)} | {format_p(c.t_paired_p)} | "
                     f"{format_p(c.wilcoxon_p)} | {format_p(c.p_holm)} | {better} |")
    fade = fade_summary(res)
    if fade:
        steps = len(next(iter(fade.values()))["peak_ratio"])
        parts += ["", "## No fade", "",
                  f"Over the rollouts to {steps} steps: mean prediction / target ratio of the peak pixel "
                  f"and of the echo energy (the sum of the pixels above {ECHO_FLOOR}), a ratio of means over "
                  "the windows whose target has echo energy at that step; min and max over the steps. "
                  f"No fade: both ratios within {FADE_TOLERANCE:.0%} of 1 at every step "
                  "(per step in metrics.json, `fade`" +
                  ("; the figure `fade.png`)." if any(Path(f).name == "fade.png" for f in figures) else ")."),
                  "", fade_table(res, fade)]
    parts += ["", "## Timing", ""]
    parts += [f"- {m}: {t:.2f} s to re-render the target frames" if m == CEILING else
              f"- {m}: {t:.2f} s for {n} windows rolled out to {max(res.horizons)} steps" for m, t in res.seconds.items()]
    if figures:
        parts += ["", "## Figures", ""]
        parts += [f"![{Path(f).stem}]({Path(f).name})" for f in figures]
    return "\n".join(parts) + "\n"
