"""Corridor control through noise bursts (the paper's Fig. 6).

A robot spawns in the corridor world's spawn box and drives to its waypoint with the subsumption
controller of :mod:`sonarset.sim.control`, which sees only sonar images and odometry. Three conditions,
run from the same spawn poses and (for the last two) the same burst schedules:

- ``clean``: every frame at the nominal SNR (5 dB);
- ``bursts``: noise bursts (SNR -80 dB for 1.2 s, about 30% of the time) reach the controller;
- ``bursts+<model>``: a burst detector on each image replaces burst frames by the model's
  forecast (the paper's condition with EchoPT; any predictor spec works, e.g. ``flow`` for
  comparison). The k-th frame of a burst is forecast k steps ahead, by the model's ``rollout``,
  from the frames the controller used before the burst (as many as the model's window takes) and
  the commands since. A model that predicts one step at a time chains its own predictions, as it
  would frame by frame; one that forecasts every horizon from measured frames (EchoWarp) is used
  as it was trained, instead of being fed its own forecasts as if they were measurements (only a
  burst that starts fewer than n_in frames after the previous one starts from that one's forecasts).

A run ends at the waypoint (success), on contact with a pole (collision) or after ``max_time_s``
(timeout). Reported per condition: success/collision/timeout counts with Wilson CIs, travel time
and mean absolute midline deviation with bootstrap CIs, and paired tests between conditions
(:class:`ControlResult`; :mod:`.control_report` writes it out).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from sonarset.sim.control import BurstDetector, ControllerGains, SubsumptionController
from sonarset.format.attrs import Processing, RobotRig, SensorGrid
from sonarset.sim.runs import spawn_seeds
from sonarset.sim.robot import ROBOT_RADIUS, integrate
from sonarset.sim.sonar import SonarModel
from sonarset.sim.families import corridor_world
from sonarset.sim.world import World
from sonarset.scoring.stats import holm, mcnemar_p, wilcoxon_p, wilson_interval
from sonarset.windows import N_IN

from sonarset.models.experiments.common import RIG, experiment_processing, mean_ci, parallel_map, predictor

CONDITIONS = ("clean", "bursts")  # plus one "bursts+<model>" condition per predictor
GOAL_RADIUS = 0.4  # m: a run succeeds when the robot centre comes this close to the waypoint


@dataclass(frozen=True)
class BurstSchedule:
    """Noise bursts of fixed length separated by exponential gaps, set for a target duty cycle."""

    burst_s: float = 1.2
    duty: float = 0.3
    snr_db: float = -80.0

    def frames(self, rng: np.random.Generator, n: int, dt: float) -> np.ndarray:
        """Which of ``n`` frames, ``dt`` seconds apart, a burst hits."""
        on = np.zeros(n, bool)
        mean_gap = self.burst_s * (1 - self.duty) / self.duty
        k = int(round(rng.exponential(mean_gap) / dt))
        length = max(1, int(round(self.burst_s / dt)))
        while k < n:
            on[k:k + length] = True
            k += length + max(1, int(round(rng.exponential(mean_gap) / dt)))
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
    precision: str = "auto"  # EchoPT's arithmetic (models/echopt/precision.py)
    # a diagnostic: on every bridged frame also steer by the frame measured without the burst (its
    # own noise draw), recorded as "w_measured" and "layer_measured" beside the commanded "w" and
    # "layer"; the run is unchanged
    shadow: bool = False


def run_episode(ep: Episode, world: World | None = None) -> dict:
    """Drive one run; returns its trajectory, per-frame SNR, burst and prediction flags, turn
    rates, and outcome."""
    world = world or corridor_world()
    spawn_ss, burst_ss, noise_ss, shadow_ss = np.random.SeedSequence(ep.seed).spawn(4)
    pose = world.sample_spawn(np.random.default_rng(spawn_ss))
    dt = RIG.frame_interval_s
    n_max = int(round(ep.max_time_s / dt))
    burst = ep.bursts.frames(np.random.default_rng(burst_ss), n_max, dt) if ep.condition != "clean" \
        else np.zeros(n_max, bool)
    noise_rng, shadow_rng = np.random.default_rng(noise_ss), np.random.default_rng(shadow_ss)
    model = SonarModel(ep.grid, snr_db=ep.snr_db, processing=ep.processing)
    ctrl = SubsumptionController(ep.grid, world.waypoint, ep.gains)
    detector = BurstDetector()
    spec = ep.condition.partition("+")[2]
    pred = predictor(spec, ep.grid, ep.device, ep.precision) if spec else None
    n_in = pred.n_in if pred is not None else N_IN  # the frames a forecast starts from
    frames: list[np.ndarray] = []  # what the controller saw: the anchor of a forecast, then the forecasts
    commands = [np.zeros(2, np.float32)]  # commands[k] moved the robot into frame k
    ahead = 0  # how many of the last frames are forecasts (the steps since the anchor)
    poses, snr, flagged, predicted, layers, turns, shadow = [], [], [], [], [], [], []
    outcome = "timeout"
    for k in range(n_max):
        img, eff = model.render(world, pose, noise_rng, snr_db=ep.bursts.snr_db if burst[k] else None, return_snr=True)
        is_burst = detector(img)
        used = img
        if pred is not None and is_burst and len(frames) - ahead >= n_in:
            ahead += 1
            if pred.chains:  # the same forecast as its rollout from the anchor, one step instead of ahead
                used = pred.predict(np.stack(frames[-n_in:])[None], np.stack(commands[-(n_in + 1):])[None])[0]
            else:
                anchor = np.stack(frames[len(frames) - (ahead - 1) - n_in:len(frames) - (ahead - 1)])[None]
                used = pred.forecast_at(anchor, np.stack(commands[-(n_in + ahead):])[None], (ahead,))[0, 0]
        else:
            ahead = 0
        frames.append(np.asarray(used, np.float32))
        del frames[:-(n_in + ahead)]
        decision = ctrl(used, pose)  # odometry: no slip here, so it is the true pose
        poses.append(pose), snr.append(eff), flagged.append(is_burst), predicted.append(used is not img)
        layers.append(decision.layer), turns.append(decision.w)
        if ep.shadow:
            shadow.append(ctrl(model.render(world, pose, shadow_rng), pose) if used is not img else None)
        if np.hypot(*(world.waypoint - pose[:2])) < GOAL_RADIUS:
            outcome = "success"
            break
        pose = integrate(pose, decision.v, decision.w, dt)
        commands.append(np.array([decision.v, decision.w], np.float32))
        del commands[:-(n_in + ahead + 1)]
        if world.clearance(pose[None, :2])[0] < ROBOT_RADIUS:
            poses.append(pose)
            outcome = "collision"
            break
    poses = np.array(poses)
    n = len(snr)
    inside = (poses[:, 0] >= 0) & (poses[:, 0] <= world.waypoint[0])
    return {
        "index": ep.index, "condition": ep.condition, "outcome": outcome,
        "travel_time_s": n * dt if outcome == "success" else float("nan"),
        "midline_deviation_m": float(np.abs(poses[inside, 1]).mean()) if inside.any() else float("nan"),
        "pose": poses, "snr_db": np.array(snr), "burst": burst[:n], "flagged": np.array(flagged),
        "predicted": np.array(predicted), "layers": {k: layers.count(k) for k in ("avoid", "corridor", "goal")},
        "w": np.array(turns), "layer": np.array(layers),
        **({"w_measured": np.array([np.nan if d is None else d.w for d in shadow]),
            "layer_measured": np.array(["" if d is None else d.layer for d in shadow])} if ep.shadow else {}),
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
    rig: RobotRig = RIG  # the robot simulated
    precision: dict[str, str] = field(default_factory=dict)  # bridging model spec -> fp32 | bf16, as it ran


def condition_name(spec: str, name: str) -> str:
    """``bursts+NAME`` (the predictor's name) for a name the registry knows (``bursts+echowarp`` for
    ``pretrained`` and ``echowarp:pretrained``); ``bursts+SPEC`` for a checkpoint's path or a
    ``module:factory``, which stay apart where names may not."""
    return "bursts+" + (name if spec.partition(":")[2] in ("", "pretrained") else spec)


def run_control_experiment(models: list[str] | tuple[str, ...] = ("pretrained",), runs: int = 50, seed: int = 0,
                           grid: SensorGrid | None = None, workers: int | None = None, device: str = "cpu",
                           max_time_s: float = 120.0, progress: Callable[[int, int], None] | None = None,
                           processing: Processing | str | None = None, precision: str = "auto") -> ControlResult:
    """``runs`` runs in each condition: clean, bursts, and bursts bridged by each model in ``models``.

    The images are those the models were trained on; ``processing`` only checks that (see
    :func:`~.common.experiment_processing`)."""
    grid = grid or SensorGrid.default()
    t0 = time.perf_counter()
    preds = {m: predictor(m, grid, device, precision) for m in models}  # fail fast on a bad model
    processing = experiment_processing(preds.values(), processing)
    conditions = [*CONDITIONS, *(f"bursts+{m}" for m in models)]
    seeds = spawn_seeds(seed, runs)  # run i uses the same spawn, bursts and noise seed in every condition
    eps = [Episode(i, s, c, grid, max_time_s=max_time_s, device=device, processing=processing, precision=precision)
           for c in conditions for i, s in enumerate(seeds)]
    results = parallel_map(run_episode, eps, workers, progress)
    names = {c: condition_name(c.partition("+")[2], preds[c.partition("+")[2]].name) if "+" in c else c
             for c in conditions}
    by = {names[c]: [dict(r, condition=names[c]) for r in results if r["condition"] == c] for c in conditions}
    res = ControlResult(", ".join(models), runs, by, gains=ControllerGains().to_dict(), processing=processing,
                        precision={m: p.precision for m, p in preds.items() if p.precision is not None})
    res.summary, res.comparisons, res.detector = summarise(by, seed)
    res.seconds = time.perf_counter() - t0
    return res


def summarise(by: dict, seed: int = 0) -> tuple[dict, list[dict], dict]:
    """Per condition outcomes and CIs, paired tests between conditions, and the burst detector's scores."""
    return {c: condition_summary(rs, seed) for c, rs in by.items()}, paired_tests(by), detector_scores(by)


def condition_summary(rs: list[dict], seed: int = 0) -> dict:
    """Outcome counts (success rate with a Wilson CI), travel time and midline deviation (bootstrap
    CIs), the share of frames in a burst and how many frames a forecast replaced."""
    n = len(rs)
    counts = {o: sum(r["outcome"] == o for r in rs) for o in ("success", "collision", "timeout")}
    tt = np.array([r["travel_time_s"] for r in rs])
    dev = np.array([r["midline_deviation_m"] for r in rs])
    frames = sum(len(r["burst"]) for r in rs)
    return {
        "runs": n, **counts, "success_rate_ci": wilson_interval(counts["success"], n),
        "travel_time_s": dict(zip(("mean", "ci_low", "ci_high"), mean_ci(tt, seed)),
                              median=float(np.nanmedian(tt)) if np.isfinite(tt).any() else float("nan")),
        "midline_deviation_m": dict(zip(("mean", "ci_low", "ci_high"), mean_ci(dev, seed))),
        "burst_time_fraction": sum(int(r["burst"].sum()) for r in rs) / max(frames, 1),
        "predicted_frames": sum(int(r["predicted"].sum()) for r in rs),
    }


def paired_tests(by: dict) -> list[dict]:
    """Every pair of conditions over the same runs: Wilcoxon on travel time and midline deviation,
    McNemar on success; Holm-corrected over all of them."""
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
            comps.append({"a": a, "b": b, "metric": "success", "n_pairs": len(sa),
                          "mean_diff": float(sa.mean() - sb.mean()), "mcnemar_p": mcnemar_p(sa, sb)})
    for c, p in zip(comps, holm([c.get("wilcoxon_p", c.get("mcnemar_p")) for c in comps])):
        c["p_holm"] = p
    return comps


def detector_scores(by: dict) -> dict:
    """The burst detector's recall and precision per bursty condition, its false alarms on clean runs."""
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
    return detector
