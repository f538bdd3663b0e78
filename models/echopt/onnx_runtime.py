"""EchoPT exported to ONNX (``sonarset export-onnx``), run by onnxruntime behind the predictor
interface: ``echopt:PATH.onnx`` wherever an EchoPT runs (eval, demo, experiments).

No torch here: a robot that has NumPy and onnxruntime can run the model. The model card travels
inside the file, as ONNX metadata (``echopt.card``: the JSON card of the checkpoint it came from,
plus flat keys for tools that only list metadata); the grid check and the notes on the images a
model was trained on read it as they read a checkpoint's card.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from sonarset.errors import GridMismatchError, SonarSetError
from sonarset.format.attrs import SensorGrid

from sonarset.models.predictor import BasePredictor, block_rollout, checked_horizons, rollout_steps

#: The metadata key of the model card (the JSON card of the exported checkpoint).
CARD_KEY = "echopt.card"
INPUTS = ("frames", "commands")
OUTPUT = "next_frame"
#: A direct forecaster's graph (EchoWarp): the frames ``horizons`` steps ahead, each from the
#: measured frames (models/echopt/onnx_export.py).
FORECAST_INPUTS = ("frames", "commands", "horizons")
FORECAST_OUTPUT = "forecast"
#: Windows per session run: onnxruntime's samples/s on 2 CPU cores peak near 16 windows and fall
#: by ~10% at 128 (bench/bench_infer.py, BENCHMARKS.md).
ONNX_BATCH = 16


def _runtime():
    try:
        import onnxruntime
    except ImportError:
        raise SonarSetError("ONNX models need onnxruntime: pip install 'sonarset[onnx]'") from None
    return onnxruntime


def _threads() -> int:
    """Intra-op threads: OMP_NUM_THREADS where set (the experiments' workers get one core each),
    else onnxruntime's default (0: one per physical core)."""
    try:
        return max(0, int(os.environ.get("OMP_NUM_THREADS", "0")))
    except ValueError:
        return 0


def open_session(path: str | os.PathLike, threads: int | None = None):
    """An onnxruntime CPU session of the ONNX file ``path``; one-line errors for a missing or bad file."""
    ort = _runtime()
    path = Path(path)
    if not path.is_file():
        raise SonarSetError(f"{path}: no ONNX model here")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = _threads() if threads is None else threads
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3  # errors only: its warnings are about the graph, not the user's input
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SonarSetError(f"{path}: not a readable ONNX model ({first})") from None


def session_card(session, path: str | os.PathLike) -> dict:
    """The EchoPT card in a session's metadata."""
    meta = session.get_modelmeta().custom_metadata_map
    if CARD_KEY not in meta:
        raise SonarSetError(f"{path}: an ONNX model without an EchoPT card (metadata {CARD_KEY!r}); "
                            "export it with 'sonarset export-onnx'")
    try:
        card = json.loads(meta[CARD_KEY])
    except ValueError as exc:
        raise SonarSetError(f"{path}: its EchoPT card (metadata {CARD_KEY!r}) is not JSON ({exc})") from None
    if not isinstance(card, dict) or not isinstance(card.get("config"), dict):
        raise SonarSetError(f"{path}: its EchoPT card (metadata {CARD_KEY!r}) has no model config")
    names = [i.name for i in session.get_inputs()], [o.name for o in session.get_outputs()]
    if (tuple(names[0]), names[1][:1]) not in ((INPUTS, [OUTPUT]), (FORECAST_INPUTS, [FORECAST_OUTPUT])):
        raise SonarSetError(f"{path}: inputs {names[0]} and outputs {names[1]}, not an EchoPT or EchoWarp export "
                            f"({', '.join(INPUTS)} -> {OUTPUT}, or {', '.join(FORECAST_INPUTS)} -> {FORECAST_OUTPUT})")
    return card


def graph_forecasts(session) -> bool:
    """Whether a checked session's graph is a direct forecast (FORECAST_INPUTS), not one next frame."""
    return tuple(i.name for i in session.get_inputs()) == FORECAST_INPUTS


def read_onnx_card(path: str | os.PathLike) -> dict:
    """The EchoPT card inside an ONNX export."""
    return session_card(open_session(path, threads=1), path)


class OnnxEchoPTPredictor(BasePredictor):
    """An exported EchoPT (or an EchoWarp exported before its graph forecast every horizon) under
    onnxruntime: the predictor interface of ``EchoPTPredictor``, a next frame per window."""

    precision = "fp32"  # the exported graph's; onnxruntime runs it as written
    output, layout = OUTPUT, ("batch", "range", "azimuth")

    def __init__(self, path: str | os.PathLike, grid: SensorGrid | None = None, batch_size: int = ONNX_BATCH,
                 threads: int | None = None, session=None):
        self.path = Path(path)
        self.session = session or open_session(self.path, threads)
        self.card = session_card(self.session, self.path)
        if graph_forecasts(self.session) != (self.output == FORECAST_OUTPUT):
            raise SonarSetError(f"{self.path}: a graph of {', '.join(i.name for i in self.session.get_inputs())}, "
                                f"not {type(self).__name__}'s; load it with load_onnx_predictor")
        cfg = self.card["config"]
        try:
            self.n_in = int(cfg["n_in"])
            self.shape = (int(cfg["n_range"]), int(cfg["n_azimuth"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise SonarSetError(f"{self.path}: its card's config lacks the grid or n_in ({exc})") from None
        trained = SensorGrid.model_validate(self.card["grid"]) if "grid" in self.card else None
        if grid is not None and trained is not None and not trained.matches(grid):
            title = {"echopt": "EchoPT", "echowarp": "EchoWarp"}.get(str(self.card.get("model", "echopt")), "the model")
            raise GridMismatchError(f"{self.path}: {title} was trained on grid {trained.describe()}, "
                                    f"the data has {grid.describe()}; retrain on this grid")
        if grid is not None and grid.shape != self.shape:
            raise GridMismatchError(f"{self.path}: the model takes {self.shape[0]}x{self.shape[1]} images, "
                                    f"the data has {grid.shape[0]}x{grid.shape[1]}")
        declared, rank, axes = self.session.get_outputs()[0].shape, len(self.layout), ", ".join(self.layout)
        fixed = [d for d in declared[-2:] if isinstance(d, int)] if declared else []
        if declared and (len(declared) != rank or len(fixed) == 2 and tuple(fixed) != self.shape):
            raise SonarSetError(f"{self.path}: the graph's {self.output} has shape {_shape_text(declared)}, its card "
                                f"says {self.shape[0]}x{self.shape[1]} images ({axes}): "
                                "a graph that does not match its card; export it again")
        self.grid = grid
        self.batch_size = batch_size
        self.name = str(self.card.get("model", "echopt"))  # the exported kind: echopt or echowarp
        self.label = f"{self.name} {self.path.name}"

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        out = np.empty((frames.shape[0], *frames.shape[2:]), dtype=np.float32)
        for lo in range(0, len(frames), self.batch_size):
            feed = {"frames": np.ascontiguousarray(frames[lo:lo + self.batch_size], dtype=np.float32),
                    "commands": np.ascontiguousarray(commands[lo:lo + self.batch_size], dtype=np.float32)}
            got = self.session.run([OUTPUT], feed)[0]  # clamped in the graph
            if got.shape != (len(feed["frames"]), *self.shape):
                raise SonarSetError(f"{self.path}: the graph's {OUTPUT} came out {_shape_text(got.shape)} for "
                                    f"{len(feed['frames'])} windows, its card says {self.shape[0]}x{self.shape[1]} "
                                    "images: a graph that does not match its card; export it again")
            out[lo:lo + len(feed["frames"])] = got
        return out


class OnnxForecastPredictor(OnnxEchoPTPredictor):
    """An exported direct forecaster (EchoWarp) under onnxruntime: ``DirectForecastPredictor``'s
    interface, each horizon forecast from the measured frames in the graph (its ``horizons``
    input), so that an AR-10 forecast is the model's own, not ten chained next frames."""

    output, layout = FORECAST_OUTPUT, ("batch", "horizon", "range", "azimuth")

    def __init__(self, path: str | os.PathLike, grid: SensorGrid | None = None, batch_size: int = ONNX_BATCH,
                 threads: int | None = None, session=None):
        super().__init__(path, grid, batch_size, threads, session)
        try:
            self.max_horizon = int(self.card["config"]["max_horizon"])
        except (KeyError, TypeError, ValueError) as exc:
            raise SonarSetError(f"{self.path}: its card's config lacks the forecast's max_horizon ({exc})") from None

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        return self.forecast_at(frames, commands[:, :self.n_in + 1], (1,))[:, 0]

    def rollout(self, frames: np.ndarray, commands: np.ndarray, horizon: int) -> np.ndarray:
        """(B, horizon, R, A): blocks of up to ``max_horizon`` steps, as ``ForecastPredictor``'s."""
        return block_rollout(lambda f, c, m: self.forecast_at(f, c, tuple(range(1, m + 1))), frames, commands,
                             horizon, self.max_horizon)

    def forecast_at(self, frames: np.ndarray, commands: np.ndarray, horizons: tuple[int, ...]) -> np.ndarray:
        """(B, len(horizons), R, A): the frames ``horizons`` (increasing) steps ahead, with commands
        (B, n_in + horizons[-1], 2), each from the measured frames; beyond ``max_horizon``, whose
        forecasts chain blocks, the rollout's steps are taken."""
        horizons = checked_horizons(horizons)
        if commands.shape[1] < self.n_in + horizons[-1]:
            raise ValueError(f"need {self.n_in + horizons[-1]} commands for horizon {horizons[-1]}, "
                             f"got {commands.shape[1]}")
        if horizons[-1] > self.max_horizon:
            return rollout_steps(self.rollout, frames, commands, horizons)
        out = np.empty((frames.shape[0], len(horizons), *self.shape), dtype=np.float32)
        steps = np.asarray(horizons, dtype=np.int64)
        per_run = max(1, round(self.batch_size / len(horizons)))  # images per run, as the one-step graph's
        for lo in range(0, len(frames), per_run):
            feed = {"frames": np.ascontiguousarray(frames[lo:lo + per_run], dtype=np.float32),
                    "commands": np.ascontiguousarray(commands[lo:lo + per_run, :self.n_in + horizons[-1]],
                                                     dtype=np.float32),
                    "horizons": steps}
            got = self.session.run([FORECAST_OUTPUT], feed)[0]  # clamped in the graph
            if got.shape != (len(feed["frames"]), len(horizons), *self.shape):
                raise SonarSetError(f"{self.path}: the graph's {FORECAST_OUTPUT} came out {_shape_text(got.shape)} "
                                    f"for {len(feed['frames'])} windows and {len(horizons)} horizons, its card says "
                                    f"{self.shape[0]}x{self.shape[1]} images: a graph that does not match its "
                                    "card; export it again")
            out[lo:lo + len(feed["frames"])] = got
        return out


def _shape_text(shape) -> str:
    return "x".join(str(d) if isinstance(d, int) else str(d or "?") for d in shape)


def load_onnx_predictor(path: str | os.PathLike, grid: SensorGrid | None = None,
                        kind: str = "echopt") -> OnnxEchoPTPredictor | OnnxForecastPredictor:
    """The export at ``path``, which must be of ``kind`` (its card's model): a direct forecast's graph
    as an OnnxForecastPredictor, a next frame's as an OnnxEchoPTPredictor."""
    session = open_session(path)
    cls = OnnxForecastPredictor if graph_forecasts(session) else OnnxEchoPTPredictor
    p = cls(path, grid, session=session)
    if p.name == "echowarp" and cls is OnnxEchoPTPredictor and int(p.card["config"].get("max_horizon", 1)) > 1:
        p.label += " (a next-frame graph, chained: export it again)"  # exported before its graph forecast
    if p.name != kind:
        raise SonarSetError(f"{path}: an ONNX export of {p.name}, not of {kind}; name it {p.name}:{path}")
    return p
