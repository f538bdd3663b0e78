"""The names the models answer to, and the predictor a name stands for.

It imports no torch and no SciPy (the predictors are imported when one is made), so the command
line reads ``BASELINES`` without loading a model.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sonarset.errors import SonarSetError
from sonarset.format.attrs import RobotRig, SensorGrid

if TYPE_CHECKING:
    from sonarset.models.baselines import Predictor

BASELINES = ("persistence", "naive", "flow")
#: The paper's prediction horizons (1 = one-shot), eval's and the demo's default.
HORIZONS = (1, 3, 5, 10)


def make_predictor(spec: str, grid: SensorGrid, rig: RobotRig, *, device: str = "cpu",
                   precision: str = "auto") -> Predictor:
    """The predictor for ``spec`` on ``grid``. The baselines turn commands into image motion with
    ``rig`` (the robot that made the frames); EchoPT uses the rig it was trained on (its config),
    in ``precision`` (models/echopt/precision.py: auto, fp32, bf16)."""
    from sonarset.models.baselines import AcousticFlow, NaiveShift, Persistence

    name, _, arg = spec.partition(":")
    if name == "persistence":
        return Persistence(grid)
    if name == "naive":
        return NaiveShift(grid, rig)
    if name == "flow":
        return AcousticFlow(grid, rig)
    if name == "echopt":
        if arg.endswith(".onnx"):  # onnxruntime, no torch
            from sonarset.models.echopt.onnx_runtime import load_onnx_predictor

            return load_onnx_predictor(arg, grid)
        try:
            from sonarset.models.echopt.predictor import load_echopt_predictor
        except ImportError as exc:
            raise SonarSetError(f"model {spec!r}: EchoPT is not available in this installation ({exc})") from None
        return load_echopt_predictor(arg or "pretrained", grid, device=device, precision=precision)
    raise SonarSetError(f"unknown model {spec!r}: use {', '.join(BASELINES)}, echopt:PATH or echopt:PATH.onnx",
                        parameter="model_specs")
