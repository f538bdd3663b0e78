"""The slip experiment's report: metrics.json, report.md and the paper's Fig. 5, from a
:class:`~.slip.SlipResult` (computed by :func:`~.slip.run_slip_experiment`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from sonarset.report.plots import pyplot
from sonarset.report.numbers import format_interval, format_p, format_value, horizon_name

from sonarset.models.experiments.common import write_outputs
from sonarset.models.experiments.slip import DETECTORS, HORIZONS, KINDS, SlipPeriod, SlipResult

DETECTOR_TEXT = {
    "eps": "the paper's eps(t) = ||I_p - I_m|| / sqrt(|CC|)",
    "ratio": "eps(predictor) / eps(persistence)",
}
FIGURE = "fig5_slip.png"


def write_slip_report(res: SlipResult, out: str | os.PathLike) -> Path:
    """metrics.json, fig5_slip.png and report.md in ``out`` (created)."""
    lines = [*auc_table(res), *tests_table(res), *paper_trajectory_table(res),
             "", f"![Fig. 5]({FIGURE})", "", f"{res.seconds:.0f} s in all"
             + "".join(f"; {m} computed in {p}" for m, p in res.precision.items()) + "."]
    return write_outputs(out, slip_metrics(res), fig5(res), FIGURE, lines)


def slip_metrics(res: SlipResult) -> dict:
    """The metrics.json document."""
    return {
        "experiment": "slip",
        "models": res.models,
        "trials": res.trials,
        "horizons": list(HORIZONS),
        "detectors": DETECTOR_TEXT,
        "auc": res.summary,
        "tests": res.comparisons,
        "per_trial_auc": res.per_trial,
        "paper_trajectory": {"trial": res.paper["trial"], "signal_ratio": res.signal_ratios},
        "processing": res.processing.model_dump(),
        "precision": res.precision,
        "seconds": res.seconds,
    }


def _header(cell: str) -> list[str]:
    """A predictor | horizon table's header, one column per detector and slip kind."""
    return ["| predictor | horizon | " + " | ".join(cell.format(d=d) for d in DETECTORS) + " |",
            "| --- | ---: | " + " | ".join("---: | ---:" for _ in DETECTORS) + " |"]


def auc_table(res: SlipResult) -> list[str]:
    """The title, what was measured, and the mean AUC [CI] per predictor, horizon, detector and kind."""
    by = {(s["predictor"], s["horizon"], s["kind"], s["detector"]): s for s in res.summary}
    lines = [
        "# Wheel-slip detection (EchoPT paper, Fig. 5)", "",
        f"{res.trials} random 60 s trajectories in lab worlds, each with one both-wheel and one one-wheel slip "
        "period (3-8 s, wheel speed factors U(0, 0.5)); the logged commands never change. Per trajectory, the "
        "ROC AUC of the detector signal separating frames reached through slip from slip-free frames; mean "
        "over trajectories with a bootstrap 95% CI. 0.5 is chance, below 0.5 the signal drops during slip. "
        f"Images: {res.processing.describe()} (the models' training images).", "",
        *_header("{d}: both wheels | {d}: one wheel"),
    ]
    for name in res.names:
        for h in HORIZONS:
            cells = []
            for det in DETECTORS:
                for kind in KINDS:
                    x = by[(name, h, kind, det)]
                    cells.append(_auc_cell(x))
            lines.append(f"| {name} | {horizon_name(h)} | " + " | ".join(cells) + " |")
    return lines + ["", "Detectors: " + "; ".join(f"`{k}` is {v}" for k, v in DETECTOR_TEXT.items()) + "."]


def tests_table(res: SlipResult) -> list[str]:
    """Each learned predictor against each baseline and each learned predictor before it (paired
    Wilcoxon, Holm); nothing without a learned predictor."""
    if not res.comparisons:
        return []
    lines = ["", "Each learned predictor against each baseline and each learned predictor listed before it, "
             "paired Wilcoxon signed-rank tests on per-trajectory AUC (Holm-corrected over all rows):", "",
             "| detector | a - b | horizon | kind | mean AUC difference | p (Holm) |",
             "| --- | --- | ---: | --- | ---: | ---: |"]
    for c in res.comparisons:
        lines.append(f"| {c['detector']} | {c['a']} - {c['b']} | {horizon_name(c['horizon'])} | {c['kind']} | "
                     f"{format_value(c['mean_auc_diff'], '+.3f', 'n/a (no trials)')} | {format_p(c['p_holm'])} |")
    return lines


def paper_trajectory_table(res: SlipResult) -> list[str]:
    """The paper's trajectory: its slip periods and each signal's rise during them."""
    p0, p1 = res.paper["trial"]["periods"]
    lines = ["", "## The paper's trajectory", "",
             f"Both wheels slip (factors {tuple(p0['factors'])}) from {p0['start_s']:g} s to {p0['end_s']:g} s, one "
             f"wheel ({tuple(p1['factors'])}) from {p1['start_s']:g} s to {p1['end_s']:g} s. Median signal during "
             "each slip period over its median in slip-free frames (> 1: the slip raises it):", "",
             *_header("{d}: both | {d}: one")]
    for name in res.names:
        for h in HORIZONS:
            cells = [format_value(res.signal_ratios[f"{name}|{h}|{det}"][kind], ".2f") for det in DETECTORS for kind in KINDS]
            lines.append(f"| {name} | {horizon_name(h)} | " + " | ".join(cells) + " |")
    return lines


def fig5(res: SlipResult):
    """Detector signals over time on the paper's trajectory: a row per predictor, a column per
    detector, a curve per horizon (each over its slip-free median), slip periods shaded."""
    plt = pyplot()
    paper, names = res.paper, res.names
    t = np.arange(len(paper["slip"])) * res.rig.frame_interval_s
    fig, axes = plt.subplots(len(names), len(DETECTORS), figsize=(13, 2.4 * len(names)), sharex=True, squeeze=False)
    colors = {"both": "tab:red", "one": "tab:orange"}
    for i, name in enumerate(names):
        for j, det in enumerate(DETECTORS):
            ax = axes[i, j]
            for p in paper["trial"]["periods"]:
                kind = SlipPeriod(p["start_s"], p["end_s"], tuple(p["factors"])).kind
                ax.axvspan(p["start_s"], p["end_s"], color=colors[kind], alpha=0.15,
                           label="both wheels slip" if kind == "both" else "one wheel slips")
            for h in HORIZONS:
                sig = paper["signals"][f"{name}|{h}|{det}"]
                clean = paper["labels"][f"{name}|{h}"]["clean"]
                ax.plot(t, sig / np.nanmedian(sig[clean]), lw=1.0, label=horizon_name(h))
            # log: eps divides by sqrt(|CC|), so a single forecast with CC near 0 is a spike of
            # 1000x that would flatten every other curve on a linear axis
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
            if j == 0:
                ax.set_ylabel(f"{name}\nsignal / slip-free median")
            if i == 0:
                ax.set_title(DETECTOR_TEXT[det], fontsize=10)
    axes[0, 0].legend(loc="upper left", fontsize=7, ncol=5)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle("Wheel-slip detection signals on the paper's trajectory (EchoPT paper, Fig. 5)")
    fig.tight_layout()
    return fig


def _auc_cell(x: dict) -> str:
    """``mean [CI]`` of an AUC, or why there is none (an AUC needs slip-free and slipping frames)."""
    why = "n/a (no slip-free and slipping frames)"
    mean = format_value(x["auc_mean"], ".2f", why)
    return mean if mean == why else f"{mean} {format_interval(x['ci_low'], x['ci_high'], '.2f', '[n/a]')}"
