"""Resolve model specs from the command line (``naive``, ``flow``, ``echopt:PATH``) to predictors."""

from __future__ import annotations

from sonarset.errors import SonarSetError
from sonarset.schema import SensorGrid

from .baselines import AcousticFlow, NaiveShift, Persistence, Predictor

BASELINES = ("persistence", "naive", "flow")


def make_predictor(spec: str, grid: SensorGrid, *, dt: float = 0.2, sensor_offset: float = 0.0,
                   device: str = "cpu") -> Predictor:
    name, _, arg = spec.partition(":")
    if name == "persistence":
        return Persistence(grid)
    if name == "naive":
        return NaiveShift(grid, dt=dt)
    if name == "flow":
        return AcousticFlow(grid, dt=dt, sensor_offset=sensor_offset)
    if name == "echopt":
        try:
            from .echopt_predictor import load_echopt_predictor
        except ImportError as exc:
            raise SonarSetError(f"model {spec!r}: EchoPT is not available in this installation ({exc})") from None
        return load_echopt_predictor(arg or "pretrained", grid, device=device)
    raise SonarSetError(f"unknown model {spec!r}: use {', '.join(BASELINES)} or echopt:PATH")
