"""The control experiment's report: metrics.json, report.md and the paper's Fig. 6, from a
:class:`~.control.ControlResult` (computed by :func:`~.control.run_control_experiment`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy import ndimage

from sonarset.sim.control import BurstDetector
from sonarset.report.plots import pyplot
from sonarset.report.numbers import format_interval, format_p, format_value
from sonarset.sim.families import corridor_world
from sonarset.sim.world import World

from sonarset.models.experiments.common import write_outputs
from sonarset.models.experiments.control import GOAL_RADIUS, BurstSchedule, ControlResult

FIGURE = "fig6_control.png"
#: What metrics.json keeps of each run (the trajectories and per-frame flags stay out).
PER_RUN_KEYS = ("index", "condition", "outcome", "travel_time_s", "midline_deviation_m", "layers")


def write_control_report(res: ControlResult, out: str | os.PathLike) -> Path:
    """metrics.json, fig6_control.png and report.md in ``out`` (created)."""
    lines = [*outcome_table(res), *tests_table(res), *detector_and_gains(res),
             "", f"![Fig. 6]({FIGURE})", "", f"![episodes]({ANIMATION}) — the first run of each condition "
             "moving: red while a noise burst is on, green where a prediction bridged the frame.",
             "", f"{res.seconds:.0f} s in all"
             + "".join(f"; {m} computed in {p}" for m, p in res.precision.items()) + "."]
    return write_outputs(out, control_metrics(res), fig6(res), FIGURE, lines,
                         extra=lambda folder: episodes_animation(res, folder / ANIMATION))


ANIMATION = "episodes.gif"


def episodes_animation(res: ControlResult, path: Path, steps: int = 48, fps: float = 6.0) -> Path:
    """The first episode of each condition moving along its path, one panel per condition, in at
    most ``steps`` GIF frames (Pillow through matplotlib's canvas)."""
    import numpy as np

    from sonarset.report.plots import pyplot, save_animation

    plt = pyplot()
    shown = [(c, eps[0]) for c, eps in res.episodes.items() if eps]
    fig, axes = plt.subplots(1, len(shown), figsize=(2.6 * len(shown), 2.8), squeeze=False, dpi=72,
                             gridspec_kw=dict(left=0.03, right=0.98, bottom=0.05, top=0.85, wspace=0.1))
    markers, longest = [], max(len(ep["pose"]) for _, ep in shown)
    for ax, (condition, ep) in zip(axes[0], shown):
        pose = np.asarray(ep["pose"])
        ax.plot(pose[:, 0], pose[:, 1], color="0.75", lw=1)
        ax.set_title(f"{condition}\n{ep['outcome']}", fontsize=8)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        markers.append(ax.plot([], [], "o", ms=6)[0])
    def step(k: int) -> None:
        for marker, (_, ep) in zip(markers, shown):
            i = min(k, len(ep["pose"]) - 1)
            j = min(i, len(ep["burst"]) - 1)
            marker.set_data([ep["pose"][i][0]], [ep["pose"][i][1]])
            marker.set_color("tab:green" if ep["predicted"][j] else "tab:red" if ep["burst"][j] else "tab:blue")

    steps_shown = np.unique(np.linspace(0, longest - 1, min(steps, longest)).round().astype(int))
    return save_animation(fig, step, steps_shown, path, fps)


def control_metrics(res: ControlResult) -> dict:
    """The metrics.json document."""
    per_run = [{k: v for k, v in r.items() if k in PER_RUN_KEYS} for rs in res.episodes.values() for r in rs]
    return {"experiment": "control", "model": res.model, "runs": res.runs, "conditions": list(res.episodes),
            "summary": res.summary, "tests": res.comparisons, "burst_detector": res.detector,
            "controller_gains": res.gains, "processing": res.processing.model_dump(), "per_run": per_run,
            "precision": res.precision, "seconds": res.seconds}


def outcome_table(res: ControlResult) -> list[str]:
    """The title, the setup, and per condition: outcomes, travel time and midline deviation."""
    bursts = BurstSchedule()  # every episode's
    lines = ["# Corridor control through noise bursts (EchoPT paper, Fig. 6)", "",
             f"{res.runs} runs per condition from the same random spawn poses; bursts: SNR {bursts.snr_db:g} dB for "
             f"{bursts.burst_s:g} s, about {bursts.duty:.0%} of the time; predictors bridging the bursts: "
             f"`{res.model}`. Images: "
             f"{res.processing.describe()} (the bridging models' training images).", "",
             "| condition | success | collision | timeout | success rate 95% CI | travel time [s] mean [CI] (median) | "
             "midline deviation [m] mean [CI] |", "| --- | ---: | ---: | ---: | --- | --- | --- |"]
    for c, s in res.summary.items():
        tt, dv = s["travel_time_s"], s["midline_deviation_m"]
        lines.append(f"| {c} | {s['success']} | {s['collision']} | {s['timeout']} | "
                     f"{s['success_rate_ci'][0]:.2f}-{s['success_rate_ci'][1]:.2f} | "
                     f"{_mean_ci(tt, '.1f', 'n/a (no robot arrived)', median=True)} | "
                     f"{_mean_ci(dv, '.3f', 'n/a (no episode)')} |")
    return lines


def _mean_ci(stat: dict, spec: str, why: str, median: bool = False) -> str:
    """``mean [CI]`` (and ``(median)``) of a summary, or why it has none."""
    mean = format_value(stat["mean"], spec, why)
    if mean == why:
        return why
    text = f"{mean} {format_interval(stat['ci_low'], stat['ci_high'], spec, '[n/a]')}"
    return text + (f" ({format_value(stat['median'], spec)})" if median else "")


def tests_table(res: ControlResult) -> list[str]:
    """The paired tests between conditions."""
    lines = ["", "Paired tests between conditions (same spawn poses): Wilcoxon signed-rank on travel time (runs "
             "that succeeded in both) and deviation, McNemar's exact test on success; Holm-corrected.", "",
             "| a vs b | metric | pairs | mean a - b | p (Holm) |", "| --- | --- | ---: | ---: | ---: |"]
    for c in res.comparisons:
        lines.append(f"| {c['a']} vs {c['b']} | {c['metric']} | {c['n_pairs']} | "
                     f"{format_value(c['mean_diff'], '+.3f', 'n/a (no pairs)')} | "
                     f"{format_p(c['p_holm'])} |")
    return lines


def detector_and_gains(res: ControlResult) -> list[str]:
    """The burst detector's scores and the controller's gains, a sentence each."""
    det = res.detector
    return ["", f"Burst detector (range bins with a pixel above {BurstDetector.level} > {BurstDetector.max_coverage:.0%}): "
            + "; ".join(f"{c}: recall {format_value(d['recall'], '.3f')}, precision {format_value(d['precision'], '.3f')} "
                          f"over {d['frames']} frames"
                        for c, d in det.items() if isinstance(d, dict))
            + (f"; false alarms on clean frames {format_value(det['false_positive_rate_clean'], '.4f')}"
               if "false_positive_rate_clean" in det else "") + ".",
            "", "Controller gains: " + ", ".join(f"{k} = {v}" for k, v in res.gains.items()) + "."]


def fig6(res: ControlResult):
    """a-c trajectory densities per condition, d travel times, e midline deviations, f an SNR trace."""
    plt = pyplot()
    world = corridor_world()
    conds = list(res.episodes)
    fig = plt.figure(figsize=(13, 2.2 * len(conds) + 3))
    gs = fig.add_gridspec(len(conds) + 1, 3)
    for i, c in enumerate(conds):
        trajectory_density(fig.add_subplot(gs[i, :]), world, res, c, chr(ord("a") + i))
    letter = lambda k: chr(ord("a") + len(conds) + k)  # noqa: E731 - panel letters after the maps
    box_panel(fig.add_subplot(gs[-1, 0]), res, "travel_time_s", "travel time [s]",
              f"{letter(0)}) travel time (successful runs)")
    box_panel(fig.add_subplot(gs[-1, 1]), res, "midline_deviation_m", "mean |y| [m]", f"{letter(1)}) midline deviation")
    snr_panel(fig.add_subplot(gs[-1, 2]), res, letter(2))
    fig.suptitle("Corridor control through noise bursts (EchoPT paper, Fig. 6)")
    fig.tight_layout()
    return fig


def trajectory_density(ax, world: World, res: ControlResult, condition: str, letter: str) -> None:
    """Where the runs of one condition drove, over the corridor's reflectors, spawn boxes and goal."""
    plt = pyplot()
    x_edges = np.arange(-0.5, world.waypoint[0] + 1.0, 0.02)
    y_edges = np.arange(-1.2, 1.2 + 1e-9, 0.02)
    pts = np.concatenate([r["pose"][:, :2] for r in res.episodes[condition]])
    # Trajectory density: a Gaussian kernel density estimate on a 2 cm grid (5 cm kernel),
    # with a fixed bandwidth so that conditions compare; square-root colour scale.
    hist, _, _ = np.histogram2d(pts[:, 0], pts[:, 1], bins=[x_edges, y_edges])
    dens = ndimage.gaussian_filter(hist, 2.5)
    ax.pcolormesh(x_edges, y_edges, np.sqrt(dens.T / max(dens.max(), 1e-12)), cmap="viridis", shading="flat")
    ax.scatter(world.circ_c[:, 0], world.circ_c[:, 1], s=12, c="tab:red", label="reflectors")
    for box in world.spawn:
        ax.add_patch(plt.Rectangle((box.x[0], box.y[0]), box.x[1] - box.x[0], box.y[1] - box.y[0],
                                   fill=False, ec="lime", lw=1.5))
    ax.add_patch(plt.Circle(world.waypoint, GOAL_RADIUS, fill=False, ec="lime", lw=1.5))
    s = res.summary[condition]
    ax.set_title(f"{letter}) {condition}: {s['success']}/{s['runs']} reached, {s['collision']} collisions",
                 fontsize=10, loc="left")
    ax.set_aspect("equal")
    ax.set_xlim(x_edges[0], x_edges[-1])
    ax.set_ylim(y_edges[0], y_edges[-1])


def box_panel(ax, res: ControlResult, key: str, ylabel: str, title: str) -> None:
    """A box per condition of one per-run value (runs where it is undefined left out)."""
    conds = list(res.episodes)
    ax.boxplot([[r[key] for r in res.episodes[c] if np.isfinite(r[key])] or [np.nan] for c in conds],
               tick_labels=conds)
    ax.tick_params(axis="x", labelrotation=15)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10, loc="left")


def snr_panel(ax, res: ControlResult, letter: str) -> None:
    """The effective SNR over the first 30 s of the first run with bursts."""
    conds = list(res.episodes)
    trace = next((r for c in conds if c != "clean" for r in res.episodes[c]), None) or res.episodes[conds[0]][0]
    t = np.arange(len(trace["snr_db"])) * res.rig.frame_interval_s
    ax.plot(t, np.clip(trace["snr_db"], -100, 40), lw=1)
    ax.set_xlim(0, min(30, t[-1] if len(t) else 30))
    ax.set_xlabel("time [s]")
    ax.set_ylabel("SNR at the microphones [dB]")
    ax.set_title(f"{letter}) effective SNR, run 0 of {trace['condition']}", fontsize=10, loc="left")
