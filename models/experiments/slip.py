"""Wheel-slip detection by predictive processing (the paper's Fig. 5, plus ROC analysis).

A robot drives through the lab world on exploration commands. During slip periods its wheels turn
slower than commanded (both wheels: it stalls; one wheel: it turns unexpectedly) while the logged
commands stay the same. Each predictor forecasts the next frame from measured frames and the
logged commands, one-shot or auto-regressively over H steps; where the robot did not move as
commanded, the forecast and the measurement disagree. The detector signal is the paper's
eps(t) = ||I_p - I_m|| / sqrt(|CC(I_p, I_m)|) (``sonarset.scoring.metrics.slip_error``).

Beyond the paper's one trajectory, :func:`run_slip_experiment` scores detection over N random
trajectories with random slip periods: per trajectory the ROC AUC of a detector signal separating
frames reached through slip (per slip kind) from slip-free frames, then the mean AUC over
trajectories with a bootstrap CI and paired Wilcoxon tests between predictors (Holm-corrected), in
a :class:`SlipResult` that :mod:`.slip_report` writes out.

Two detector signals are scored. ``eps`` is the paper's. ``ratio`` = eps(predictor) /
eps(persistence) asks whether the motion-compensated forecast beats "nothing moved", which it
should exactly when the robot moved as commanded; it divides out how much the scene changes
between frames. On the default ``ertis`` images both detect slip. On ``raw`` images (format 1.0's
delay-and-sum energy) eps does not: there it mostly measures the log-domain speckle of the noise
floor and the residual of imperfect motion compensation, both of which grow with motion, so a
stalled robot, whose scene stops changing, *lowers* it (AUC 0.24-0.61, BENCHMARKS.md).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from sonarset.scoring.metrics import slip_error
from sonarset.format.attrs import Processing, RobotRig, SensorGrid
from sonarset.sim.runs import spawn_seeds, world_seed
from sonarset.sim.robot import ExplorationPolicy, apply_slip, integrate
from sonarset.sim.sonar import SonarModel
from sonarset.sim.families import lab_world
from sonarset.scoring.stats import auc, holm, wilcoxon_p

from sonarset.models.predictor import CheckedPredictor
from sonarset.models.registry import BASELINES
from sonarset.models.experiments.common import RIG, experiment_processing, learned_precision, mean_ci, parallel_map, predictor

HORIZONS = (1, 3, 5)
KINDS = ("both", "one")
DETECTORS = ("eps", "ratio")


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
    return SlipTrial(seed, world_seed(seed), 45.0, (SlipPeriod(10.0, 16.0, (0.25, 0.25)), SlipPeriod(30.0, 36.0, (0.25, 1.0))))


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
    return SlipTrial(seed, world_seed(seed), 60.0, (SlipPeriod(s1, s1 + d1, both), SlipPeriod(s2, s2 + d2, one)))


def simulate_trial(trial: SlipTrial, grid: SensorGrid, snr_db: float = 5.0, processing: Processing | None = None) -> dict:
    """Images (T, R, A), logged commands (T, 2), true slip factors (T, 2) and poses (T, 3);
    ``commands[k]`` and ``slip[k]`` belong to the motion into frame k (docs/conventions.md, "Commands")."""
    world = lab_world(trial.world_seed)
    motion_ss, noise_ss = np.random.SeedSequence(trial.seed).spawn(2)
    rng = np.random.default_rng(motion_ss)
    dt = RIG.frame_interval_s
    policy = ExplorationPolicy(world, rng, dt=dt)
    pose = world.sample_spawn(rng)
    T = int(round(trial.duration_s / dt))
    commands, slip, poses = np.zeros((T, 2), np.float32), np.ones((T, 2)), np.zeros((T, 3))
    for k in range(T):
        t = k * dt
        for p in trial.periods:
            if p.start_s <= t < p.end_s:
                slip[k] = p.factors
        v, w = policy(pose)
        pose = integrate(pose, *apply_slip(v, w, tuple(slip[k])), dt)
        commands[k], poses[k] = (v, w), pose
    model = SonarModel(grid, snr_db=snr_db, processing=processing or Processing.ertis())
    images, _ = model.render_batch(world, poses, np.random.default_rng(noise_ss))
    return {"images": images, "commands": commands, "slip": slip, "pose": poses}


def slip_signals(pred: CheckedPredictor, images: np.ndarray, commands: np.ndarray, horizons=HORIZONS,
                 batch: int = 64) -> dict[int, np.ndarray]:
    """eps(t) per horizon H: for every frame t with H steps of prediction behind it (NaN before).

    Step h of an auto-regressive rollout from window i (``pred.n_in`` frames) is the horizon-h
    forecast of frame i + n_in - 1 + h, so one rollout to the largest horizon serves every horizon: 5 model steps per
    window instead of 1 + 3 + 5 (a model that forecasts each horizon directly, ``forecast_at``,
    computes those alone). Rollouts that run past the last frame are fed zero commands there;
    a step reads only the commands up to its own, so the forecasts that are kept never see them.
    """
    horizons = tuple(sorted(set(horizons)))
    T, H, n_in = len(images), max(horizons), pred.n_in
    eps = {h: np.full(T, np.nan) for h in horizons}
    starts = np.arange(0, T - n_in)  # every window with at least one target
    padded = np.concatenate([commands, np.zeros((H, *commands.shape[1:]), commands.dtype)])
    for lo in range(0, len(starts), batch):
        i = starts[lo:lo + batch]
        frames = images[i[:, None] + np.arange(n_in)]
        cmds = padded[i[:, None] + np.arange(n_in + H)]
        forecasts = pred.forecast_at(frames, cmds, horizons)
        for j, h in enumerate(horizons):
            t = i + n_in - 1 + h
            ok = t < T
            if ok.any():
                eps[h][t[ok]] = slip_error(forecasts[ok, j], images[t[ok]])
    return eps


def frame_labels(slip: np.ndarray, horizon: int, n_in: int) -> dict[str, np.ndarray]:
    """Per frame t forecast from windows of ``n_in`` frames: which slip kinds touched the predicted
    motion (moves t-H+1 .. t), and whether the frame is clean (no slip in any move the window
    spans: between its input frames, and predicted)."""
    T = len(slip)
    both = (slip < 1).all(1)
    one = (slip < 1).any(1) & ~both
    out = {k: np.zeros(T, bool) for k in (*KINDS, "clean")}
    any_slip = both | one
    for t in range(n_in - 1 + horizon, T):
        moves = slice(t - horizon + 1, t + 1)
        out["both"][t], out["one"][t] = both[moves].any(), one[moves].any()
        out["clean"][t] = not any_slip[t - horizon - n_in + 2:t + 1].any()
    return out


@dataclass(frozen=True)
class _Task:
    trial: SlipTrial
    grid: SensorGrid
    models: tuple[str, ...]
    snr_db: float
    device: str
    keep_signals: bool
    processing: Processing = field(default_factory=Processing.ertis)
    precision: str = "auto"


def _run_trial(task: _Task) -> dict:
    """AUC per predictor|horizon|kind|detector; with ``keep_signals``, also the detector signals,
    frame labels (per predictor|horizon), poses and slip factors."""
    data = simulate_trial(task.trial, task.grid, task.snr_db, task.processing)
    out = {"trial": asdict(task.trial), "auc": {}, "signals": {}, "labels": {}}
    still = predictor("persistence", task.grid)
    base = slip_signals(still, data["images"], data["commands"])
    labels: dict[tuple[int, int], dict[str, np.ndarray]] = {}  # per (horizon, n_in): the same for every model
    for spec in task.models:
        pred = predictor(spec, task.grid, task.device, task.precision)
        eps = slip_signals(pred, data["images"], data["commands"])
        for h in HORIZONS:
            if (h, pred.n_in) not in labels:
                labels[h, pred.n_in] = frame_labels(data["slip"], h, pred.n_in)
            lab = labels[h, pred.n_in]
            for det, signal in (("eps", eps[h]), ("ratio", eps[h] / base[h])):
                for kind in KINDS:
                    out["auc"][f"{pred.name}|{h}|{kind}|{det}"] = auc(signal[lab[kind]], signal[lab["clean"]])
                if task.keep_signals:
                    out["signals"][f"{pred.name}|{h}|{det}"] = signal
            if task.keep_signals:
                out["labels"][f"{pred.name}|{h}"] = lab
    if task.keep_signals:
        out["pose"], out["slip"] = data["pose"], data["slip"]
    return out


@dataclass
class SlipResult:
    models: list[str]
    names: list[str]
    trials: int
    paper: dict  # the paper trajectory: signals per predictor|horizon|detector, labels, slip factors, poses
    per_trial: list[dict]  # AUC per trial
    summary: list[dict] = field(default_factory=list)
    comparisons: list[dict] = field(default_factory=list)
    signal_ratios: dict = field(default_factory=dict)  # on the paper trajectory: see signal_ratios()
    seconds: float = 0.0
    processing: Processing = field(default_factory=Processing.ertis)  # the images simulated
    rig: RobotRig = RIG  # the robot simulated
    precision: dict[str, str] = field(default_factory=dict)  # learned predictor -> fp32 | bf16, as it ran


def run_slip_experiment(models: list[str], trials: int = 30, seed: int = 0, grid: SensorGrid | None = None,
                        snr_db: float = 5.0, workers: int | None = None, device: str = "cpu",
                        progress: Callable[[int, int], None] | None = None,
                        processing: Processing | str | None = None, precision: str = "auto") -> SlipResult:
    """The paper trajectory (seeded by ``seed``) plus ``trials`` random trajectories, every model on each.

    The images are those the models were trained on; ``processing`` only checks that (see
    :func:`~.common.experiment_processing`)."""
    grid = grid or SensorGrid.default()
    t0 = time.perf_counter()
    preds = [predictor(m, grid, device, precision) for m in models]  # fail fast on a bad model
    names = [p.name for p in preds]
    processing = experiment_processing(preds, processing)
    seeds = spawn_seeds(seed, trials + 1)
    tasks = [_Task(paper_trial(seeds[0]), grid, tuple(models), snr_db, device, True, processing, precision)]
    tasks += [_Task(random_trial(s), grid, tuple(models), snr_db, device, False, processing, precision)
              for s in seeds[1:]]
    results = parallel_map(_run_trial, tasks, workers, progress)
    res = SlipResult(list(models), names, trials, results[0], [r["auc"] for r in results[1:]], processing=processing,
                     precision=learned_precision(preds))
    res.summary, res.comparisons = summarise(res.per_trial, names, seed)
    res.signal_ratios = signal_ratios(res.paper, names)
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
    # every model (a checkpoint, a plugin, a module:factory) against every baseline beside it and
    # every model listed before it (as the benchmark's vs_models): a new model meets the old one
    learned = [n for n in names if n not in BASELINES]
    baselines = [n for n in names if n in BASELINES]
    for i, a in enumerate(learned):
        for b in baselines + learned[:i]:
            for h, kind, det in keys:
                x = np.array([t[f"{a}|{h}|{kind}|{det}"] - t[f"{b}|{h}|{kind}|{det}"] for t in per_trial], float)
                x = x[np.isfinite(x)]
                p = wilcoxon_p(x)
                comps.append({"a": a, "b": b, "horizon": h, "kind": kind, "detector": det, "n": len(x),
                              "mean_auc_diff": float(x.mean()) if len(x) else float("nan"), "wilcoxon_p": p})
    for c, p in zip(comps, holm([c["wilcoxon_p"] for c in comps])):
        c["p_holm"] = p
    return summary, comps


def signal_ratios(paper: dict, names: list[str]) -> dict[str, dict[str, float]]:
    """Per predictor|horizon|detector and slip kind: the signal's median during that kind of slip over
    its median in slip-free frames (> 1: the slip raises it), on one trajectory kept with its signals.
    Medians, because eps divides by sqrt(|CC|): one forecast with CC near 0 makes a spike that
    would carry a mean by itself (Fig. 5 shows the spikes)."""
    out = {}
    for name in names:
        for h in HORIZONS:
            lab = paper["labels"][f"{name}|{h}"]
            for det in DETECTORS:
                sig = paper["signals"][f"{name}|{h}|{det}"]
                base = np.nanmedian(sig[lab["clean"]])
                out[f"{name}|{h}|{det}"] = {k: float(np.nanmedian(sig[lab[k]]) / base) for k in KINDS}
    return out
