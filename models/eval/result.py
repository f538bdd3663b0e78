"""What an evaluation returns (:class:`EvalResult`) and what is read off it: the per-metric means,
the windows where a metric is undefined, and the "no fade" check, whether the rollouts keep the
targets' peak pixel and echo energy at every step forecast (``fade_summary``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sonarset.report.numbers import horizon_name
from sonarset.scoring.ceiling import CEILINGS, OBSERVABLE
from sonarset.scoring.echoes import ECHO_METRICS, EchoMatching
from sonarset.scoring.stats import Comparison
from sonarset.windows import N_IN

IMAGE_METRICS = ("cc", "nrmsd")  # the paper's
#: Every per-window metric: the paper's, then the echo metrics (sonarset/scoring/echoes.py).
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
    # the "no fade" data, per window: (N, max horizon) arrays of the peak pixel and the echo energy at
    # every rollout step, per predicting method and for the targets (a method in ``direct`` computes
    # only the scored horizons, column h - 1: its other columns are NaN)
    step_peak: dict[str, np.ndarray] = field(default_factory=dict)
    step_energy: dict[str, np.ndarray] = field(default_factory=dict)
    target_peak: np.ndarray | None = None
    target_energy: np.ndarray | None = None
    n_in: int = N_IN  # input frames per window
    precision: dict[str, str] = field(default_factory=dict)  # learned method -> fp32 | bf16, as it ran
    echo_matching: EchoMatching = field(default_factory=EchoMatching)
    worlds: list[str] | None = None  # the world families the runs were restricted to
    direct: list[str] = field(default_factory=list)  # methods that forecast the scored horizons alone

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
    """The "no fade" check of every predicting method (the noise ceiling is none), at every step it
    forecast: each step 1..max horizon of a rollout, the scored horizons of a method that forecasts
    each horizon directly (``res.direct``).

    Returns {method: {"steps": [...], "peak_ratio": [...], "energy_ratio": [...], "n_windows": [...],
    "within_15pct": bool, "first_out": step or None}}, lists over its steps. Each ratio is a ratio
    of means over the windows whose target has echo energy at that step (``FADE_MEANING``);
    ``within_15pct`` is True when both ratios are within ``tolerance`` of 1 at each of its steps (a
    step with no usable window fails it); ``first_out`` is the first step where one is not. Empty
    when the result carries no step data.
    """
    if res.target_peak is None or res.target_energy is None:
        return {}
    keep = res.target_energy > 0  # (N, H)
    out = {}
    for m in res.predictors:
        if m not in res.step_peak:
            continue
        steps = list(res.horizons) if m in res.direct else list(range(1, keep.shape[1] + 1))
        peak = [_ratio_of_means(res.step_peak[m][:, h - 1], res.target_peak[:, h - 1], keep[:, h - 1]) for h in steps]
        energy = [_ratio_of_means(res.step_energy[m][:, h - 1], res.target_energy[:, h - 1], keep[:, h - 1])
                  for h in steps]
        ok = [bool(np.isfinite(p) and np.isfinite(e) and abs(p - 1) <= tolerance and abs(e - 1) <= tolerance)
              for p, e in zip(peak, energy)]
        out[m] = {"steps": steps, "peak_ratio": peak, "energy_ratio": energy,
                  "n_windows": [int(keep[:, h - 1].sum()) for h in steps], "within_15pct": all(ok),
                  "first_out": next((h for h, g in zip(steps, ok) if not g), None)}
    return out


def undefined_counts(res: EvalResult) -> dict[str, dict[int, dict[str, int]]]:
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


def _non_finite_predictions(res: EvalResult) -> dict[str, dict[int, np.ndarray]]:
    """Per predicting method and horizon: the windows whose prediction holds a NaN or an infinity
    (its peak pixel is not finite). Every metric of such a window is undefined through the model,
    not through the target, and the note must say so."""
    return {m: {h: ~np.isfinite(res.step_peak[m][:, h - 1]) for h in res.horizons}
            for m in res.methods if m in res.step_peak and res.step_peak[m].shape[-1] >= max(res.horizons)}


def undefined_notes(res: EvalResult) -> list[str]:
    """One line per metric saying for how many windows it is undefined, and why."""
    counts = undefined_counts(res)
    n = len(res.window_ids)
    notes = []
    broken = _non_finite_predictions(res)
    counts = {m: {h: dict(per) for h, per in by_h.items()} for m, by_h in counts.items()}
    nan_parts = []
    for m, by_h in broken.items():
        for h, bad in by_h.items():
            if not bad.any():
                continue
            nan_parts.append(f"{m} {int(bad.sum())} of {n} windows at {horizon_name(h)}")
            for k, c in counts.get(m, {}).get(h, {}).items():  # the rest are the target's doing
                counts[m][h][k] = c - int(np.sum(bad & ~np.isfinite(res.per_window[m][h][k])))
    if nan_parts:
        notes.append(f"note: the prediction is NaN (not finite): {'; '.join(nan_parts)}; every metric of those "
                     "windows is left out of its means, stds and tests")
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
