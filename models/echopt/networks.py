"""The networks the trainer builds and a checkpoint holds, by kind: EchoPT, and the reference methods
of video prediction (models/zoo/). One place maps a kind to its config and presets, so that
training, checkpoints and predictors treat every kind alike.
"""

from __future__ import annotations

import torch.nn as nn

from sonarset.models.echopt.config import PRESETS as ECHOPT_PRESETS
from sonarset.models.echopt.config import EchoPTConfig, make_config
from sonarset.models.echopt.model import EchoPT
from sonarset.models.zoo import ZOO, network

#: The kinds, EchoPT first; train_config.MODEL_KINDS names the same.
KINDS = ("echopt", *ZOO)
#: How messages name each kind, and with its article.
TITLES = {"echopt": "EchoPT", "convlstm": "ConvLSTM", "simvp": "SimVP", "unet": "U-Net", "echowarp": "EchoWarp"}
A_TITLE = {"echopt": "an EchoPT", "convlstm": "a ConvLSTM", "simvp": "a SimVP", "unet": "a U-Net", "echowarp": "an EchoWarp"}


def kind_of(model: nn.Module) -> str:
    """The kind of a network built here."""
    return getattr(model, "kind", "echopt") or "echopt"


def presets(kind: str) -> tuple[str, ...]:
    return tuple(ECHOPT_PRESETS) if kind == "echopt" else tuple(network(kind).presets)


def preset_refusal(kind: str, preset: str) -> str | None:
    """Why ``kind`` cannot be built at ``preset`` (None: it can), in words for an error message."""
    known = presets(kind)
    if preset in known:
        return None
    what = "EchoPT's only (the paper's network)" if preset in presets("echopt") else "unknown"
    return f"{what}; {kind} has {', '.join(known)}"


def build(kind: str, preset: str, n_range: int, n_azimuth: int, **overrides) -> nn.Module:
    """A ``kind``'s ``preset`` network on an ``n_range`` x ``n_azimuth`` grid (``overrides``: any
    config field; ValueError, or config.ConfigError naming the setting, for one no network can have)."""
    if kind == "echopt":
        return EchoPT(make_config(preset, n_range, n_azimuth, **overrides))
    net = network(kind)
    return net.model(net.make_config(preset, n_range, n_azimuth, **overrides))


def from_config(kind: str, config: dict) -> nn.Module:
    """The network a model card's ``config`` describes (checked: ValueError, KeyError or TypeError
    for a card no network can have)."""
    if kind == "echopt":
        cfg = EchoPTConfig.from_dict(config)
        cfg.check()
        return EchoPT(cfg)
    net = network(kind)
    cfg = net.config.from_dict(config)
    cfg.check()
    return net.model(cfg)
