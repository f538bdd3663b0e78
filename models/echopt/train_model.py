"""The network a training run trains (``build_model``): of the run's kind (EchoPT or a reference
method of models/zoo/), on the store's grid and robot, seeded or warm-started from ``init``'s
weights, with its optimizer."""

from __future__ import annotations

import math

import torch
import torch.nn as nn

from sonarset.errors import SonarSetError
from sonarset.format.attrs import RobotRig
from sonarset.store.store import SonarStore

from sonarset.models.echopt.checkpoint import load_checkpoint
from sonarset.models.echopt.config import ADDABLE_FIELDS, WARM_START_FIELDS, ConfigError, grid_and_rig
from sonarset.models.echopt.model import GEOMETRY_PREFIX
from sonarset.models.echopt.networks import TITLES, build, preset_refusal
from sonarset.models.echopt.train_config import TrainConfig


def widenable(model: nn.Module) -> dict:
    """The config fields a fine-tune of ``model``'s kind may grow, each with its test (old, new config)."""
    if getattr(model, "kind", None) != "echowarp":
        return {}
    from sonarset.models.echowarp.widen import WIDENABLE_FIELDS, can_widen

    return dict.fromkeys(WIDENABLE_FIELDS, can_widen)


def _same(a, b) -> bool:
    """Equal, numbers to a float32's rounding (as ``SensorGrid.matches`` takes a grid's edges: a
    store imported from a bag has them as float32 bin centres made them)."""
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and math.isclose(a, b, rel_tol=1e-6,
                                                                                           abs_tol=1e-6)
    return a == b


def init_from(model: nn.Module, spec: str, trained: nn.Module, card: dict, store: SonarStore) -> None:
    """Copy a trained model's weights into ``model``, which must be the same network on the same grid,
    trained on the same images (a fine-tune continues a model; it cannot change what it is, except
    how its inputs are prepared: ``WARM_START_FIELDS``; or add a branch it lacks, which starts at
    zero: ``ADDABLE_FIELDS``; or, for EchoWarp, widen its U-Net, computing the same function:
    models/echowarp/widen.py)."""
    from sonarset.models.echopt.card_images import card_processing, describe_images

    differ = [k for k in model.cfg.__dataclass_fields__ if not _same(getattr(trained.cfg, k), getattr(model.cfg, k))]
    added = [k for k in differ if k in ADDABLE_FIELDS and not getattr(trained.cfg, k)]
    growable = widenable(model)
    widened = [k for k in differ if k in growable and growable[k](trained.cfg, model.cfg)]
    if any(k not in WARM_START_FIELDS and k not in added and k not in widened for k in differ):
        diff = ", ".join(f"{k}: {getattr(trained.cfg, k)!r} vs {getattr(model.cfg, k)!r}" for k in differ)
        rigless = "dt" in differ and getattr(store, "rig", 0) is None
        why = "; this store records no rig, so its frame rate sets dt" if rigless else ""
        raise SonarSetError(f"init {spec}: another network than this preset and prior make here ({diff}){why}",
                            parameter="init")
    trained_on = card_processing(card)
    if not trained_on.same_images(store.processing):
        way_out = "train from scratch, or write them to a store that makes its images the same way"
        if store.processing.unknown:  # the user may know what the import did not record
            way_out = (f"if they are made as {trained_on.profile}'s are, say so in the processing block of the "
                       "import's metadata and import them again; else train from scratch")
        raise SonarSetError(f"init {spec}: trained on {describe_images(trained_on)}, {store.location} has "
                            f"{describe_images(store.processing)}; {way_out}", parameter="init")
    if widened:
        from sonarset.models.echowarp.widen import widen_into

        if set(trained.state_dict()) != set(model.state_dict()):  # widening changes shapes, never names
            raise SonarSetError(f"init {spec}: its weights do not fit this network "
                                f"({', '.join(sorted(set(trained.state_dict()) ^ set(model.state_dict())))})",
                                parameter="init")
        try:
            widen_into(model, trained, seed=torch.initial_seed())
        except (RuntimeError, ValueError) as exc:
            raise SonarSetError(f"init {spec}: cannot widen it into this network ({exc})", parameter="init") from None
        return
    missing, unexpected = model.load_state_dict(trained.state_dict(), strict=not added)
    if unexpected or any(not k.startswith(GEOMETRY_PREFIX) for k in missing):  # only the added branch may be new
        raise SonarSetError(f"init {spec}: its weights do not fit this network ({', '.join(unexpected + missing)})",
                            parameter="init")


def refuse_echopt_options(cfg: TrainConfig) -> None:
    """A reference method (``cfg.model`` other than echopt) has its own presets, and none of
    EchoPT's own options: each is refused in one line naming it, not silently ignored."""
    kind, title = cfg.model, TITLES[cfg.model]
    why = preset_refusal(kind, cfg.preset)
    if why:
        raise SonarSetError(f"preset {cfg.preset}: {why}", parameter="preset")
    if cfg.geometry_channels > 0:
        raise SonarSetError(f"geometry_channels {cfg.geometry_channels}: an EchoPT option; {title} has no geometry "
                            "branch", parameter="geometry_channels")
    if cfg.trainable != "all":
        raise SonarSetError(f"trainable {cfg.trainable}: an EchoPT option (its geometry branch); {title} trains all "
                            "its weights", parameter="trainable")


def build_model(store: SonarStore, cfg: TrainConfig, device: str) -> tuple[nn.Module, torch.optim.Optimizer]:
    """The network of kind ``cfg.model`` for the store's grid and robot (seeded, or ``init``'s
    weights) on ``device``, and its optimizer."""
    if cfg.model != "echopt":
        refuse_echopt_options(cfg)
    torch.manual_seed(cfg.seed)
    trained = card = None
    if cfg.init:
        trained, card = load_checkpoint(cfg.init_parts()[1], store.grid, kind=cfg.model)
    # A store without a rig: one step is its own frame interval (not the simulator's 0.2 s), and
    # the sensor sits where eval's baselines put it (models/eval/evaluate.py, baseline_rig), on the
    # wheel axle, or, for a fine-tune, where the model was trained with it: the store says nothing.
    rig = store.rig or RobotRig(frame_interval_s=1.0 / store.attrs.frame_rate_hz,
                                sensor_offset_m=trained.cfg.sensor_offset if trained is not None else 0.0)
    overrides = grid_and_rig(store.grid, rig)
    if cfg.prior:
        overrides["prior"] = cfg.prior
    if cfg.n_in:
        overrides["n_in"] = cfg.n_in
    if cfg.inputs or trained is not None:  # a fine-tune keeps its model's unless told otherwise
        overrides["inputs"] = cfg.inputs or trained.cfg.inputs
    if cfg.model == "echopt" and cfg.geometry_channels >= 0:
        overrides["geometry_channels"] = cfg.geometry_channels
    elif cfg.model == "echopt" and trained is not None:
        overrides["geometry_channels"] = trained.cfg.geometry_channels
    try:
        model = build(cfg.model, cfg.preset, *store.grid.shape, **overrides)
    except ValueError as exc:  # a size this run set, else what it derives from (n_in sets d_model)
        setting = exc.setting if isinstance(exc, ConfigError) else None
        what = setting if setting in ("n_in", "geometry_channels") else "n_in" if cfg.n_in else "preset"
        raise SonarSetError(f"{what} {getattr(cfg, what)}: {exc}", parameter=what) from None
    if trained is not None:
        init_from(model, cfg.init, trained, card, store)
    if cfg.trainable == "geometry":
        if not model.cfg.geometry_channels:
            raise SonarSetError("trainable geometry: the model has no geometry branch (geometry_channels 0)",
                                parameter="trainable")
        for name, p in model.named_parameters():
            p.requires_grad_(name.startswith(GEOMETRY_PREFIX))
    model = model.to(device).to(memory_format=torch.channels_last)
    opt_cls = torch.optim.AdamW if cfg.optimizer == "adamw" else torch.optim.Adam
    opt = opt_cls([p for p in model.parameters() if p.requires_grad], lr=cfg.lr, betas=(0.9, 0.999), eps=1e-8,
                  weight_decay=cfg.weight_decay)
    return model, opt
