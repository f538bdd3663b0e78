"""The evaluation report: an :class:`~sonarset.models.eval.evaluate.EvalResult` rendered as
metrics.json, per_window.csv, report.md and the figures (``sonarset eval``, ``sonarset demo``)."""

from __future__ import annotations

import csv
import json
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np

from sonarset.store.atomic import atomic_text, atomic_write, publish_files
from sonarset.scoring.ceiling import CEILING, CEILINGS, OBSERVABLE
from sonarset.scoring.echoes import ECHO_METRICS
from sonarset.scoring.stats import HAC_SPANS
from sonarset.report.numbers import finite_or_none, format_interval, format_p, format_value, horizon_name

from sonarset.models.eval.result import (ECHO_FLOOR, FADE_TOLERANCE, IMAGE_METRICS, METRICS, EvalResult, fade_summary,
                                         undefined_counts)

#: The paper's Table 1: mean CC and NRMSD on 1000 test windows (one-shot, AR-3, AR-5, AR-10).
PAPER = {
    "naive": {"cc": {1: 0.85, 3: 0.66, 5: 0.56, 10: 0.38}, "nrmsd": {1: 0.42, 3: 0.76, 5: 0.83, 10: 1.34}},
    "flow": {"cc": {1: 0.86, 3: 0.73, 5: 0.69, 10: 0.56}, "nrmsd": {1: 0.38, 3: 0.62, 5: 0.65, 10: 0.99}},
    "echopt": {"cc": {1: 0.97, 3: 0.83, 5: 0.80, 10: 0.69}, "nrmsd": {1: 0.15, 3: 0.46, 5: 0.52, 10: 0.80}},
}
LOWER_IS_BETTER = {"cc": False, "nrmsd": True, "echo_f1": False, "echo_precision": False, "echo_recall": False,
                   "echo_range_cm": True, "echo_azimuth_deg": True}
ECHO_LABELS = {"echo_f1": "F1", "echo_precision": "precision", "echo_recall": "recall",
               "echo_range_cm": "range error cm", "echo_azimuth_deg": "azimuth error deg"}
FADE_MEANING = (f"Per rollout step h (1 .. longest horizon; a method that forecasts each horizon directly: "
                "the scored horizons, its 'steps'), for each method: peak = the brightest pixel "
                f"of the image, echo energy = the sum of the pixels above {ECHO_FLOOR} (ECHO_FLOOR), for "
                "the prediction and for the target of each window. Ratio = mean over windows of the "
                "prediction's value / mean over the same windows of the target's (a ratio of means, "
                "not a mean of per-window ratios, so that windows with little echo cannot dominate); "
                "windows whose target has no echo energy at that step are left out. 'within_15pct': "
                f"both ratios stay within {FADE_TOLERANCE:.0%} of 1 at each of its steps (no fade, no "
                "brightening). The noise ceiling is not a predictor and has no entry.")
CEILING_MEANING = ("noise ceiling: each target frame re-rendered from its run's recorded world and poses "
                   "with an independent noise draw, scored against the recorded frame; it shows how much "
                   "of a frame is predictable at all (the same scene, only the noise differs).")
OBSERVABLE_MEANING = ("observable ceiling: each target frame re-rendered at its true pose from only the "
                      "reflectors that produced an echo within the image's display range in the window's context frames "
                      "(heard stretches of walls, heard circles), with an independent noise draw; it shows how "
                      "much of a frame the context could know. The noise ceiling minus it is what enters the "
                      "view during the rollout, which no predictor from this context can know.")
CEILING_LABELS = {CEILING: "noise ceiling", OBSERVABLE: "observable ceiling"}



def md_cell(name: str) -> str:
    """A method's name as a Markdown table cell: a '|' in it would end the cell."""
    return name.replace("|", "\\|")

def write_report(res: EvalResult, out: str | os.PathLike, *, figures: bool = True) -> Path:
    """metrics.json, per_window.csv, the figures (unless ``figures`` is False) and report.md in ``out``."""
    def write(folder: Path) -> None:
        atomic_text(folder / "metrics.json", json.dumps(metrics_document(res), indent=2) + "\n")
        atomic_write(folder / "per_window.csv", lambda path: write_per_window(res, path))
        figs = []
        if figures:
            from sonarset.models.eval.figures import write_figures

            figs = write_figures(res, folder)
        atomic_text(folder / "report.md", render_report(res, figs))

    return publish_files(out, write, last="report.md")


def metrics_document(res: EvalResult) -> dict:
    """The result as metrics.json records it: summaries, tests, windows, notes, fade, the paper's values."""
    fade = fade_summary(res)
    return {
        "results": res.summary(),
        "tests": [c.to_dict() for c in res.comparisons],
        "store": res.store,
        "split": res.split,
        "runs": res.runs,
        "windows": {"n": len(res.window_ids), "n_in": res.n_in, "horizons": res.horizons,
                    "ids": [[r, k] for r, k in res.window_ids]},
        "worlds": res.worlds,
        "echo_matching": {**asdict(res.echo_matching), "meaning": res.echo_matching.describe()},
        "seconds": res.seconds,
        "precision": res.precision,
        "notes": res.notes,
        "undefined_windows": {m: {str(h): v for h, v in d.items()} for m, d in undefined_counts(res).items()},
        **({"ceiling": {"method": CEILING, "meaning": CEILING_MEANING, "skipped_runs": res.ceiling_skipped},
            "observable": {"method": OBSERVABLE, "meaning": OBSERVABLE_MEANING,
                           "gap_closed_vs_flow": finite_or_none(res.gap_closed())}}
           if CEILING in res.methods or res.ceiling_skipped else {}),
        **({"fade": finite_or_none(fade),
            "fade_definition": {"echo_floor": ECHO_FLOOR, "tolerance": FADE_TOLERANCE,
                                "steps": list(range(1, max(res.horizons) + 1)),
                                "meaning": FADE_MEANING}} if fade else {}),
        "paper": {m: {k: {str(h): v for h, v in d.items()} for k, d in t.items()} for m, t in PAPER.items()},
    }


def write_per_window(res: EvalResult, path: str | os.PathLike) -> None:
    """One CSV row per method, horizon and window: its CC, NRMSD and echo metrics (empty: undefined)."""
    def cell(x: float):
        return float(x) if np.isfinite(x) else ""

    rows = [(m, h, f"{r}:{k}", *(cell(res.per_window[m][h][name][i]) for name in METRICS))
            for m in res.methods for h in res.horizons for i, (r, k) in enumerate(res.window_ids)
            if m not in CEILINGS or r not in res.ceiling_skipped]  # the ceilings have no row for runs they skipped
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "horizon", "window", *METRICS])
        w.writerows(rows)


def fade_table(res: EvalResult, fade: dict | None = None) -> str:
    """The "no fade" table: per method, the range of its peak and echo-energy ratios over the
    steps it forecast, and the verdict."""
    fade = fade_summary(res) if fade is None else fade
    lines = ["| method | peak ratio min | peak ratio max | energy ratio min | energy ratio max | verdict |",
             "|---|---|---|---|---|---|"]

    def rng(v):
        v = np.asarray(v, float)
        v = v[np.isfinite(v)]
        return (f"{v.min():.3f}", f"{v.max():.3f}") if len(v) else ("n/a", "n/a")

    for m, f in fade.items():
        checked = "scored horizon" if m in res.direct else "step"
        if f["within_15pct"]:
            verdict = f"no fade (within {FADE_TOLERANCE:.0%} at every {checked})"
        else:
            h = f["first_out"]
            p, e = (f[key][f["steps"].index(h)] for key in ("peak_ratio", "energy_ratio"))
            if np.isfinite(p) and np.isfinite(e):
                kind = "fades" if max((p, e), key=lambda r: abs(r - 1)) < 1 else "brightens"
            else:
                kind = "no window with echo energy"
            verdict = f"{kind} from step {h}" + (f" (steps checked: {', '.join(map(str, f['steps']))})"
                                                  if m in res.direct else "")
        lines.append(f"| {md_cell(m)} | " + " | ".join([*rng(f["peak_ratio"]), *rng(f["energy_ratio"])]) + f" | {verdict} |")
    return "\n".join(lines)


def results_table(res: EvalResult, with_paper: bool = True) -> str:
    s = res.summary()
    head = "| method | " + " | ".join(f"CC {horizon_name(h)}" for h in res.horizons) + " | " + \
           " | ".join(f"NRMSD {horizon_name(h)}" for h in res.horizons) + " |"
    lines = [head, "|---" * (1 + 2 * len(res.horizons)) + "|"]
    for m in res.methods:
        cells = [_cell(s[m][str(h)][k]) for k in IMAGE_METRICS for h in res.horizons]
        label = f"*{m} ({CEILING_LABELS[m]}, not a predictor)*" if m in CEILINGS else m
        lines.append(f"| {md_cell(label)} | " + " | ".join(cells) + " |")
        if with_paper and m in PAPER:
            p = PAPER[m]
            cells = [format_value(p["cc"][h], ".2f") if h in p["cc"] else "-" for h in res.horizons]
            cells += [format_value(p["nrmsd"][h], ".2f") if h in p["nrmsd"] else "-" for h in res.horizons]
            lines.append(f"| *{m} (paper)* | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def echo_table(res: EvalResult) -> str:
    """Echo F1, precision, recall and matched-echo position errors: mean over the windows where
    each is defined (n after the F1)."""
    s = res.summary()
    lines = ["| method | horizon | F1 (n) | precision | recall | range error cm | azimuth error deg |",
             "|---|---|---|---|---|---|---|"]
    for m in res.methods:
        for h in res.horizons:
            e = s[m][str(h)]
            f1 = e["echo_f1"]
            cells = [f"{_mean_only(f1)} ({f1.get('n', 0)})"] + [_mean_only(e[k]) for k in ECHO_METRICS[1:]]
            lines.append(f"| {md_cell(m)} | {horizon_name(h)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _mean_only(entry: dict) -> str:
    return "undefined" if entry["mean"] is None else f"{entry['mean']:.3f}"


def _cell(entry: dict) -> str:
    if entry["mean"] is None:
        return "undefined"
    return f"{entry['mean']:.3f} ({format_value(entry['std'], '.3f')})"


def render_report(res: EvalResult, figures: list[str]) -> str:
    """report.md: the results table, the statistics, the fade check, timing and ``figures``."""
    n = len(res.window_ids)
    parts = [
        "# Evaluation report",
        "",
        f"Store `{res.store}`, split `{res.split}` ({', '.join(res.runs)})"
        + (f", worlds {', '.join(res.worlds)}" if res.worlds else "") + f"; {n} windows drawn once "
        f"(seeded) and shared by every method and horizon. Mean (std) over windows; the paper's "
        "Table 1 values in italics below ours (its simulator differs: compare orderings and gaps, "
        "not absolute values). CC higher is better; NRMSD lower is better.",
        "",
        *[f"> {note}\n" for note in res.notes],
        results_table(res),
        *(["", f"*{CEILING}* is the {CEILING_MEANING} It is not a predictor and is left out of the "
               "statistics below."] if CEILING in res.methods else []),
        *(["", f"*{OBSERVABLE}* is the {OBSERVABLE_MEANING} Not a predictor either."] if OBSERVABLE in res.methods
          else []),
        *gap_section(res),
        "", "## Echoes", "",
        f"Are the echoes where the target's are? Per image, {res.echo_matching.describe()} (one-to-one, "
        "least summed distance; sonarset/scoring/echoes.py). F1 = 2 matched / (predicted + target echoes); precision and "
        "recall as usual; errors are the mean absolute offsets of matched echoes. Means over the windows "
        "where each is defined (F1: either image has an echo); paired tests in the statistics below.",
        "", echo_table(res),
        *statistics_section(res),
        *fade_section(res, figures),
        "", "## Timing", "",
        *[f"- {m}: {t:.2f} s to re-render the target frames" if m in CEILINGS else
          (f"- {m}: {t:.2f} s for {n} windows forecast at {', '.join(map(str, res.horizons))} steps ahead"
           if m in res.direct else
           f"- {m}: {t:.2f} s for {n} windows rolled out to {max(res.horizons)} steps")
          + (f" ({res.precision[m]})" if m in res.precision else "") for m, t in res.seconds.items()],
    ]
    if figures:
        parts += ["", "## Figures", ""]
        parts += [f"![{Path(f).stem}]({Path(f).name})" for f in figures]
    return "\n".join(parts) + "\n"


def gap_section(res: EvalResult) -> list[str]:
    """The share of the flow-to-observable-ceiling gap each predictor closes, per horizon."""
    gap = res.gap_closed()
    if not gap:
        return []
    s = res.summary()
    keys = ("cc", "nrmsd", "echo_f1")
    lines = ["", "## What the context could know", "",
             "Share of the gap between flow and the observable ceiling that each predictor closes: "
             "(method - flow) / (observable - flow) on the means (1: all the context allows; 0: no better "
             "than flow; negative: worse). The gap itself is the observable ceiling minus flow.", "",
             "| method | horizon | CC share | NRMSD share | echo F1 share |", "|---|---|---|---|---|"]
    for h in res.horizons:
        cells = [_gap(s[OBSERVABLE][str(h)][k]["mean"], s["flow"][str(h)][k]["mean"]) for k in keys]
        lines.append(f"| *gap (observable - flow)* | {horizon_name(h)} | " + " | ".join(cells) + " |")
    for m, per in gap.items():
        for h in res.horizons:
            cells = ["undefined" if per[str(h)][k] is None else f"{per[str(h)][k]:.2f}" for k in keys]
            lines.append(f"| {md_cell(m)} | {horizon_name(h)} | " + " | ".join(cells) + " |")
    return lines


def statistics_section(res: EvalResult) -> list[str]:
    """The report's paired comparisons: one table row per horizon, metric and pair of methods."""
    lines = [
        "",
        "## Statistics",
        "",
        "Per horizon and metric, each pair of methods on the same windows: mean difference (a - b) "
        "with a bootstrap 95% CI (BCa, 2000 resamples); the paper's two-sample t-test (Welch); the "
        "paired t-test and Wilcoxon signed-rank test on per-window differences; the paired t-test's "
        f"p adjusted by Holm over all {len(res.comparisons)} comparisons; and the paired test with the "
        "windows' serial correlation in its variance (windows of one run share frames and scene: "
        f"Newey-West, a Bartlett kernel reaching {HAC_SPANS} window spans), Holm-adjusted alike.",
        "",
        "| horizon | metric | a | b | mean(a-b) | 95% CI | 2-sample t p | paired t p | Wilcoxon p | Holm p "
        "| serial-robust p | its Holm p | better |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in res.comparisons:
        better = "-"
        if c.p_holm is not None and np.isfinite(c.p_holm) and c.p_holm < 0.05:
            a_better = (c.mean_diff < 0) if LOWER_IS_BETTER[c.metric] else (c.mean_diff > 0)
            better = c.a if a_better else c.b
        why = "n/a (one window)" if c.n < 2 else "n/a (undefined)"
        lines.append(f"| {horizon_name(c.horizon)} | {c.metric} | "
                     f"{md_cell(c.a)} | {md_cell(c.b)} | {format_value(c.mean_diff, '+.4f', why)} | "
                     f"{format_interval(c.ci_low, c.ci_high, '+.4f', why)} | "
                     f"{format_p(c.t_two_sample_p)} | {format_p(c.t_paired_p)} | "
                     f"{format_p(c.wilcoxon_p)} | {format_p(c.p_holm)} | {format_p(c.t_hac_p)} | "
                     f"{format_p(c.p_hac_holm)} | {better} |")
    return lines


def fade_section(res: EvalResult, figures: list[str]) -> list[str]:
    """The report's "no fade" section (none when the result has no step data)."""
    fade = fade_summary(res)
    if not fade:
        return []
    drawn = any(Path(f).name == "fade.png" for f in figures)
    return ["", "## No fade", "",
            f"Over the rollouts to {max(res.horizons)} steps (a method that forecasts each horizon directly: "
            "at the scored horizons): mean prediction / target ratio of the peak pixel and of the echo energy "
            f"(the sum of the pixels above {ECHO_FLOOR}), a ratio of means over the windows whose target has echo "
            "energy at that step; min and max over the steps. "
            f"No fade: both ratios within {FADE_TOLERANCE:.0%} of 1 at every step checked "
            "(per step in metrics.json, `fade`" + ("; the figure `fade.png`)." if drawn else ")."),
            "", fade_table(res, fade)]


def _gap(observable: float | None, flow: float | None) -> str:
    """The observable ceiling's lead over flow, or why there is none."""
    if observable is None or flow is None:
        return "undefined"
    return format_value(observable - flow, "+.3f", "undefined")
