"""``sonarset view``: a run, and what models predicted of it, as a Rerun recording (``.rrd``).

On a ``frame`` timeline and a ``time`` timeline (seconds), for each frame:
- ``sonar/image``: the energyscape, range up and left on the left (azimuth positive to the left);
- ``sonar/fan``: the same in metres in the sensor frame (forward up, left on the left);
- ``map/robot``, ``map/path``, ``map/fov`` and, for simulated runs, ``map/world``: the top-down map;
- ``commands/v``, ``commands/omega`` and, where recorded, ``signal/snr_db`` and ``robot/slip``;
- per model: ``predictions/NAME/image`` (its ``horizon``-step auto-regressive prediction of this
  frame) and ``predictions/NAME/error`` (|prediction - measured|).
A blueprint arranges the views. Frames are read and predicted ``block`` at a time and streamed to
the file, so memory does not grow with the run. Needs the ``view`` extra (rerun-sdk).
"""

from __future__ import annotations

import errno
import functools
import os
from pathlib import Path
from typing import Callable

import numpy as np

from sonarset.errors import SonarSetError
from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.store.atomic import refuse_non_regular
from sonarset.store.store import SonarStore

from sonarset.models.experiments.record import entity_name
from sonarset.models.predictor import CheckedPredictor

FAN_PIXELS = 256  # the metric fan's width and height


@functools.cache
def _viridis() -> np.ndarray:
    from matplotlib import colormaps

    return (colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)


def _colour(images: np.ndarray) -> np.ndarray:
    """(..., H, W) in [0, 1] -> uint8 RGB through viridis (the colour map of the static figures)."""
    return _viridis()[np.clip(np.nan_to_num(images) * 255, 0, 255).astype(np.uint8)]


def _as_picture(image: np.ndarray) -> np.ndarray:
    """Range up (far at the top) and positive azimuth (left) on the left, as the robot sees it."""
    return image[::-1, ::-1]


class FanMap:
    """Resamples energyscapes onto a metric fan (x forward up, y left on the left) with scipy."""

    def __init__(self, grid: SensorGrid, pixels: int = FAN_PIXELS):
        r_max = grid.range_max_m
        half = r_max * max(np.sin(min(abs(grid.azimuth_min_rad), np.pi / 2)),
                           np.sin(min(abs(grid.azimuth_max_rad), np.pi / 2)), 0.1)
        x = np.linspace(r_max, min(0.0, r_max * np.cos(max(abs(grid.azimuth_min_rad), abs(grid.azimuth_max_rad)))),
                        pixels)  # rows: forward distance, far first (top)
        y = np.linspace(half, -half, pixels)  # columns: left first
        X, Y = np.meshgrid(x, y, indexing="ij")
        r, a = np.hypot(X, Y), np.arctan2(Y, X)
        dr = (grid.range_max_m - grid.range_min_m) / grid.n_range
        da = (grid.azimuth_max_rad - grid.azimuth_min_rad) / grid.n_azimuth
        self.rows = (r - grid.range_min_m) / dr - 0.5
        self.cols = (a - grid.azimuth_min_rad) / da - 0.5
        self.inside = (r >= grid.range_min_m) & (r <= grid.range_max_m) & \
            (a >= grid.azimuth_min_rad) & (a <= grid.azimuth_max_rad)
        self.extent_m = (float(x[-1]), float(x[0]), float(half))

    def __call__(self, image: np.ndarray) -> np.ndarray:
        from scipy.ndimage import map_coordinates

        out = map_coordinates(image.astype(np.float32), [self.rows, self.cols], order=1, mode="nearest")
        return np.where(self.inside, out, 0.0)


def record_run(store: SonarStore, run_name: str | None, out: str | os.PathLike, *, models: list[str] = (),
               horizon: int = 1, frames: slice | None = None, device: str = "cpu", precision: str = "auto",
               block: int = 64, progress: Callable[[str, int, int], None] | None = None) -> Path:
    """Write run ``run_name`` (default: the first complete run) of ``store`` as a Rerun recording
    to ``out``, with each model's ``horizon``-step prediction of every frame that has the context.
    ``models`` are specs the registry resolves (models/registry.py)."""
    import rerun as rr

    from sonarset.models.registry import make_predictor

    refuse_non_regular(Path(out), "the recording", "the recording needs a .rrd file path")  # before any model loads
    name = run_name or (store.runs() or [None])[0]
    if name is None or name not in store.runs():
        raise SonarSetError(f"{store.location}: no complete run {name!r} (runs: {', '.join(store.runs())})",
                            parameter="run_name")
    if horizon < 1:
        raise SonarSetError(f"horizon must be >= 1, got {horizon}", parameter="horizon")
    run = store.run(name)
    T = run.n_frames
    start, stop, _ = (frames or slice(None)).indices(T)
    if stop - start < 1:
        raise SonarSetError(f"frames {start}:{stop} of run {name} ({T} frames) select nothing", parameter="frames")
    grid = store.grid
    time_s, velocity = run.read_time(), run.read("velocity")
    pose = run.read("pose") if run.has("pose") else None
    extras = {k: run.read(k) for k in ("snr_db", "slip") if run.has(k)}
    preds = {}
    if models:
        # the robot the baselines warp with, as eval takes it: the rig at the time stamps' interval
        dt = float(np.median(np.diff(time_s))) if T > 1 else 1.0 / store.attrs.frame_rate_hz
        rig = store.rig.model_copy(update={"frame_interval_s": dt}) if store.rig is not None \
            else RobotRig(frame_interval_s=dt, sensor_offset_m=0.0)
        for spec in dict.fromkeys(models):
            p = make_predictor(spec, grid, rig, device=device, precision=precision)
            key = next((k for k in (p.name, p.label, spec) if _logged_as(preds, k) is None), None)
            if key is None:  # as eval: two models of one name would be one entity in the recording
                raise SonarSetError(f"model {spec!r}: another model ({_logged_as(preds, p.name)!r}) would be logged "
                                    f"as the same entity, predictions/{entity_name(p.name)}; view them apart",
                                    parameter="model")
            preds[key] = p
    out = Path(out)
    aside = _aside_file(out)
    rec = rr.RecordingStream("sonarset", recording_id=f"{Path(store.location).name}/{name}")
    try:
        rec.save(aside, default_blueprint=_blueprint(list(preds), pose is not None))
        _record(rec, rr, name, run, store, preds, pose, extras, time_s, velocity, start, stop, horizon, block, progress)
        rec.flush()
        rec.disconnect()
        os.replace(aside, out)
    finally:
        rec.disconnect()  # closes the file before it is removed (a no-op after the first)
        aside.unlink(missing_ok=True)
    return out


def _aside_file(out: Path) -> Path:
    """A new hidden file beside ``out`` to record into; renamed over ``out`` only once complete, so
    an interrupted, killed or failing recording never replaces a good one nor looks like one.

    Refuses an ``out`` that is not a regular file (a folder, a FIFO that would block the writer for
    ever, a device) and says in one line why a file cannot be made there. Leftovers of killed
    recorders of this host are removed.
    """
    import socket

    refuse_non_regular(out, "the recording", "the recording needs a .rrd file path")
    host = "".join(c if c.isalnum() or c == "-" else "_" for c in socket.gethostname())[:40] or "host"
    _remove_dead_asides(out, host)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        for attempt in range(100):
            aside = out.with_name(f".{out.name}.{host}-{os.getpid()}-{attempt}.tmp")
            try:
                os.close(os.open(aside, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
                return aside
            except FileExistsError:
                continue
        raise FileExistsError(errno.EEXIST, "too many recordings of this process in flight")
    except OSError as exc:
        raise SonarSetError(f"{out}: cannot write the recording there ({exc.strerror or exc})",
                            parameter="out") from None


def _remove_dead_asides(out: Path, host: str) -> None:
    import re

    from sonarset.store.atomic import _alive

    pattern = re.compile(re.escape(f".{out.name}.{host}-") + r"(\d+)-\d+\.tmp")
    try:
        entries = list(out.parent.iterdir())
    except OSError:
        return
    for entry in entries:
        m = pattern.fullmatch(entry.name)
        if m is not None and not _alive(int(m.group(1))) and entry.is_file():
            entry.unlink(missing_ok=True)


def _record(rec, rr, name: str, run, store: SonarStore, preds: dict, pose, extras: dict, time_s, velocity, start: int,
            stop: int, horizon: int, block: int, progress) -> None:
    from sonarset.report.overview import simulated_world

    grid = store.grid
    fan = FanMap(grid)
    world = simulated_world(run.attrs.source)
    _log_static(rec, rr, world, pose, grid, fan)
    context = max((p.n_in for p in preds.values()), default=0)
    first_predicted = context + horizon - 1
    for a in range(start, stop, block):
        b = min(stop, a + block)
        lo = max(0, a - first_predicted) if preds else a
        images = run.read("images", lo, b).astype(np.float32)
        predicted = {n: _predict(p, images, velocity, lo, a, b, horizon) for n, p in preds.items()}
        for k in range(a, b):
            rec.set_time("frame", sequence=k)
            rec.set_time("time", duration=float(time_s[k] - time_s[0]))
            img = images[k - lo]
            rec.log("sonar/image", rr.Image(_colour(_as_picture(img))))
            rec.log("sonar/fan", rr.Image(_colour(fan(img))))
            rec.log("commands/v", rr.Scalars(float(velocity[k, 0])))
            rec.log("commands/omega", rr.Scalars(float(velocity[k, 1])))
            for key, values in extras.items():
                rec.log("signal/snr_db" if key == "snr_db" else "robot/slip",
                        rr.Scalars(np.atleast_1d(values[k]).astype(float)))
            if pose is not None:
                _log_pose(rec, rr, pose[k], grid)
            for n, pred in predicted.items():
                frame = pred.get(k)
                if frame is not None:
                    rec.log(f"predictions/{entity_name(n)}/image", rr.Image(_colour(_as_picture(frame))))
                    rec.log(f"predictions/{entity_name(n)}/error",
                            rr.Image(_colour(_as_picture(np.abs(frame - img)))))
        if progress:
            progress(name, b - start, stop - start)


def _predict(p: CheckedPredictor, images: np.ndarray, velocity: np.ndarray, lo: int, a: int, b: int,
             horizon: int) -> dict:
    """{frame k: the H-step prediction of frame k} for k in a..b-1 with the context in ``images``
    (frames lo..b-1): from frames k-H-n_in+1 .. k-H and commands k-H-n_in+1 .. k."""
    n_in = p.n_in
    ks = [k for k in range(a, b) if k - horizon - n_in + 1 >= lo]
    if not ks:
        return {}
    starts = np.array([k - horizon - n_in + 1 for k in ks])
    ctx = np.stack([images[s - lo:s - lo + n_in] for s in starts])
    cmds = np.stack([velocity[s:s + n_in + horizon] for s in starts]).astype(np.float32)
    out = p.forecast_at(ctx, cmds, (horizon,))[:, 0]  # a direct forecaster computes that step alone
    return dict(zip(ks, out))


def _log_static(rec, rr, world, pose, grid: SensorGrid, fan: FanMap) -> None:
    if world is not None:
        walls = [np.array([a, b]) for a, b in zip(world.seg_a, world.seg_b)]
        if walls:
            rec.log("map/world/walls", rr.LineStrips2D(walls, colors=[60, 60, 60]), static=True)
        t = np.linspace(0, 2 * np.pi, 33)
        circles = [np.c_[c[0] + r * np.cos(t), c[1] + r * np.sin(t)] for c, r in zip(world.circ_c, world.circ_r)]
        if circles:
            rec.log("map/world/circles", rr.LineStrips2D(circles, colors=[90, 90, 90]), static=True)
    if pose is not None:
        rec.log("map/path", rr.LineStrips2D([pose[:, :2]], colors=[31, 119, 180]), static=True)


def _log_pose(rec, rr, pose: np.ndarray, grid: SensorGrid) -> None:
    x, y, th = (float(v) for v in pose)
    rec.log("map/robot", rr.Arrows2D(origins=[[x, y]], vectors=[[0.4 * np.cos(th), 0.4 * np.sin(th)]],
                                     colors=[255, 127, 14]))
    a = np.linspace(grid.azimuth_min_rad, grid.azimuth_max_rad, 24) + th
    r = grid.range_max_m
    wedge = np.r_[[[x, y]], np.c_[x + r * np.cos(a), y + r * np.sin(a)], [[x, y]]]
    rec.log("map/fov", rr.LineStrips2D([wedge], colors=[255, 127, 14, 90]))


def _logged_as(models: dict, name: str) -> str | None:
    """The model of ``models`` whose entity a model named ``name`` would be logged as, if any."""
    return next((k for k in models if entity_name(k) == entity_name(name)), None)


def _blueprint(models: list[str], has_pose: bool):
    import rerun.blueprint as rrb

    sonar = rrb.Vertical(rrb.Spatial2DView(origin="sonar/image", name="energyscape (range x azimuth, left +)"),
                         rrb.Spatial2DView(origin="sonar/fan", name="fan (metres, forward up)"))
    right = [rrb.TimeSeriesView(origin="commands", name="commands (v, omega)"),
             rrb.TimeSeriesView(origin="signal", name="SNR"), rrb.TimeSeriesView(origin="robot", name="slip")]
    if has_pose:
        right.insert(0, rrb.Spatial2DView(origin="map", name="map"))
    views = [sonar, rrb.Vertical(*right)]
    if models:
        views.append(rrb.Grid(*[rrb.Spatial2DView(origin=f"predictions/{entity_name(m)}/{what}",
                                                  name=f"{m}: {what}")
                                for m in models for what in ("image", "error")]))
    return rrb.Blueprint(rrb.Horizontal(*views), collapse_panels=False)
