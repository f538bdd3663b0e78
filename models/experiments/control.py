"""Corridor control through noise bursts (the paper's Fig. 6).

A robot spawns in the corridor world's spawn box and drives to its waypoint with the subsumption
controller of :mod:`sonarset.control`, which sees only sonar images and odometry. Three conditions,
run from the same spawn poses and (for the last two) the same burst schedules:

- ``clean``: every frame at the nominal SNR (5 dB);
- ``bursts``: noise bursts (SNR -80 dB for 1.2 s, about 30% of the time) reach the controller;
- ``bursts+<model>``: a burst detector on each image replaces burst frames by the model's
  auto-regressive forecast from the last three frames the controller used and the commands
  (the paper's condition with EchoPT; any predictor spec works, e.g. ``flow`` for comparison).

A run ends at the waypoint (success), on contact with a pole (collision) or after ``max_time_s``
(timeout). Reported per condition: success/collision/timeout counts with Wilson CIs, travel time
and mean absolute midline deviation with bootstrap CIs, and paired tests between conditions.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy import ndimage, stats

from sonarset.control import BurstDetector, ControllerGains, SubsumptionController
from sonarset.atomic import atomic_text, save_figure
from sonarset.schema import Processing, SensorGrid
from sonarset.sim.generate import DT, spawn_seeds
from sonarset.sim.robot import ROBOT_RADIUS, integrate
from sonarset.sim.sonar import SonarModel
from sonarset.sim.world import World, corridor_world
from sonarset.report import format_p
from sonarset.stats import holm, wilcoxon_p

from .common import experiment_processing, finite_or_none, mean_ci, parallel_map, predictor

CONDITIONS = ("clean", "bursts")  # plus one "bursts+<model>" condition per predictor
N_IN = 3
GOAL_RADIUS = 0.4  # m: a run succeeds when the robot centre comes this close to the waypoint


@dataclass(frozen=True)
class BurstSchedule:
    """Noise bursts of fixed length separated by exponential gaps, set for a target duty cycle."""

    burst_s: float = 1.2
    duty: float = 0.3
    snr_db: float = -80.0

    def frames(self, rng: np.random.Generator, n: int) -> np.ndarray:
        on = np.zeros(n, bool)
        mean_gap = self.burst_s * (1 - self.duty) / self.duty
        k = int(round(rng.exponential(mean_gap) / DT))
        length = max(1, int(round(self.burst_s / DT)))
        while k < n:
            on[k:k + length] = True
            k += length + max(1, int(round(rng.exponential(mean_gap) / DT)))
        return on


@dataclass(frozen=True)
class Episode:
    index: int
    seed: int
    condition: str  # "clean", "bursts" or "bursts+<predictor spec>"
    grid: SensorGrid
    snr_db: float = 5.0
    max_time_s: float = 120.0
    bursts: BurstSchedule = BurstSchedule()
    gains: ControllerGains = ControllerGains()
    device: str = "cpu"
    processing: Processing = field(default_factory=Processing.ertis)  # the simulator's default images


def run_episode(ep: Episode, world: World | None = None) -> dict:
    """Drive one run; returns its trajectory, per-frame SNR, burst and prediction flags, and outcome."""
    world = world or corridor_world()
    spawn_ss, burst_ss, noise_ss = np.random.SeedSequence(ep.seed).spawn(3)
    pose = world.sample_spawn(np.random.default_rng(spawn_ss))
    n_max = int(round(ep.max_time_s / DT))
    burst = BurstSchedule.frames(ep.bursts, np.random.default_rng(burst_ss), n_max) if ep.condition != "clean" \
        else np.zeros(n_max, bool)
    noise_rng = np.random.default_rng(noise_ss)
    model = SonarModel(ep.grid, snr_db=ep.snr_db, processing=ep.processing)
    ctrl = SubsumptionController(ep.grid, world.waypoint, ep.gains)
    detector = BurstDetector()
    spec = ep.condition.partition("+")[2]
    pred = predictor(spec, ep.grid, ep.device) if spec else None
    frames: list[np.ndarray] = []  # what the controller saw
    commands = [np.zeros(2, np.float32)]  # commands[k] moved the robot into frame k
    poses, snr, flagged, predicted, layers = [], [], [], [], []
    outcome = "timeout"
    for k in range(n_max):
        img, eff = model.render(world, pose, noise_rng, snr_db=ep.bursts.snr_db if burst[k] else None, return_snr=True)
        is_burst = detector(img)
        used = img
        if pred is not None and is_burst and len(frames) >= N_IN:
            window = np.stack(frames[-N_IN:])[None]
            cmds = np.stack(commands[-(N_IN + 1):])[None]
            used = pred.predict(window, cmds)[0]
        frames.append(np.asarray(used, np.float32))
        del frames[:-N_IN]
        decision = ctrl(used, pose)  # odometry: no slip here, so it is the true pose
        poses.append(pose), snr.append(eff), flagged.append(is_burst), predicted.append(used is not img)
        layers.append(decision.layer)
        if np.hypot(*(world.waypoint - pose[:2])) < GOAL_RADIUS:
            outcome = "success"
            break
        pose = integrate(pose, decision.v, decision.w, DT)
        commands.append(np.array([decision.v, decision.w], np.float32))
        del commands[:-(N_IN + 1)]
        if world.clearance(pose[None, :2])[0] < ROBOT_RADIUS:
            poses.append(pose)
            outcome = "collision"
            break
    poses = np.array(poses)
    n = len(snr)
    inside = (poses[:, 0] >= 0) & (poses[:, 0] <= world.waypoint[0])
    return {
        "index": ep.index, "condition": ep.condition, "outcome": outcome,
        "travel_time_s": n * DT if outcome == "success" else float("nan"),
        "midline_deviation_m": float(np.abs(poses[inside, 1]).mean()) if inside.any() else float("nan"),
        "pose": poses, "snr_db": np.array(snr), "burst": burst[:n], "flagged": np.array(flagged),
        "predicted": np.array(predicted), "layers": {k: layers.count(k) for k in ("avoid", "corridor", "goal")},
    }


@dataclass
class ControlResult:
    model: str
    runs: int
    episodes: dict  # condition -> list of run_episode results
    summary: dict = field(default_factory=dict)
    comparisons: list[dict] = field(default_factory=list)
    detector: dict = field(default_factory=dict)
    gains: dict = field(default_factory=dict)
    seconds: float = 0.0
    processing: Processing = field(default_factory=Processing.ertis)  # the images simulated


def condition_name(spec: str) -> str:
    """``bursts+echopt`` for ``echopt:pretrained``; the spec itself for other checkpoints' paths."""
    return "bursts+" + (spec.partition(":")[0] if spec.partition(":")[2] in ("", "pretrained") else spec)


def run_control_experiment(models: list[str] | tuple[str, ...] = ("echopt:pretrained",), runs: int = 50, seed: int = 0,
                           grid: SensorGrid | None = None, workers: int | None = None, device: str = "cpu",
                           max_time_s: float = 120.0, progress: Callable[[int, int], None] | None = None,
                           processing: Processing | str | None = None) -> ControlResult:
    """``runs`` runs in each condition: clean, bursts, and bursts bridged by each model in ``models``.

    The images are those the models were trained on; ``processing`` only checks that (see
    :func:`~.common.experiment_processing`)."""
    grid = grid or SensorGrid.default()
    t0 = time.perf_counter()
    for m in models:
        predictor(m, grid, device)  # fail fast on a bad model
    processing = experiment_processing(models, processing)
    conditions = [*CONDITIONS, *(f"bursts+{m}" for m in models)]
    seeds = spawn_seeds(seed, runs)  # run i uses the same spawn, bursts and noise seed in every condition
    eps = [Episode(i, s, c, grid, max_time_s=max_time_s, device=device, processing=processing)
           for c in conditions for i, s in enumerate(seeds)]
    results = parallel_map(run_episode, eps, workers, progress)
    names = {c: condition_name(c.partition("+")[2]) if "+" in c else c for c in conditions}
    by = {names[c]: [dict(r, condition=names[c]) for r in results if r["condition"] == c] for c in conditions}
    res = ControlResult(", ".join(models), runs, by, gains=ControllerGains().to_dict(), processing=processing)
    res.summary, res.comparisons, res.detector = summarise(by, seed)
    res.seconds = time.perf_counter() - t0
    return res


def _wilson(k: int, n: int) -> tuple[float, float]:
    ci = stats.binomtest(k, n).proportion_ci(method="wilson") if n else None
    return (float(ci.low), float(ci.high)) if ci else (float("nan"), float("nan"))


def summarise(by: dict, seed: int = 0) -> tuple[dict, list[dict], dict]:
    summary = {}
    for c, rs in by.items():
        n = len(rs)
        counts = {o: sum(r["outcome"] == o for r in rs) for o in ("success", "collision", "timeout")}
        tt = np.array([r["travel_time_s"] for r in rs])
        dev = np.array([r["midline_deviation_m"] for r in rs])
        frames = sum(len(r["burst"]) for r in rs)
        summary[c] = {
            "runs": n, **counts, "success_rate_ci": _wilson(counts["success"], n),
            "travel_time_s": dict(zip(("mean", "ci_low", "ci_high"), mean_ci(tt, seed)),
                                  median=float(np.nanmedian(tt)) if np.isfinite(tt).any() else float("nan")),
            "midline_deviation_m": dict(zip(("mean", "ci_low", "ci_high"), mean_ci(dev, seed))),
            "burst_time_fraction": sum(int(r["burst"].sum()) for r in rs) / max(frames, 1),
            "predicted_frames": sum(int(r["predicted"].sum()) for r in rs),
        }
    comps = []
    names = list(by)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            for metric in ("travel_time_s", "midline_deviation_m"):
                x = np.array([r[metric] for r in by[a]]) - np.array([r[metric] for r in by[b]])
                x = x[np.isfinite(x)]  # runs that reached the goal in both conditions, for travel time
                p = wilcoxon_p(x)
                comps.append({"a": a, "b": b, "metric": metric, "n_pairs": len(x),
                              "mean_diff": float(x.mean()) if len(x) else float("nan"), "wilcoxon_p": p})
            sa = np.array([r["outcome"] == "success" for r in by[a]])
            sb = np.array([r["outcome"] == "success" for r in by[b]])
            # McNemar's exact test on the discordant pairs of the paired runs
            n01, n10 = int((~sa & sb).sum()), int((sa & ~sb).sum())
            p = float(stats.binomtest(n10, n01 + n10).pvalue) if n01 + n10 else float("nan")
            comps.append({"a": a, "b": b, "metric": "success", "n_pairs": len(sa),
                          "mean_diff": float(sa.mean() - sb.mean()), "mcnemar_p": p})
    for c, p in zip(comps, holm([c.get("wilcoxon_p", c.get("mcnemar_p")) for c in comps])):
        c["p_holm"] = p
    detector = {}
    for c, rs in by.items():
        truth = np.concatenate([r["burst"] for r in rs])
        flag = np.concatenate([r["flagged"] for r in rs])
        if c == "clean":
            detector["false_positive_rate_clean"] = float(flag.mean()) if len(flag) else float("nan")
            continue
        detector[c] = {"frames": len(truth), "bursts": int(truth.sum()),
                       "recall": float((flag & truth).sum() / max(truth.sum(), 1)),
                       "precision": float((flag & truth).sum() / max(flag.sum(), 1))}
    return summary, comps, detector


def write_control_report(res: ControlResult, out: str | os.PathLike) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    per_run = [{k: v for k, v in r.items() if k in ("index", "condition", "outcome", "travel_time_s",
                                                    "midline_deviation_m", "layers")}
               for rs in res.episodes.values() for r in rs]
    doc = {"experiment": "control", "model": res.model, "runs": res.runs, "conditions": list(res.episodes),
           "summary": res.summary, "tests": res.comparisons, "burst_detector": res.detector,
           "controller_gains": res.gains, "processing": res.processing.model_dump(), "per_run": per_run,
           "seconds": res.seconds}
    atomic_text(out / "metrics.json", json.dumps(finite_or_none(doc), indent=2) + "\n")
    fig_path = out / "fig6_control.png"
    save_figure(fig6(res), fig_path)
    lines = ["# Corridor control through noise bursts (EchoPT paper, Fig. 6)", "",
             f"{res.runs} runs per condition from the same random spawn poses; bursts: SNR -80 dB for 1.2 s, "
             f"about 30% of the time; predictors bridging the bursts: `{res.model}`. Images: "
             f"{res.processing.describe()} (the bridging models' training images).", "",
             "| condition | success | collision | timeout | success rate 95% CI | travel time [s] mean [CI] (median) | "
             "midline deviation [m] mean [CI] |", "| --- | ---: | ---: | ---: | --- | --- | --- |"]
    for c, s in res.summary.items():
        tt, dv = s["travel_time_s"], s["midline_deviation_m"]
        lines.append(f"| {c} | {s['success']} | {s['collision']} | {s['timeout']} | "
                     f"{s['success_rate_ci'][0]:.2f}-{s['success_rate_ci'][1]:.2f} | "
                     f"{tt['mean']:.1f} [{tt['ci_low']:.1f}, {tt['ci_high']:.1f}] ({tt['median']:.1f}) | "
                     f"{dv['mean']:.3f} [{dv['ci_low']:.3f}, {dv['ci_high']:.3f}] |")
    lines += ["", "Paired tests between conditions (same spawn poses): Wilcoxon signed-rank on travel time (runs "
              "that succeeded in both) and deviation, McNemar's exact test on success; Holm-corrected.", "",
              "| a vs b | metric | pairs | mean a - b | p (Holm) |", "| --- | --- | ---: | ---: | ---: |"]
    for c in res.comparisons:
        lines.append(f"| {c['a']} vs {c['b']} | {c['metric']} | {c['n_pairs']} | {c['mean_diff']:+.3f} | "
                     f"{format_p(c['p_holm'])} |")
    det = res.detector
    lines += ["", f"Burst detector (range bins with a pixel above {BurstDetector.level} > {BurstDetector.max_coverage:.0%}): "
              + "; ".join(f"{c}: recall {d['recall']:.3f}, precision {d['precision']:.3f} over {d['frames']} frames"
                          for c, d in det.items() if isinstance(d, dict))
              + (f"; false alarms on clean frames {det['false_positive_rate_clean']:.4f}"
                 if "false_positive_rate_clean" in det else "") + ".",
              "", "Controller gains: " + ", ".join(f"{k} = {v}" for k, v in res.gains.items()) + ".",
              "", f"![Fig. 6]({fig_path.name})", "", f"{res.seconds:.0f} s in all."]
    atomic_text(out / "report.md", "\n".join(lines) + "\n")
    return out


def fig6(res: ControlResult):
    """a-c trajectory densities per condition, d travel times, e midline deviations, f an SNR trace."""
    from sonarset.plots import pyplot

    plt = pyplot()

    world = corridor_world()
    conds = list(res.episodes)
    fig = plt.figure(figsize=(13, 2.2 * len(conds) + 3))
    gs = fig.add_gridspec(len(conds) + 1, 3)
    x_edges = np.arange(-0.5, world.waypoint[0] + 1.0, 0.02)
    y_edges = np.arange(-1.2, 1.2 + 1e-9, 0.02)
    for i, c in enumerate(conds):
        ax = fig.add_subplot(gs[i, :])
        pts = np.concatenate([r["pose"][:, :2] for r in res.episodes[c]])
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
        s = res.summary[c]
        ax.set_title(f"{chr(ord('a') + i)}) {c}: {s['success']}/{s['runs']} reached, {s['collision']} collisions",
                     fontsize=10, loc="left")
        ax.set_aspect("equal")
        ax.set_xlim(x_edges[0], x_edges[-1])
        ax.set_ylim(y_edges[0], y_edges[-1])
    ax = fig.add_subplot(gs[-1, 0])
    data = [[r["travel_time_s"] for r in res.episodes[c] if np.isfinite(r["travel_time_s"])] for c in conds]
    ax.boxplot([d if d else [np.nan] for d in data], tick_labels=conds)
    ax.tick_params(axis="x", labelrotation=15)
    ax.set_ylabel("travel time [s]")
    letter = lambda k: chr(ord("a") + len(conds) + k)  # noqa: E731 - panel letters after the maps
    ax.set_title(f"{letter(0)}) travel time (successful runs)", fontsize=10, loc="left")
    ax = fig.add_subplot(gs[-1, 1])
    ax.boxplot([[r["midline_deviation_m"] for r in res.episodes[c] if np.isfinite(r["midline_deviation_m"])] or [np.nan]
                for c in conds], tick_labels=conds)
    ax.tick_params(axis="x", labelrotation=15)
    ax.set_ylabel("mean |y| [m]")
    ax.set_title(f"{letter(1)}) midline deviation", fontsize=10, loc="left")
    ax = fig.add_subplot(gs[-1, 2])
    trace = next((r for c in conds if c != "clean" for r in res.episodes[c]), None) or res.episodes[conds[0]][0]
    t = np.arange(len(trace["snr_db"])) * DT
    ax.plot(t, np.clip(trace["snr_db"], -100, 40), lw=1)
    ax.set_xlim(0, min(30, t[-1] if len(t) else 30))
    ax.set_xlabel("time [s]")
    ax.set_ylabel("SNR at the microphones [dB]")
    ax.set_title(f"{letter(2)}) effective SNR, run 0 of {trace['condition']}", fontsize=10, loc="left")
    fig.suptitle("Corridor control through noise bursts (EchoPT paper, Fig. 6)")
    fig.tight_layout()
    return fig
