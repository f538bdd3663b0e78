"""Reference methods of video prediction, action-conditioned, trained by EchoPT's trainer
(``sonarset train`` with model convlstm, simvp or unet) on the same windows and losses: ConvLSTM
(convlstm.py), SimVP (simvp.py) and a U-Net over the flow warp (unet.py); what they share is
common.py. ``ZOO`` also maps sonarset's own EchoWarp (models/echowarp/), built on the same base, so
that the trainer, checkpoints and the registry treat it alike.

Importing this package loads no torch: :func:`network` imports a method's module when one is built.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable

#: The methods by the name ``--model`` and a model card use: (module, network class, config class).
ZOO = {"convlstm": ("convlstm", "ConvLSTM", "ConvLSTMConfig"),
       "simvp": ("simvp", "SimVP", "SimVPConfig"),
       "unet": ("unet", "UNet", "UNetConfig"),
       "echowarp": ("sonarset.models.echowarp.model", "EchoWarp", "EchoWarpConfig")}
#: The reference methods of video prediction among them (the rest are sonarset's own designs).
REFERENCE_METHODS = ("convlstm", "simvp", "unet")
#: What each is, in a line (``sonarset models`` lists it beside ``KIND:PATH``).
DESCRIPTIONS = {
    "convlstm": "ConvLSTM (Shi 2015), action-conditioned: trained with model = convlstm",
    "simvp": "SimVP + gSTA (Gao 2022, Tan 2022), every horizon in one pass: trained with model = simvp",
    "unet": "U-Net over the flow warp (Ronneberger 2015, RainNet 2020): trained with model = unet",
    "echowarp": "EchoWarp: corrected motion + source term, every horizon in one pass: trained with model = echowarp",
}


@dataclass(frozen=True)
class Network:
    """A method's network class, its config class and its presets."""

    kind: str
    model: Any
    config: Any
    presets: dict[str, dict]

    def make_config(self, preset: str, n_range: int, n_azimuth: int, **overrides):
        from sonarset.models.zoo.common import make_config

        return make_config(self.config, self.presets, preset, n_range, n_azimuth, **overrides)


def network(kind: str) -> Network:
    """The method named ``kind`` (a key of ``ZOO``)."""
    module_name, model, config = ZOO[kind]
    module = importlib.import_module(module_name if "." in module_name else f"sonarset.models.zoo.{module_name}")
    return Network(kind, getattr(module, model), getattr(module, config), module.PRESETS)


def checkpoint_loader(kind: str) -> Callable:
    """The model registry's loader of ``KIND:PATH`` (models/registry.py ``CHECKPOINT_KINDS``):
    ``(arg, grid, rig, device, precision) -> predictor``; a checkpoint of another kind is refused.
    Torch is imported when a model is loaded, not here."""
    if kind not in ZOO:
        raise ValueError(f"unknown reference method {kind!r}; choose from {', '.join(ZOO)}")

    def load(arg: str, grid, rig=None, device: str = "cpu", precision: str = "auto"):
        if arg.endswith(".onnx"):  # an export (EchoWarp's): onnxruntime, without torch
            from sonarset.models.echopt.onnx_runtime import load_onnx_predictor

            return load_onnx_predictor(arg, grid, kind=kind)
        from sonarset.models.echopt.predictor import load_learned_predictor

        return load_learned_predictor(arg, grid, device=device, precision=precision, kind=kind)

    load.__doc__ = DESCRIPTIONS[kind]
    return load
