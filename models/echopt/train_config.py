"""The settings of a training run (``TrainConfig``), built once by the caller (``sonarset train``
builds it from its options and a recipe file: models/echopt/recipes.py) and carried whole through
training, into the card and the resumable state. No torch here: the command line lists the
optimizers and schedules without loading it.
"""

from __future__ import annotations

import math
import shlex
import sys
from dataclasses import dataclass, field

from sonarset.errors import SonarSetError
from sonarset.stream import DEFAULT_SHUFFLE_BUFFER

from sonarset.models.echopt.config import INPUTS, PRIORS

OPTIMIZERS = ("adam", "adamw")
SCHEDULES = ("none", "cosine")
#: How the steps of a rollout share the loss: uniform (each 1/k) or harmonic (step h ~ 1/h, normalised:
#: the evaluation scores one-shot, AR-3, AR-5 and AR-10 alike, while a uniform 10-step loss gives the
#: one-step forecast a tenth of the gradient and the late, large errors most of it).
STEP_WEIGHTS = ("uniform", "harmonic")
#: Which weights a run updates: all, or only the geometry branch (config.geometry_channels), the rest
#: frozen as ``init`` trained it: what the branch adds is then measured on an unchanged model.
TRAINABLE = ("all", "geometry")
#: The networks ``sonarset train`` builds: EchoPT and the reference methods of video prediction
#: (models/zoo/), trained by the same trainer on the same windows and losses.
MODEL_KINDS = ("echopt", "convlstm", "simvp", "unet", "echowarp")


@dataclass
class TrainConfig:
    model: str = "echopt"  # MODEL_KINDS
    preset: str = "small"
    epochs: int = 1000
    batch_size: int = 64
    lr: float = 5e-5
    weight_decay: float = 1e-4  # L2, as Adam's weight_decay (MATLAB's L2Regularization)
    # adam: the paper's, L2 added to the gradient; adamw: decoupled decay (Loshchilov & Hutter).
    # With a prior the last convolution starts at zero, so the layers behind it see almost no
    # gradient at first, and Adam's normalised L2 alone shrinks them by ~lr a step: in short runs
    # they never learn (measured on the tiny preset). AdamW's decay does not go through Adam's scaling.
    optimizer: str = "adam"  # OPTIMIZERS
    schedule: str = "none"  # SCHEDULES: none (paper) | cosine (decays to 1% of lr over the run, 2% warm-up)
    seed: int = 0
    device: str = "auto"
    n_val: int = 1600
    eval_every: int = 0  # steps between validations and checkpoints; 0 = once per epoch
    max_steps: int = 0  # stop after this many optimizer steps in total (0 = no limit)
    max_minutes: float = 0.0  # stop after this much wall time in this process (0 = no limit)
    compile: bool = False  # torch.compile (GPU; on a CPU it measured 0.69x eager: BENCHMARKS.md)
    precision: str = "auto"  # auto | fp32 | bf16 autocast (models/echopt/precision.py); auto: bf16 where the hardware has it
    test_samples: int = 1000  # one-shot + AR test metrics in the card (0 = skip)
    prior: str = ""  # config.PRIORS (none | last | flow); "" = the preset's (paper: none, small and tiny: flow)
    loss: str = "mse"  # a term of losses.LOSSES, or a weighted sum "mse=1,w1=2"
    curriculum: str = "1"  # rollout length k: "k", or "step:k,step:k,..." from those steps on
    pushforward: bool = False  # only the last of the k steps carries gradient
    step_weights: str = "uniform"  # STEP_WEIGHTS: the rollout steps' shares of the loss
    horizons: str = ""  # the rollout steps that carry the loss ("1,3,5,10"; "" = every step up to k)
    context_noise: float = 0.0  # std of Gaussian noise added to the measured context frames
    val_horizon: int = 0  # rollout steps of the validation loss (0 = the curriculum's longest)
    init: str = ""  # fine-tune: start from this checkpoint's weights (same preset, prior, grid, images)
    worlds: str = ""  # comma-separated world families to train on ("" = every training run)
    n_in: int = 0  # input frames per window (0 = the preset's: the paper's 3)
    inputs: str = ""  # config.INPUTS (raw | aligned); "" = the preset's (raw), or init's model's
    geometry_channels: int = -1  # config.geometry_channels; -1 = the preset's (0, none), or init's model's
    trainable: str = "all"  # TRAINABLE
    # stream windows from the store instead of loading it (sonarset.stream): memory bounded by the
    # shuffle buffer (windows mixed at once) and the DataLoader workers' read-ahead, not the store
    stream: bool = False
    shuffle_buffer: int = DEFAULT_SHUFFLE_BUFFER
    loader_workers: int = 0  # DataLoader worker processes reading the stream (0: in this process)
    # the command line that ran, as typed; the card records it portable (recipes.portable_command)
    command: str = field(default_factory=lambda: " ".join(shlex.quote(a) for a in sys.argv))

    def stages(self) -> list[tuple[int, int]]:
        """The curriculum as (first step, k) pairs, sorted."""
        try:
            if ":" not in self.curriculum:
                out = [(0, int(self.curriculum))]
            else:
                out = sorted((int(a), int(b)) for a, b in (p.split(":") for p in self.curriculum.split(",")))
        except ValueError:
            raise SonarSetError(f"curriculum {self.curriculum!r}: expected k or step:k,step:k (e.g. 0:1,400:2)",
                                parameter="curriculum") from None
        if not out or out[0][0] != 0 or any(k < 1 for _, k in out):
            raise SonarSetError(f"curriculum {self.curriculum!r}: must start at step 0 with k >= 1",
                                parameter="curriculum")
        return out

    def loss_horizons(self, k: int) -> tuple[int, ...] | None:
        """The steps of a ``k``-step rollout that carry the loss: ``horizons`` up to k, or None for
        every step (SonarSetError when none of them is a step of it)."""
        if not self.horizons:
            return None
        try:
            hs = [int(h) for h in self.horizons.split(",")]
        except ValueError:
            hs = []
        if not hs or hs != sorted(set(hs)) or hs[0] < 1:
            raise SonarSetError(f"horizons {self.horizons!r}: expected increasing steps >= 1 (e.g. 1,3,5,10)",
                                parameter="horizons")
        if self.pushforward:
            raise SonarSetError("horizons and pushforward do not go together: pushforward trains the last step alone",
                                parameter="horizons")
        inside = tuple(h for h in hs if h <= k)
        if not inside:
            raise SonarSetError(f"horizons {self.horizons!r}: none within a {k}-step rollout", parameter="horizons")
        return inside

    def check(self) -> None:
        """SonarSetError naming the first setting no run can have (the loss terms: losses.parse_loss)."""
        for k in {k for _, k in self.stages()} | {self.val_horizon or self.k_max}:
            self.loss_horizons(k)
        if self.shuffle_buffer < 1 or self.loader_workers < 0:
            bad = "shuffle_buffer" if self.shuffle_buffer < 1 else "loader_workers"
            raise SonarSetError(f"shuffle_buffer must be >= 1 and loader_workers >= 0, got {self.shuffle_buffer} "
                                f"and {self.loader_workers}", parameter=bad)
        for name, allowed in (("prior", PRIORS), ("inputs", INPUTS), ("optimizer", OPTIMIZERS),
                              ("schedule", SCHEDULES), ("step_weights", STEP_WEIGHTS), ("trainable", TRAINABLE),
                              ("model", MODEL_KINDS)):
            value = getattr(self, name)
            if (value or name not in ("prior", "inputs")) and value not in allowed:
                raise SonarSetError(f"{name} must be one of {', '.join(allowed)}, got {value!r}", parameter=name)
        init_kind = self.init_parts()[0]
        if init_kind and init_kind != self.model:
            raise SonarSetError(f"init {self.init}: a {init_kind} checkpoint, but this run trains model {self.model}; "
                                f"set model {init_kind} to fine-tune it", parameter="init")

    def notes(self) -> list[str]:
        """Settings that run but are probably not meant: EchoWarp forecasts every horizon at once,
        and the options' defaults (the paper EchoPT's one-step windows) train its first alone."""
        if self.model == "echowarp" and self.k_max == 1 and not self.horizons:
            return ["note: EchoWarp on one-step windows (curriculum 1, the paper EchoPT's default) learns its first "
                    "horizon alone; its recipes train all ten (curriculum 10: docs/guides/training.md)"]
        return []

    def init_parts(self) -> tuple[str, str]:
        """``init`` as (kind, checkpoint): it may be written as eval names a checkpoint
        (``echowarp:RUN``); kind is "" when it names none."""
        kind, sep, spec = self.init.partition(":")
        return (kind, spec or "pretrained") if sep and kind in MODEL_KINDS else ("", self.init)

    def lr_at(self, step: int, total: int) -> float:
        """The learning rate of ``step`` of ``total``: constant, or the cosine schedule."""
        if self.schedule == "none" or total <= 0:
            return self.lr
        warm = max(1, int(0.02 * total))
        if step < warm:
            return self.lr * (step + 1) / warm
        t = min(1.0, (step - warm) / max(1, total - warm))
        return self.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * t)))

    def world_list(self) -> list[str] | None:
        """The world families to train on, or None for every training run."""
        names = [w.strip() for w in self.worlds.split(",") if w.strip()]
        return names or None

    def k_at(self, step: int) -> int:
        return [k for s, k in self.stages() if s <= step][-1]

    @property
    def k_max(self) -> int:
        return max(k for _, k in self.stages())


#: Settings that must not change when a run is resumed.
RESUME_KEYS = ("model", "preset", "batch_size", "seed", "n_val", "lr", "schedule", "epochs", "max_steps", "prior", "loss",
               "curriculum", "pushforward", "step_weights", "horizons", "context_noise", "val_horizon", "optimizer",
               "weight_decay", "init", "worlds", "n_in", "inputs", "geometry_channels", "trainable", "stream",
               "shuffle_buffer", "loader_workers")
#: Of those, the ones that matter only when the windows are streamed.
STREAM_KEYS = ("shuffle_buffer", "loader_workers")
