"""Training EchoPT on a SonarSet store (``sonarset train``), and by the same code the reference
methods of video prediction (``TrainConfig.model``: convlstm, simvp, unet; models/zoo/): the same
windows, losses, rollouts, precision, checkpoints and resume, so that they compare at equal budget.

Paper defaults: Adam, lr 5e-5, batch 64, L2 1e-4, 1600 random validation windows, best validation
loss kept. By default all frames of the training runs are held in memory (on the GPU when there is
one), and each batch is one gather from them (sonarset.torchdata.torch_batcher), so the loader never
starves the model; with ``stream`` the windows are read from the store as they are needed, each
process and DataLoader worker its own shards, in memory bounded by the shuffle buffer
(models/echopt/train_data.py, sonarset.stream).

For auto-regressive use (beyond the paper): an unrolled loss over k steps, each step fed the
model's own previous predictions, with a curriculum on k (``curriculum="0:1,400:2,800:4"``: from
step 0 k = 1, from step 400 k = 2, ...) and the steps' losses weighted alike or, ``harmonic``, step h
by 1/h (losses.step_weights); optionally "pushforward" (the first k - 1 steps without
gradient, so memory stays that of one step); Gaussian noise on the measured context frames; and a
loss choice (``mse``, ``l1``, ``gdl`` image-gradient difference, ``cc`` = 1 - correlation, or a
weighted sum such as ``mse=1,gdl=0.5``). Validation is the mean MSE over a rollout of
``val_horizon`` steps (1: the paper's one-step loss).

Precision (models/echopt/precision.py): ``auto`` trains under bf16 autocast where the hardware has bf16
units (a GPU, or a CPU with AMX or AVX-512 BF16) and in fp32 elsewhere; the losses, the optimizer
and the weights stay fp32. The card records the precision a model was trained in.

Crash-safe and resumable: the whole training state (weights, Adam moments, step, best loss,
metrics history) is one file, ``state.safetensors`` (models/echopt/train_state.py), replaced
atomically every ``eval_every`` steps; a kill at any point leaves either the previous state or the
new one. ``metrics.jsonl`` and the best model are derived from it and rewritten on resume. The
batch order (streamed: of the seed, epoch, processes and workers) and the augmentation noise are
pure functions of (seed, epoch, step), so a resumed run replays exactly the steps an uninterrupted
one would have taken.

Distributed (models/echopt/distributed.py): started by ``torchrun`` (WORLD_SIZE > 1), every process
draws the same global batch order and trains on its own contiguous slice of each global batch of
``batch_size`` windows (streamed: each process reads its own shards, ``batch_size / processes``
windows a step, the same number of steps an epoch), under DistributedDataParallel (NCCL on GPUs,
gloo on CPUs). DDP averages the gradients of the slices, which is the gradient of the global
batch's mean loss: the same optimizer steps as one process with that batch, up to floating-point
summation order. Validation is sharded and all-reduced; only rank 0 writes checkpoints, logs and
reports progress.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import torch
import torch.nn as nn

from sonarset import __version__
from sonarset.errors import SonarSetError
from sonarset.scoring.echoes import tolerance_bins
from sonarset.store.store import SonarStore

from sonarset.models.echopt.checkpoint import save_checkpoint
from sonarset.models.echopt.distributed import Dist, destroy_process_group, init_distributed
from sonarset.models.echopt.losses import parse_loss, rollout_losses, validation_loss, weighted_loss
from sonarset.models.echopt.precision import resolve_device, resolve_precision
from sonarset.models.echopt.recipes import SETTINGS, portable_command, recipe_of
from sonarset.models.echopt.train_config import RESUME_KEYS, STREAM_KEYS, TrainConfig
from sonarset.models.echopt.train_model import build_model
from sonarset.models.echopt.train_data import MemoryWindows, StreamedWindows, fewer_than_a_batch
from sonarset.models.echopt.train_state import STATE, load_state, save_state, write_metrics

#: Called with a phase name after each write of a checkpoint (tests kill training there).
_AFTER_WRITE: Callable[[str], None] | None = None


def _written(phase: str) -> None:
    if _AFTER_WRITE is not None:
        _AFTER_WRITE(phase)


@dataclass
class TrainResult:
    out_dir: Path
    steps: int
    epochs_done: float
    best_val_loss: float
    history: list[dict]


def train(store: SonarStore, out_dir: str | os.PathLike, cfg: TrainConfig, *, resume: bool = False,
          progress: Callable[[dict], None] | None = None) -> TrainResult:
    out = Path(out_dir)
    _refuse_a_used_directory(out, resume)
    # resuming a run killed before its first checkpoint (no state yet) starts it from step 0
    cfg.check()
    parse_loss(cfg.loss)
    dist, device, started = init_distributed(resolve_device(cfg.device))
    try:
        if cfg.batch_size % dist.world:
            raise SonarSetError(f"batch_size {cfg.batch_size} is not a multiple of the {dist.world} processes",
                                parameter="batch_size")
        created = not out.exists()
        lock = _lock_run(out) if dist.main else None
        try:
            if lock is not None:
                _refuse_a_used_directory(out, resume)  # again, now that no other training can start in it
            dist.barrier()  # every rank has checked the run directory before rank 0 writes to it
            return _train(store, out, cfg, resume, progress, dist, device)
        finally:
            if lock is not None:
                os.close(lock)  # releases the lock; the file stays (removing it would race a new taker)
                if created and [p.name for p in out.iterdir()] == [LOCK]:
                    # refused before it wrote anything: leave no directory behind, as before the lock
                    (out / LOCK).unlink(missing_ok=True)
                    out.rmdir()
    finally:
        if started:
            destroy_process_group()


LOCK = ".lock"


def _refuse_a_used_directory(out: Path, resume: bool) -> None:
    if not resume and out.is_dir() and any(p.name != LOCK for p in out.iterdir()):
        raise SonarSetError(f"{out}: exists and is not empty (resume the run in it, or train into another directory)",
                            parameter="out_dir")


def _lock_run(out: Path) -> int:
    """An exclusive lock on the run directory (``OUT/.lock``, held while this training runs): two
    trainings writing one run would replace each other's state and checkpoints."""
    import fcntl

    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / LOCK, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise SonarSetError(f"{out}: another training is running in it (pid {holder})", parameter="out_dir") from None
    except OSError:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


@dataclass(frozen=True)
class _Plan:
    """A run's length in optimizer steps, and how often it validates and saves."""

    steps_per_epoch: int
    total_steps: int
    eval_every: int

    @classmethod
    def of(cls, cfg: TrainConfig, n_train: int, location: str, steps_per_epoch: int | None = None) -> "_Plan":
        if steps_per_epoch is None:
            steps_per_epoch = n_train // cfg.batch_size  # drop the last partial batch
        if steps_per_epoch == 0:
            raise fewer_than_a_batch(location, n_train, cfg.n_val)
        total_steps = cfg.epochs * steps_per_epoch
        if cfg.max_steps:
            total_steps = min(total_steps, cfg.max_steps)
        return cls(steps_per_epoch, total_steps, cfg.eval_every or steps_per_epoch)


def _resumed(out: Path, model: nn.Module, opt: torch.optim.Optimizer, cfg: TrainConfig,
             dist: Dist) -> tuple[int, float, list[dict]]:
    """(step, best validation loss, history) of the saved state, loaded into ``model`` and ``opt``,
    after checking that the settings that shape the run are the saved ones."""
    meta = load_state(out, model, opt)
    saved = meta["train_config"]
    for key in RESUME_KEYS:
        if key in STREAM_KEYS and not cfg.stream:
            continue  # how a stream is read matters only to a streamed run
        if saved.get(key, getattr(TrainConfig, key, None)) != getattr(cfg, key):
            raise SonarSetError(f"{out}: resume with {key}={getattr(cfg, key)!r}, but the run used {saved.get(key)!r}",
                                parameter=key)
    if cfg.stream and int(meta.get("processes", dist.world)) != dist.world:
        # each process streams its own shards: another count cuts the epoch into other shards
        raise SonarSetError(f"{out}: resume a streamed run on {meta['processes']} processes, as it was started "
                            f"(not {dist.world})", parameter="stream")
    card = json.loads((out / "model.json").read_text()) if (out / "model.json").is_file() else {}
    for key, was in ((k, (card.get("config") or {}).get(k)) for k in ("dt", "sensor_offset")):
        if isinstance(was, (int, float)) and not math.isclose(was, getattr(model.cfg, key, was), rel_tol=1e-6):
            # a store without a rig made the simulator's robot before 2026-12-07, its own frame rate since
            raise SonarSetError(f"{out}: the run's model has {key} {was:g}, this store makes {getattr(model.cfg, key):g}; "
                                "start a new run")
    if dist.main:  # derived from the state: whatever a kill left behind, rewrite it
        write_metrics(out, list(meta["history"]))
    return int(meta["step"]), float(meta["best_val_loss"]), list(meta["history"])


def _forward(model: nn.Module, cfg: TrainConfig, dist: Dist, device: str):
    """The model as a training step calls it: under DistributedDataParallel across processes,
    compiled on request (GPU)."""
    fwd = model
    if dist.world > 1:
        from torch.nn.parallel import DistributedDataParallel

        fwd = DistributedDataParallel(model, device_ids=[dist.local_rank] if device.startswith("cuda") else None)
    if cfg.compile and device.startswith("cuda"):
        fwd = torch.compile(fwd)
    return fwd


def _card_base(store: SonarStore, cfg: TrainConfig, out: Path, run_names: list[str], n_train: int, n_val: int,
               steps_per_epoch: int, precision: str) -> dict:
    """What every checkpoint's card says about the model's data and training: its recipe and command
    with paths relative to the run directory ``out``, so a card names no directory of this machine."""
    recipe = recipe_of(cfg, store.location, out, relative_to=out)
    return {
        "format": "echopt-card/1", "model": cfg.model, "preset": cfg.preset, "grid": store.grid.model_dump(),
        # what the model knows: the images' processing and the robot (models/echopt/cards.py reads them)
        "processing": store.processing.model_dump(mode="json"),
        "rig": store.rig.model_dump(mode="json") if store.rig is not None else None,
        "training": {"store": recipe["store"], "runs": run_names, "worlds": _run_worlds(store, run_names),
                     "command": portable_command(cfg.command, out), "recipe": recipe,
                     "sonarset": __version__, "config": {k: v for k, v in recipe.items() if k in SETTINGS},
                     "windows_train": n_train,
                     "windows_val": n_val, "steps_per_epoch": steps_per_epoch, "precision": precision},
    }


def _run_worlds(store: SonarStore, names: list[str]) -> dict[str, int]:
    """{world family: training runs} of ``names`` (runs whose provenance names no world are left out)."""
    out: dict[str, int] = {}
    for name in names:
        world = (store.run(name).attrs.source or {}).get("world")
        if world is not None:
            out[str(world)] = out.get(str(world), 0) + 1
    return out


@dataclass
class _Tally:
    """Training loss and throughput since the last validation."""

    loss: float = 0.0
    n: int = 0
    samples: int = 0
    t0: float = field(default_factory=time.perf_counter)


@dataclass
class _Run:
    """What every step of one training run needs."""

    cfg: TrainConfig
    out: Path
    dist: Dist
    model: nn.Module
    fwd: Callable
    opt: torch.optim.Optimizer
    terms: dict[str, float]
    echo_window: tuple[int, int]  # the echo term's tolerance in bins on the store's grid
    data: MemoryWindows | StreamedWindows
    plan: _Plan
    val_horizon: int
    precision: str  # resolved: fp32 | bf16
    card_base: dict
    progress: Callable[[dict], None] | None
    t_start: float = field(default_factory=time.perf_counter)

    def batch(self, step: int, windows: Callable[[int], tuple], k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Input frames, commands and ``k`` rollout targets of a batch of training windows."""
        frames, commands, targets = windows(k)
        if self.cfg.context_noise:
            # drawn from (seed, step): a resumed run adds the same noise
            gen = torch.Generator().manual_seed(self.cfg.seed * 1_000_003 + step)
            noise = torch.randn(frames.shape, generator=gen) * self.cfg.context_noise
            frames = (frames + noise.to(frames.device)).clamp_(0, 1)
        return frames, commands, targets

    def optimizer_step(self, step: int, windows: Callable[[int], tuple], k: int) -> torch.Tensor:
        """One step on a batch of windows with a ``k``-step rollout; returns its loss."""
        frames, cmds, targets = self.batch(step, windows, k)
        for g in self.opt.param_groups:
            g["lr"] = self.cfg.lr_at(step, self.plan.total_steps)
        horizons = self.cfg.loss_horizons(k)
        losses = rollout_losses(self.fwd, frames, cmds, targets, self.terms, self.cfg.pushforward, self.precision,
                                flow=self.model.flow_prior, echo_window=self.echo_window, horizons=horizons)
        loss = weighted_loss(losses, self.cfg.step_weights, horizons)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return loss

    def out_of_time(self) -> bool:
        """Whether ``max_minutes`` is spent; every rank agrees, so that all stop at the same step."""
        late = bool(self.cfg.max_minutes) and (time.perf_counter() - self.t_start) > 60 * self.cfg.max_minutes
        if self.dist.world > 1 and self.cfg.max_minutes:
            late = bool(self.dist.all_sum(float(late))[0])
        return late

    def validate(self, step: int, k: int, tally: _Tally, history: list[dict], best: float) -> float:
        """Validate, append to ``history``, save (rank 0) and report; returns the best loss so far."""
        dist = self.dist
        # twice a training batch, not a fixed 128 windows: a forecaster (EchoWarp) holds all of a window's
        # horizons at once, so memory goes with windows x horizons (BENCHMARKS, "EchoWarp")
        val = validation_loss(self.model, self.data.val_batcher, self.data.val_idx, self.val_horizon, dist=dist,
                              batch_size=2 * self.cfg.batch_size, terms=self.terms, precision=self.precision,
                              weights=self.cfg.step_weights, echo_window=self.echo_window,
                              horizons=self.cfg.loss_horizons(self.val_horizon))
        run_loss, run_n = dist.all_sum(tally.loss, tally.n)
        rate = tally.samples / (time.perf_counter() - tally.t0)
        rec = {"step": step, "epoch": step / self.plan.steps_per_epoch, "train_loss": run_loss / max(run_n, 1),
               "val_loss": val, "rollout_k": k, "lr": self.opt.param_groups[0]["lr"], "samples_per_s": rate,
               "elapsed_s": time.perf_counter() - self.t_start}
        history.append(rec)
        if dist.main:
            self.save(step, val, best, history)
            if self.progress:
                self.progress({**rec, "total_steps": self.plan.total_steps, "best_val_loss": min(best, val)})
        return min(best, val)

    def save(self, step: int, val: float, best: float, history: list[dict]) -> None:
        """Rank 0's writes. Order matters for a kill at any point: the best model first (a resumed
        run redoes these steps and rewrites it identically), then the state, the commit point, then
        the metrics derived from it."""
        if val < best:
            save_checkpoint(self.out / "model.safetensors", self.model, {
                **self.card_base, "epochs": step / self.plan.steps_per_epoch, "steps": step, "val_loss": val,
                "val_horizon": self.val_horizon, "processes": self.dist.world}, after_weights=_written)
            _written("best")
        save_state(self.out, self.model, self.opt, {"step": step, "best_val_loss": min(best, val),
                                                    "train_config": asdict(self.cfg), "history": history,
                                                    "processes": self.dist.world})
        _written("state")
        write_metrics(self.out, history)
        _written("metrics")


def _train(store: SonarStore, out: Path, cfg: TrainConfig, resume: bool, progress, dist: Dist,
           device: str) -> TrainResult:
    model, opt = build_model(store, cfg, device)
    precision = resolve_precision(cfg.precision, device)
    terms = parse_loss(cfg.loss)
    val_horizon = cfg.val_horizon or cfg.k_max
    # a window holds the model's input frames and the longest rollout's targets
    horizon = max(cfg.k_max, val_horizon)
    data = (StreamedWindows if cfg.stream else MemoryWindows).make(store, cfg, model.cfg.n_in, horizon, dist, device)
    if dist.main:
        out.mkdir(parents=True, exist_ok=True)
    plan = _Plan.of(cfg, data.n_train, store.location, data.steps_per_epoch)
    step, best, history = 0, float("inf"), []
    if resume and (out / STATE).is_file():
        step, best, history = _resumed(out, model, opt, cfg, dist)
    run = _Run(cfg, out, dist, model, _forward(model, cfg, dist, device), opt, terms, tolerance_bins(store.grid), data,
               plan, val_horizon, precision,
               _card_base(store, cfg, out, data.run_names, data.n_train, len(data.val_idx), plan.steps_per_epoch,
                          precision),
               progress)
    step, best = _steps(run, step, best, history)
    dist.barrier()  # rank 0's last checkpoint is on disk before any process returns
    return TrainResult(out, step, step / plan.steps_per_epoch, best, history)


def _steps(run: _Run, step: int, best: float, history: list[dict]) -> tuple[int, float]:
    """Train from ``step`` to the plan's end or ``max_minutes``; returns (step reached, best loss).

    Each epoch's window order is drawn from (seed, epoch) (in memory: each process takes its slice
    of every global batch; streamed: each reads its own shards, positioned by the step count), so a
    resumed run replays the steps an uninterrupted one would have taken.
    """
    cfg, plan, dist = run.cfg, run.plan, run.dist
    local = cfg.batch_size // dist.world  # this process's share of each batch
    run.model.train()
    tally = _Tally()
    while step < plan.total_steps:
        epoch, pos = divmod(step, plan.steps_per_epoch)
        for windows in run.data.epoch(epoch, pos, plan.steps_per_epoch):
            k = cfg.k_at(step)
            loss = run.optimizer_step(step, windows, k).item()
            bad = not math.isfinite(loss)  # every later step would be too: every process stops here
            if bad or (dist.world > 1 and dist.all_sum(float(bad))[0]):
                hint = "precision fp32 (it trains in bf16), or " if run.precision == "bf16" else ""
                raise SonarSetError(f"step {step + 1}: the training loss is {loss} (not finite); the weights kept, if "
                                    f"any, are those of the best validation before it; try {hint}a lower lr")
            step += 1
            tally.loss += loss * local
            tally.n += local
            tally.samples += cfg.batch_size
            out_of_time = run.out_of_time()
            if step % plan.eval_every == 0 or step == plan.total_steps or out_of_time:
                best = run.validate(step, k, tally, history, best)
                tally = _Tally()
            elif run.progress and dist.main and step % 10 == 0:
                run.progress({"step": step, "total_steps": plan.total_steps, "train_loss": loss})
            if step >= plan.total_steps or out_of_time:
                return step, best
    return step, best
