"""Export an EchoPT or EchoWarp checkpoint to ONNX (``sonarset export-onnx MODEL OUT.onnx``).

The graph is the predictor a robot runs, clamped to [0, 1] as in evaluation, with the acoustic-flow
geometry computed inside it:

- EchoPT: ``frames`` (batch, n_in, R, A) in [0, 1] and ``commands`` (batch, n_in + 1, 2) in m/s
  and rad/s give ``next_frame`` (batch, R, A);
- EchoWarp, which forecasts each horizon directly from the measured frames: ``frames``,
  ``commands`` (batch, n_in + the largest horizon, 2) and ``horizons`` (int64, increasing steps
  ahead, 1 to its ``max_horizon``) give ``forecast`` (batch, len(horizons), R, A): a robot asks
  for ``[1]``, the evaluation for the horizons it scores, and an AR-10 forecast is the model's own,
  not ten chained next frames.

The batch, command and horizon axes are dynamic. The checkpoint's card goes into the ONNX metadata
(models/echopt/onnx_runtime.py reads it), and the export is checked against torch on random sparse
windows before it is written.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from sonarset import __version__
from sonarset.store.atomic import atomic_write
from sonarset.errors import SonarSetError

from sonarset.models.echopt.checkpoint import load_checkpoint
from sonarset.models.echopt.model import EchoPT
from sonarset.models.echopt.networks import A_TITLE, TITLES, kind_of
from sonarset.models.echopt.onnx_runtime import CARD_KEY, FORECAST_INPUTS, FORECAST_OUTPUT, INPUTS, OUTPUT
from sonarset.models.registry import PRETRAINED, RECOMMENDED_KIND

#: The kinds that export as a graph (EchoPT's next frame, EchoWarp's forecast): the reference methods
#: are not shipped to robots, and ConvLSTM's recurrence and SimVP's slots were never checked against
#: onnxruntime.
ONNX_KINDS = ("echopt", "echowarp")
#: The largest torch-vs-onnxruntime difference an export may have (images are in [0, 1]). The two
#: round the warp's fp32 sampling coordinates differently by a few ulp (up to 8e-5 of a pixel at
#: range bin 200), which moves a sampled value by that times the image's steepest pixel step, 1 in
#: sparse random windows: the shipped EchoWarp differs by up to 1.4e-4 (mean 7e-7) on eight
#: windows at all ten horizons; the graph of a wrong horizon differs by 0.97.
PARITY_TOLERANCE = 1e-3
#: ONNX's Gelu operator is opset 20's: onnxruntime (>= 1.20, the onnx extra's) runs it as one kernel,
#: where opset 18 spells it as five (Div, Erf, Add, Mul, Mul) that also break the convolutions'
#: blocked layout: batch-1 latency 1.11x (EchoWarp) and 1.05x (EchoPT) on one core (bench_infer --opsets)
OPSET = 20


class DeployedEchoPT(nn.Module):
    """EchoPT as a predictor runs it: the output clamped to the energyscape's [0, 1]."""

    def __init__(self, model: EchoPT):
        super().__init__()
        self.model = model

    def forward(self, frames: torch.Tensor, commands: torch.Tensor) -> torch.Tensor:
        return self.model(frames, commands).clamp(0, 1)


class DeployedForecast(nn.Module):
    """A direct forecaster (EchoWarp) as a predictor runs it: the frames ``horizons`` steps ahead
    (a 1-D int64 tensor), clamped to [0, 1]; the checks of ``forecast_at`` are the runtime's
    (models/echopt/onnx_runtime.py), where the horizons are numbers, not a graph's input."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, frames: torch.Tensor, commands: torch.Tensor, horizons: torch.Tensor) -> torch.Tensor:
        return self.model.composed(self.model.slot_parts(frames, commands, horizons)).clamp(0, 1)


def exports_a_forecast(model: nn.Module) -> bool:
    """Whether ``model`` forecasts each of several horizons from the measured frames, and so exports
    as DeployedForecast (an EchoWarp of ``max_horizon`` 1, the ablation's chained one, forecasts the
    next frame alone: its rollout chains, and its graph is the next frame's)."""
    return callable(getattr(model, "slot_parts", None)) and model.max_horizon > 1


@dataclass
class Export:
    path: Path
    bytes: int
    max_abs_diff: float | None  # torch vs onnxruntime on the check windows; None without onnxruntime
    check_windows: int
    kind: str = "echopt"  # the exported network's


def random_windows(model: EchoPT, n: int, seed: int = 0, steps: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` windows shaped like sonar data: sparse frames (about 12% of pixels lit, as in the
    default 'ertis' images) and commands within the simulator's limits, for ``steps`` steps ahead."""
    cfg = model.cfg
    g = torch.Generator().manual_seed(seed)
    shape = (n, cfg.n_in, cfg.n_range, cfg.n_azimuth)
    frames = torch.rand(shape, generator=g) * (torch.rand(shape, generator=g) > 0.88)
    commands = (torch.rand((n, cfg.n_in + steps, 2), generator=g) * 2 - 1) * torch.tensor([0.3, 1.0])
    return frames, commands


def metadata(card: dict, model: EchoPT) -> dict[str, str]:
    """The ONNX metadata of an export: the whole card, and its main facts as flat keys."""
    cfg = model.cfg
    grid = card.get("grid") or {}
    flat = {
        CARD_KEY: json.dumps({**card, "config": cfg.to_dict(), "n_params": model.n_params()}),
        "echopt.preset": str(card.get("preset", "")),
        "echopt.prior": cfg.prior,
        "echopt.n_in": str(cfg.n_in),
        "echopt.grid": json.dumps(grid),
        "echopt.processing": json.dumps(card.get("processing")),
        "echopt.rig": json.dumps(card.get("rig")),
        "echopt.trained_precision": str((card.get("training") or {}).get("precision", "fp32")),
        "echopt.inputs": (f"frames: float32 (batch, {cfg.n_in}, {cfg.n_range}, {cfg.n_azimuth}) energyscapes "
                          f"in [0, 1], oldest first; commands: float32 (batch, {cfg.n_in + 1}, 2) (v m/s, "
                          "omega rad/s), commands[:, -1] moves the robot from the last frame to the predicted one"),
        "echopt.output": f"next_frame: float32 (batch, {cfg.n_range}, {cfg.n_azimuth}) in [0, 1]",
        "sonarset.version": __version__,
    }
    if exports_a_forecast(model):
        h = model.max_horizon
        flat["echopt.inputs"] = (
            f"frames: float32 (batch, {cfg.n_in}, {cfg.n_range}, {cfg.n_azimuth}) energyscapes in [0, 1], oldest "
            f"first; commands: float32 (batch, {cfg.n_in} + H, 2) (v m/s, omega rad/s), commands[:, {cfg.n_in} + t - 1] "
            f"moves the robot from frame t - 1 to frame t ahead, H the largest horizon; horizons: int64 (k,), "
            f"increasing steps ahead, 1 to {h}")
        flat["echopt.output"] = f"forecast: float32 (batch, k, {cfg.n_range}, {cfg.n_azimuth}) in [0, 1]"
        flat["echopt.max_horizon"] = str(h)
    return flat


def _hypot(x, y):
    """aten::hypot in ONNX, which has no such operator: sqrt(x^2 + y^2) (the flow prior's ranges are
    metres, far from where hypot's overflow guard matters)."""
    from onnxscript import opset20 as op  # OPSET's

    return op.Sqrt(op.Add(op.Mul(x, x), op.Mul(y, y)))


def _onnx_modules():
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401  torch's ONNX exporter translates through it
    except ImportError:
        raise SonarSetError("export-onnx needs onnx and onnxscript: pip install 'sonarset[onnx]'") from None
    import onnx

    return onnx


def export_onnx(spec: str | os.PathLike, out: str | os.PathLike, *, check_windows: int = 8,
                opset: int = OPSET) -> Export:
    """Export the checkpoint ``spec`` (``pretrained``, the recommended shipped model; ``KIND:pretrained``;
    a run directory or a ``.safetensors`` path, EchoPT's, or ``echowarp:`` before one) to ``out``;
    written atomically, after the onnxruntime check where onnxruntime is installed."""
    out = Path(out)
    if out.suffix != ".onnx":
        raise SonarSetError(f"{out}: the output must be an .onnx file")
    if out.is_dir():
        raise SonarSetError(f"{out}: is a directory")
    onnx = _onnx_modules()
    text = str(spec)
    kind = next((k for k in ONNX_KINDS if text.startswith(f"{k}:")), None)
    if text == PRETRAINED:  # a bare pretrained is the recommended shipped model, as everywhere
        kind, text = RECOMMENDED_KIND, f"{RECOMMENDED_KIND}:{PRETRAINED}"
    model, card = load_checkpoint(text.removeprefix(f"{kind}:") if kind else text, kind=kind)
    if kind_of(model) not in ONNX_KINDS:
        raise SonarSetError(f"{spec}: {A_TITLE[kind_of(model)]} checkpoint; ONNX export is for "
                            f"{' and '.join(TITLES[k] for k in ONNX_KINDS)} only")
    model = model.float().eval()
    batch = torch.export.Dim("batch", min=1, max=1 << 16)
    if exports_a_forecast(model):
        deployed, names, output = DeployedForecast(model).eval(), list(FORECAST_INPUTS), FORECAST_OUTPUT
        n_in, most = model.cfg.n_in, model.max_horizon
        example = (*random_windows(model, 2, seed=1, steps=min(3, most)), torch.arange(1, min(3, most) + 1))
        dims = ({0: batch}, {0: batch, 1: torch.export.Dim("commands", min=n_in + 1, max=n_in + most)},
                {0: torch.export.Dim("horizons", min=1, max=most)})
    else:
        deployed, names, output = DeployedEchoPT(model).eval(), list(INPUTS), OUTPUT
        example, dims = random_windows(model, 2, seed=1), ({0: batch}, {0: batch})
    log = io.StringIO()
    exporter_log = logging.getLogger("torch.onnx")
    level = exporter_log.level
    try:
        # the exporter narrates each stage on stdout and logs optional torchvision ops it skips
        exporter_log.setLevel(logging.ERROR)
        with warnings.catch_warnings(), contextlib.redirect_stdout(log):
            warnings.simplefilter("ignore")
            program = torch.onnx.export(deployed, example, input_names=names, output_names=[output],
                                        dynamic_shapes=dims, opset_version=opset,
                                        dynamo=True, optimize=True, verbose=False, external_data=False,
                                        custom_translation_table={torch.ops.aten.hypot.default: _hypot})
    except Exception as exc:  # the exporter's own error types; the log says which op
        raise SonarSetError(f"{spec}: ONNX export failed ({type(exc).__name__}: {str(exc).splitlines()[0]})") from None
    finally:
        exporter_log.setLevel(level)
    proto = program.model_proto
    what = (f"the sonar energyscapes 1 to {model.max_horizon} steps ahead, each from {model.cfg.n_in} frames and "
            "the velocity commands up to it" if exports_a_forecast(model) else
            f"next sonar energyscape from {model.cfg.n_in} frames and {model.cfg.n_in + 1} velocity commands")
    proto.doc_string = (f"{TITLES[kind_of(model)]} ({card.get('preset', 'custom')} preset, {model.cfg.prior} prior) exported by "
                        f"sonarset {__version__}: {what}")
    del proto.metadata_props[:]
    for k, v in metadata(card, model).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.checker.check_model(proto)
    data = proto.SerializeToString()
    diff = _parity(data, deployed, check_windows) if check_windows else None
    if diff is not None and diff > PARITY_TOLERANCE:
        raise SonarSetError(f"{spec}: the ONNX graph differs from torch by {diff:.2e} (more than "
                            f"{PARITY_TOLERANCE:g}) on {check_windows} random windows; not written")
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, lambda p: p.write_bytes(data))
    return Export(out, len(data), diff, check_windows, kind_of(model))


@torch.no_grad()
def _parity(data: bytes, deployed: nn.Module, n: int) -> float | None:
    """Max |torch - onnxruntime| on ``n`` random windows of a few batch sizes (and, for a forecast,
    of a few sets of horizons); None without onnxruntime."""
    try:
        import onnxruntime as ort
    except ImportError:
        return None
    sess = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    model = deployed.model
    direct = isinstance(deployed, DeployedForecast)
    most = model.max_horizon if direct else 1
    frames, commands = random_windows(model, n, seed=2, steps=most)
    # batch 1 and the rest: the batch axis is dynamic; a forecast's horizons and commands are too
    # (every horizon on two windows: each is a slot of the pass, so this is 20 images, not 10 n)
    cases = [(0, 1, (1,)), (1, n, (1,)), (1, n, (most,)), (0, min(n, 2), tuple(range(1, most + 1)))]
    worst = 0.0
    for lo, hi, horizons in cases if direct else cases[:2]:
        if hi <= lo:
            continue
        f, c = frames[lo:hi], commands[lo:hi, :model.cfg.n_in + horizons[-1]]
        if direct:
            h = torch.tensor(horizons)
            ref = deployed(f, c, h).numpy()
            got = sess.run([FORECAST_OUTPUT], {"frames": f.numpy(), "commands": c.numpy(), "horizons": h.numpy()})[0]
        else:
            ref = deployed(f, c).numpy()
            got = sess.run([OUTPUT], {"frames": f.numpy(), "commands": c.numpy()})[0]
        worst = max(worst, float(np.abs(ref - got).max()))
    return worst
