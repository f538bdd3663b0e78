"""Wheel-slip detection by predictive processing (the paper's Fig. 5, plus ROC analysis).

A robot drives through the lab world on exploration commands. During slip periods its wheels turn
slower than commanded (both wheels: it stalls; one wheel: it turns unexpectedly) while the logged
commands stay the same. Each predictor forecasts the next frame from measured frames and the
logged commands, one-shot or auto-regressively over H steps; where the robot did not move as
commanded, the forecast and the measurement disagree. The detector signal is the paper's
eps(t) = ||I_p - I_m|| / sqrt(|CC(I_p, I_m)|) (``sonarset.metrics.slip_error``).

Beyond the paper's one trajectory, :func:`run_slip_experiment` scores detection over N random
trajectories with random slip periods: per trajectory the ROC AUC of a detector signal separating
frames reached through slip (per slip kind) from slip-free frames, then the mean AUC over
trajectories with a bootstrap CI and paired Wilcoxon tests between predictors (Holm-corrected).

Two detector signals are scored. ``eps`` is the paper's. ``ratio`` = eps(predictor) /
eps(persistence) asks whether the motion-compensated forecast beats "nothing moved", which it
should exactly when the robot moved as commanded; it divides out how much the scene changes
between frames. On the default ``ertis`` images both detect slip. On ``raw`` images (format 1.0's
delay-and-sum energy) eps does not: there it mostly measures the log-domain speckle of the noise
floor and the residual of imperfect motion compensation, both of which grow with motion, so a
stalled robot, whose scene stops changing, *lowers* it (AUC 0.24-0.61, BENCHMARKS.md).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy import stats

from sonarset.metrics import slip_error
from sonarset.atomic import atomic_text, save_figure
from sonarset.schema import Processing, SensorGrid
from sonarset.sim.generate import DT, spawn_seeds
from sonarset.sim.robot import ExplorationPolicy, apply_slip, integrate
from sonarset.sim.sonar import SonarModel
from sonarset.sim.world import lab_world
from sonarset.report import format_p, horizon_name
from sonarset.stats import holm, wilcoxon_p

from ..baselines import rollout
from .common import experiment_processing, finite_or_none, mean_ci, parallel_map, predictor

HORIZONS = (1, 3, 5)
KINDS = ("both", "one")
DETECTORS = ("eps", "ratio")
N_IN = 3


@dataclass(frozen=True)
class SlipPeriod:
    start_s: float
    end_s: float
    factors: tuple[float, float]  # (left, right) wheel speed factors while it lasts

    @property
    def kind(self) -> str:
        return "both" if min(self.factors) < 1 and max(self.factors) < 1 else "one"


@dataclass(frozen=True)
class SlipTrial:
    seed: int
    world_seed: int
    duration_s: float
    periods: tuple[SlipPeriod, ...]


def paper_trial(seed: int = 0) -> SlipTrial:
    """The paper's trajectory: both wheels slip from 10 s to 16 s, one wheel from 30 s to 36 s."""
    return SlipTrial(seed, seed % 1_000_003, 45.0, (SlipPeriod(10.0, 16.0, (0.25, 0.25)), SlipPeriod(30.0, 36.0, (0.25, 1.0))))


def random_trial(seed: int) -> SlipTrial:
    """A 60 s trajectory with one both-wheel and one one-wheel slip period of random timing (3-8 s
    each), slip factors U(0, 0.5), and a random wheel for the one-wheel period."""
    rng = np.random.default_rng(seed)
    d1, d2 = rng.uniform(3, 8, size=2)
    s1 = rng.uniform(5, 24 - d1)
    s2 = rng.uniform(30, 56 - d2)
    both = tuple(float(f) for f in rng.uniform(0, 0.5, size=2))
    wheel, f = int(rng.integers(2)), float(rng.uniform(0, 0.5))
    one = (f, 1.0) if wheel == 0 else (1.0, f)
    return SlipTrial(seed, seed % 1_000_003, 60.0, (SlipPeriod(s1, s1 + d1, both), SlipPeriod(s2, s2 + d2, one)))


def simulate_trial(trial: SlipTrial, grid: SensorGrid, snr_db: float = 5.0, processing: Processing | None = None) -> dict:
    """Images (T, R, A), logged commands (T, 2), true slip factors (T, 2) and poses (T, 3);
    ``commands[k]`` and ``slip[k]`` belong to the motion into frame k (DESIGN.md §2)."""
    world = lab_world(trial.world_seed)
    motion_ss, noise_ss = np.random.SeedSequence(trial.seed).spawn(2)
    rng = np.random.default_rng(motion_ss)
    policy = ExplorationPolicy(world, rng, dt=DT)
    pose = world.sample_spawn(rng)
    T = int(round(trial.duration_s / DT))
    commands, slip, poses = np.zeros((T, 2), np.float32), np.ones((T, 2)), np.zeros((T, 3))
    for k in range(T):
        t = k * DT
        for p in trial.periods:
            if p.start_s <= t < p.end_s:
                slip[k] = p.factors
        v, w = policy(pose)
        pose = integrate(pose, *apply_slip(v, w, tuple(slip[k])), DT)
        commands[k], poses[k] = (v, w), pose
    model = SonarModel(grid, snr_db=snr_db, processing=processing or Processing.ertis())
    images, _ = model.render_batch(world, poses, np.random.default_rng(noise_ss))
    return {"images": images, "commands": commands, "slip": slip, "pose": poses}


def slip_signals(pred, images: np.ndarray, commands: np.ndarray, horizons=HORIZONS, batch: int = 64) -> dict[int, np.ndarray]:
    """eps(t) per horizon H: for every frame t with H steps of prediction behind it (NaN before).

    Step h of an auto-regressive rollout from window i is the horizon-h forecast of frame
    i + n_in - 1 + h, so one rollout to the largest horizon serves every horizon: 5 model steps per
    window instead of 1 + 3 + 5. Rollouts that run past the last frame are fed zero commands there;
    a step reads only the commands up to its own, so the forecasts that are kept never see them.
    """
    T, H = len(images), max(horizons)
    eps = {h: np.full(T, np.nan) for h in horizons}
    starts = np.arange(0, T - N_IN)  # every window with at least one target
    padded = np.concatenate([commands, np.zeros((H, *commands.shape[1:]), commands.dtype)])
    for lo in range(0, len(starts), batch):
        i = starts[lo:lo + batch]
        frames = images[i[:, None] + np.arange(N_IN)]
        cmds = padded[i[:, None] + np.arange(N_IN + H)]
        steps = rollout(pred, frames, cmds, H)
        for h in horizons:
            t = i + N_IN - 1 + h
            ok = t < T
            if ok.any():
                eps[h][t[ok]] = slip_error(steps[ok, h - 1], images[t[ok]])
    return eps


def frame_labels(slip: np.ndarray, horizon: int) -> dict[str, np.ndarray]:
    """Per frame t: which slip kinds touched the predicted motion (moves t-H+1 .. t), and whether
    the frame is clean (no slip in any move the window spans, inputs included)."""
    T = len(slip)
    both = (slip < 1).all(1)
    one = (slip < 1).any(1) & ~both
    out = {k: np.zeros(T, bool) for k in (*KINDS, "clean")}
    any_slip = both | one
    for t in range(N_IN - 1 + horizon, T):
        moves = slice(t - horizon + 1, t + 1)
        out["both"][t], out["one"][t] = both[moves].any(), one[moves].any()
        out["clean"][t] = not any_slip[t - horizon - 1:t + 1].any()
    return out


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """ROC AUC of a score separating ``pos`` from ``neg``: P(pos > neg) + P(tie) / 2 (Mann-Whitney U)."""
    pos, neg = pos[np.isfinite(pos)], neg[np.isfinite(neg)]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    return float(stats.mannwhitneyu(pos, neg).statistic / (len(pos) * len(neg)))


@dataclass(frozen=True)
class _Task:
    trial: SlipTrial
    grid: SensorGrid
    models: tuple[str, ...]
    snr_db: float
    device: str
    keep_signals: bool
    processing: Processing = field(default_factory=Processing.ertis)


def _run_trial(task: _Task) -> dict:
    data = simulate_trial(task.trial, task.grid, task.snr_db, task.processing)
    out = {"trial": asdict(task.trial), "auc": {}, "signals": {}}
    still = predictor("persistence", task.grid)
    labels = {h: frame_labels(data["slip"], h) for h in HORIZONS}
    base = slip_signals(still, data["images"], data["commands"])
    for spec in task.models:
        pred = predictor(spec, task.grid, task.device)
        eps = slip_signals(pred, data["images"], data["commands"])
        for h in HORIZONS:
            lab = labels[h]
            for det, signal in (("eps", eps[h]), ("ratio", eps[h] / base[h])):
                for kind in KINDS:
                    out["auc"][f"{pred.name}|{h}|{kind}|{det}"] = auc(signal[lab[kind]], signal[lab["clean"]])
                if task.keep_signals:
                    out["signals"][f"{pred.name}|{h}|{det}"] = signal
    if task.keep_signals:
        out["pose"], out["slip"] = data["pose"], data["slip"]
    return out


@dataclass
class SlipResult:
    models: list[str]
    names: list[str]
    trials: int
    paper: dict  # the paper trajectory: signals per predictor|horizon, slip factors, poses
    per_trial: list[dict]  # AUC per trial
    summary: list[dict] = field(default_factory=list)
    comparisons: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    processing: Processing = field(default_factory=Processing.ertis)  # the images simulated


def run_slip_experiment(models: list[str], trials: int = 30, seed: int = 0, grid: SensorGrid | None = None,
                        snr_db: float = 5.0, workers: int | None = None, device: str = "cpu",
                        progress: Callable[[int, int], None] | None = None,
                        processing: Processing | str | None = None) -> SlipResult:
    """The paper trajectory (seeded by ``seed``) plus ``trials`` random trajectories, every model on each.

    The images are those the models were trained on; ``processing`` only checks that (see
    :func:`~.common.experiment_processing`)."""
    grid = grid or SensorGrid.default()
    t0 = time.perf_counter()
    names = [predictor(m, grid, device).name for m in models]  # fail fast on a bad model
    processing = experiment_processing(models, processing)
    seeds = spawn_seeds(seed, trials + 1)
    tasks = [_Task(paper_trial(seeds[0]), grid, tuple(models), snr_db, device, True, processing)]
    tasks += [_Task(random_trial(s), grid, tuple(models), snr_db, device, False, processing) for s in seeds[1:]]
    results = parallel_map(_run_trial, tasks, workers, progress)
    res = SlipResult(list(models), names, trials, results[0], [r["auc"] for r in results[1:]], processing=processing)
    res.summary, res.comparisons = summarise(res.per_trial, names, seed)
    res.seconds = time.perf_counter() - t0
    return res


def summarise(per_trial: list[dict], names: list[str], seed: int = 0) -> tuple[list[dict], list[dict]]:
    summary, comps = [], []
    keys = [(h, kind, det) for det in DETECTORS for h in HORIZONS for kind in KINDS]
    for name in names:
        for h, kind, det in keys:
            x = np.array([t[f"{name}|{h}|{kind}|{det}"] for t in per_trial], float)
            m, lo, hi = mean_ci(x, seed)
            summary.append({"predictor": name, "horizon": h, "kind": kind, "detector": det, "auc_mean": m,
                            "ci_low": lo, "ci_high": hi, "n": int(np.isfinite(x).sum())})
    for a in (n for n in names if n == "echopt"):
        for b in (n for n in names if n != a):
            for h, kind, det in keys:
                x = np.array([t[f"{a}|{h}|{kind}|{det}"] - t[f"{b}|{h}|{kind}|{det}"] for t in per_trial], float)
                x = x[np.isfinite(x)]
                p = wilcoxon_p(x)
                comps.append({"a": a, "b": b, "horizon": h, "kind": kind, "detector": det, "n": len(x),
                              "mean_auc_diff": float(x.mean()) if len(x) else float("nan"), "wilcoxon_p": p})
    for c, p in zip(comps, holm([c["wilcoxon_p"] for c in comps])):
        c["p_holm"] = p
    return summary, comps


DETECTOR_TEXT = {
    "eps": "the paper's eps(t) = ||I_p - I_m|| / sqrt(|CC|)",
    "ratio": "eps(predictor) / eps(persistence)",
}


def write_slip_report(res: SlipResult, out: str | os.PathLike) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paper = res.paper
    trial = paper["trial"]
    doc = {
        "experiment": "slip",
        "models": res.models,
        "trials": res.trials,
        "horizons": list(HORIZONS),
        "detectors": DETECTOR_TEXT,
        "auc": res.summary,
        "tests": res.comparisons,
        "per_trial_auc": res.per_trial,
        "paper_trajectory": {"trial": trial, "signal_ratio": _slip_ratios(paper, res.names)},
        "processing": res.processing.model_dump(),
        "seconds": res.seconds,
    }
    atomic_text(out / "metrics.json", json.dumps(finite_or_none(doc), indent=2) + "\n")
    fig_path = out / "fig5_slip.png"
    save_figure(fig5(paper, res.names), fig_path)
    by = {(s["predictor"], s["horizon"], s["kind"], s["detector"]): s for s in res.summary}
    lines = [
        "# Wheel-slip detection (EchoPT paper, Fig. 5)", "",
        f"{res.trials} random 60 s trajectories in lab worlds, each with one both-wheel and one one-wheel slip "
        "period (3-8 s, wheel speed factors U(0, 0.5)); the logged commands never change. Per trajectory, the "
        "ROC AUC of the detector signal separating frames reached through slip from slip-free frames; mean "
        "over trajectories with a bootstrap 95% CI. 0.5 is chance, below 0.5 the signal drops during slip. "
        f"Images: {res.processing.describe()} (the models' training images).", "",
        "| predictor | horizon | " + " | ".join(f"{d}: both wheels | {d}: one wheel" for d in DETECTORS) + " |",
        "| --- | ---: | " + " | ".join("---: | ---:" for _ in DETECTORS) + " |",
    ]
    for name in res.names:
        for h in HORIZONS:
            cells = []
            for det in DETECTORS:
                for kind in KINDS:
                    x = by[(name, h, kind, det)]
                    cells.append(f"{x['auc_mean']:.2f} [{x['ci_low']:.2f}, {x['ci_high']:.2f}]")
            lines.append(f"| {name} | {horizon_name(h)} | " + " | ".join(cells) + " |")
    lines += ["", "Detectors: " + "; ".join(f"`{k}` is {v}" for k, v in DETECTOR_TEXT.items()) + "."]
    if res.comparisons:
        lines += ["", "EchoPT against each baseline, paired Wilcoxon signed-rank tests on per-trajectory AUC "
                  "(Holm-corrected over all rows):", "",
                  "| detector | a - b | horizon | kind | mean AUC difference | p (Holm) |",
                  "| --- | --- | ---: | --- | ---: | ---: |"]
        for c in res.comparisons:
            lines.append(f"| {c['detector']} | {c['a']} - {c['b']} | {horizon_name(c['horizon'])} | {c['kind']} | "
                         f"{c['mean_auc_diff']:+.3f} | {format_p(c['p_holm'])} |")
    p0, p1 = trial["periods"]
    lines += ["", "## The paper's trajectory", "",
              f"Both wheels slip (factors {tuple(p0['factors'])}) from {p0['start_s']:g} s to {p0['end_s']:g} s, one "
              f"wheel ({tuple(p1['factors'])}) from {p1['start_s']:g} s to {p1['end_s']:g} s. Mean signal during "
              "each slip period over its mean in slip-free frames (> 1: the slip raises it):", "",
              "| predictor | horizon | " + " | ".join(f"{d}: both | {d}: one" for d in DETECTORS) + " |",
              "| --- | ---: | " + " | ".join("---: | ---:" for _ in DETECTORS) + " |"]
    ratios = doc["paper_trajectory"]["signal_ratio"]
    for name in res.names:
        for h in HORIZONS:
            cells = [f"{ratios[f'{name}|{h}|{det}'][kind]:.2f}" for det in DETECTORS for kind in KINDS]
            lines.append(f"| {name} | {horizon_name(h)} | " + " | ".join(cells) + " |")
    lines += ["", f"![Fig. 5]({fig_path.name})", "", f"{res.seconds:.0f} s in all."]
    atomic_text(out / "report.md", "\n".join(lines) + "\n")
    return out


def _slip_ratios(paper: dict, names: list[str]) -> dict:
    out = {}
    for name in names:
        for h in HORIZONS:
            lab = frame_labels(paper["slip"], h)
            for det in DETECTORS:
                sig = paper["signals"][f"{name}|{h}|{det}"]
                base = np.nanmean(sig[lab["clean"]])
                out[f"{name}|{h}|{det}"] = {k: float(np.nanmean(sig[lab[k]]) / base) for k in KINDS}
    return out


def fig5(paper: dict, names: list[str]):
    """Detector signals over time: a row per predictor, a column per detector, a curve per horizon
    (each over its slip-free median), slip periods shaded."""
    from sonarset.plots import pyplot

    plt = pyplot()

    t = np.arange(len(paper["slip"])) * DT
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
                ax.plot(t, sig / np.nanmedian(sig[frame_labels(paper["slip"], h)["clean"]]), lw=1.0, label=horizon_name(h))
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
