"""A raw microphone recording, read and checked completely before anything is written.

A recording is per-measurement microphone signals (T, channels, samples) in a ``.npz`` or a
directory of ``.npy`` files, with a JSON sidecar (``schema.RawRecordingMeta``: sample rate, sweep,
microphone layout, speed of sound). Every problem is one line naming the file; the check includes
one streamed pass over the signals for non-finite values and dead channels. Signals stay on disk
(``recording_files.RawSource``): they are read in blocks of measurements, so memory does not grow
with the recording's length.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from sonarset.format import plausibility
from sonarset.format.arrays import dtype_problem, layout_problem, nonfinite_problem, time_order_problem
from sonarset.errors import InputValidationError
from sonarset.ingest.files import RawSource, short_reason
from sonarset.format.units import grid_to_si, pose_to_si, time_to_si, velocity_to_si
from sonarset.format.attrs import RawRecordingMeta, SensorGrid, pydantic_problems
from sonarset.ingest.metadata import read_sidecar, sidecar_for

ARRAY_KEYS = ("signals", "velocity", "time", "pose", "sweep")
REQUIRED_KEYS = ("signals", "velocity", "time")
BLOCK = 8  # measurements read and beamformed at a time (8 x 32 x 7000 float32: 7 MB); divides a chunk
MAX_LAYOUT_M = 1.0  # microphones farther from the emitter than this: probably not metres


@dataclass
class RawRecording:
    """A validated raw recording, its signals still on disk."""

    source_path: str
    meta: RawRecordingMeta
    reader: RawSource
    positions: np.ndarray  # (M, 3) metres
    sweep: np.ndarray  # at sample_rate_hz
    first: int  # first measurement imported (1 with velocity_alignment 'next')
    arrays: dict[str, np.ndarray] = field(default_factory=dict)  # velocity, time, pose: SI, aligned

    @property
    def n_frames(self) -> int:
        return int(self.arrays["time"].shape[0])

    @property
    def n_samples(self) -> int:
        return int(self.reader.members["signals"].shape[2])


def load_raw(src: str | os.PathLike, meta_path: str | os.PathLike | None = None, *,
             grid: SensorGrid | None = None, scan: bool = True) -> tuple[RawRecording, SensorGrid]:
    """Read and check a raw recording; raise InputValidationError listing every problem.

    ``grid``: the output grid (an existing store's); default: the sidecar's, else the default grid.
    ``scan``: also read every signal once, for non-finite values and silent channels.
    """
    src = Path(src)
    where = str(src)
    if not src.exists():
        raise InputValidationError(where, ["no such file or directory"])
    reader = RawSource(src)
    problems = list(reader.problems)
    if problems and not reader.members:
        raise InputValidationError(where, problems)
    sidecar = Path(meta_path) if meta_path is not None else sidecar_for(src)
    meta = _raw_meta(sidecar, problems)
    problems += [f"unknown array {key!r} (expected {', '.join(ARRAY_KEYS)})" for key in reader.members
                 if key not in ARRAY_KEYS]
    problems += [f"missing required array {key!r}" for key in REQUIRED_KEYS if key not in reader.members]
    T, M, n = _signals_shape(reader, problems)
    small = _small_arrays(reader, T, problems)
    if meta is None:
        raise InputValidationError(where, problems)
    _small_to_si(small, meta, problems)
    positions = _layout(meta, sidecar, problems)
    if positions is not None and M is not None and M != len(positions):
        problems.append(f"signals: {M} channels but the microphone layout has {len(positions)} microphones")
    sweep = _sweep(meta, reader, problems)
    out_grid = _resolve_grid(meta, grid, problems)
    if out_grid is not None:
        problems += _grid_time_and_echo_problems(meta, out_grid, small.get("time"), n, sweep)
    if T is not None and meta.velocity_alignment == "next" and T < 2:
        problems.append("velocity_alignment 'next' needs at least 2 measurements")
    if not problems and scan:
        problems += _scan(reader, where)
    if problems:
        raise InputValidationError(where, problems)
    first = 1 if meta.velocity_alignment == "next" else 0
    arrays = {"time": small["time"][first:],
              "velocity": (small["velocity"][:-1] if first else small["velocity"]).astype(np.float32)}
    if "pose" in small:
        arrays["pose"] = small["pose"][first:]
    return RawRecording(where, meta, reader, positions, sweep, first, arrays), out_grid


def _raw_meta(sidecar: Path, problems: list[str]) -> RawRecordingMeta | None:
    """The sidecar's settings (sample rate, sweep, microphones...); None when missing or invalid."""
    if not sidecar.is_file():
        problems.append(f"{sidecar.name}: metadata file not found (the sidecar with sample rate, sweep, microphones)")
        return None
    doc = read_sidecar(sidecar, problems)
    if doc is None:
        return None
    try:
        return RawRecordingMeta.model_validate(doc)
    except ValidationError as exc:
        problems += pydantic_problems(exc, f"{sidecar.name}: ")
        return None


def _signals_shape(reader: RawSource, problems: list[str]) -> tuple[int | None, int | None, int | None]:
    """(measurements, channels, samples) of the signals; Nones when they cannot be streamed."""
    sig = reader.members.get("signals")
    if sig is None:
        return None, None, None
    if len(sig.shape) != 3:
        problems.append(f"signals: expected 3-D (measurement, channel, sample), got shape {sig.shape}")
    elif dtype_problem(sig) is not None:
        problems.append(f"signals: {dtype_problem(sig)}")
    elif 0 in sig.shape:
        problems.append(f"signals: empty, shape {sig.shape}")
    elif sig.fortran and sig.member is not None:
        problems.append("signals: stored in Fortran order, which a .npz cannot stream; save it C-ordered "
                        "(np.ascontiguousarray) or as a .npy")
    else:
        return sig.shape
    return None, None, None


def _small_arrays(reader: RawSource, n_measurements: int | None, problems: list[str]) -> dict[str, np.ndarray]:
    """velocity, time and pose, read whole (float64) once their headers pass the run-array checks."""
    small: dict[str, np.ndarray] = {}
    for key in ("velocity", "time", "pose"):
        m = reader.members.get(key)
        if m is None:
            continue
        line = dtype_problem(m) or layout_problem(key, m.shape)
        if line is None and n_measurements is not None and m.shape[0] != n_measurements:
            line = f"{m.shape[0]} rows but signals has {n_measurements} measurements"
        if line is None:
            try:
                arr = reader.read(key).astype(np.float64)
            except Exception as exc:
                line = f"unreadable ({short_reason(exc)})"
            else:
                line = nonfinite_problem(arr)
        if line is not None:
            problems.append(f"{key}: {line}")
            continue
        small[key] = arr
    return small


def _small_to_si(small: dict[str, np.ndarray], meta: RawRecordingMeta, problems: list[str]) -> None:
    """Convert ``small`` to SI in place, with the image importer's command and time-order rules."""
    u = meta.units
    if "velocity" in small:
        small["velocity"] = velocity_to_si(small["velocity"], u)
        problems += plausibility.command_problems(small["velocity"], meta.rig, u)
    if "time" in small:
        small["time"] = time_to_si(small["time"], u)
        line = time_order_problem(small["time"], unit="measurement")
        if line is not None:
            problems.append(f"time: {line}")
    if "pose" in small:
        small["pose"] = pose_to_si(small["pose"], u)


def _grid_time_and_echo_problems(meta: RawRecordingMeta, grid: SensorGrid, time: np.ndarray | None,
                                 n_samples: int | None, sweep: np.ndarray | None) -> list[str]:
    """The declared grid's and the time stamps' plausibility, and whether every measurement holds
    the echoes from the grid's first to its last range."""
    from sonarset.sensor.beamform import MARGIN_S

    out = plausibility.grid_problems(grid, meta.units) if meta.grid is not None else []
    if time is not None:
        out += plausibility.time_problems(time, meta.rig.frame_interval_s if meta.rig else None,
                                          grid.range_max_m, meta.units, "sidecar's rig")
    if n_samples is None or sweep is None:
        return out
    fs, c = meta.sample_rate_hz, meta.speed_of_sound_m_s
    reach = (n_samples - len(sweep)) / fs + meta.start_time_s  # the last echo whose sweep ends in the record
    if reach < 2 * grid.range_max_m / c:
        out.append(f"signals: {n_samples} samples at {fs:g} Hz hold complete echoes out to "
                   f"{max(reach, 0) * c / 2:.2f} m; the grid reaches {grid.range_max_m:g} m")
    if 2 * grid.range_min_m / c - MARGIN_S < meta.start_time_s:
        out.append(f"metadata.start_time_s: {meta.start_time_s:g} s is after the echoes of the grid's "
                   f"first range ({grid.range_min_m:g} m)")
    return out


def chirp(f0: float, f1: float, duration: float, fs: float, window: str = "hann") -> np.ndarray:
    """A linear FM sweep sampled at fs, as ``sim.sonar.sweep`` makes the eRTIS one."""
    from scipy import signal

    t = np.arange(int(round(duration * fs))) / fs
    s = signal.chirp(t, f0, duration, f1)
    return s * signal.windows.hann(len(t)) if window == "hann" else s


def _layout(meta: RawRecordingMeta, sidecar: Path, problems: list[str]) -> np.ndarray | None:
    from sonarset.sensor.beamform import read_layout_csv

    spec = meta.microphones
    if isinstance(spec, str):
        if spec == "ertis32":
            return read_layout_csv()
        path = (sidecar.parent / spec) if not Path(spec).is_absolute() else Path(spec)
        try:
            pos = read_layout_csv(path)
        except FileNotFoundError:
            problems.append(f"{path.name}: microphone layout file not found")
            return None
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            problems.append(f"{path.name}: not a microphone layout CSV ({short_reason(exc)})")
            return None
        where = path.name
    else:
        where = "metadata.microphones"
        rows = spec
        if any(len(r) not in (2, 3) for r in rows):
            problems.append(f"{where}: each position must be [x, y] or [x, y, z] in metres")
            return None
        pos = np.array([list(r) + [0.0] * (3 - len(r)) for r in rows], float)
    if len(pos) < 3:
        problems.append(f"{where}: {len(pos)} microphone(s); beamforming needs at least 3")
        return None
    if not np.all(np.isfinite(pos)):
        problems.append(f"{where}: positions contain NaN or infinite values")
        return None
    far = float(np.abs(pos).max())
    if far > MAX_LAYOUT_M:
        problems.append(f"{where}: microphones up to {far:g} from the emitter; positions must be metres "
                        "(millimetres?)")
        return None
    if len(np.unique(np.round(pos[:, :2], 9), axis=0)) < len(pos):
        problems.append(f"{where}: two microphones share a horizontal position")
        return None
    return pos


def _sweep(meta: RawRecordingMeta, reader: RawSource, problems: list[str]) -> np.ndarray | None:
    fs = meta.sample_rate_hz
    has_array = "sweep" in reader.members
    if has_array and meta.sweep is not None:
        problems.append("the sweep is given twice (sidecar 'sweep' and a 'sweep' array): keep one")
        return None
    if not has_array and meta.sweep is None:
        problems.append("no emitted sweep: give sidecar 'sweep' (parameters or samples) or a 'sweep' array")
        return None
    if has_array:
        m = reader.members["sweep"]
        if len(m.shape) != 1 or m.dtype.kind not in "fiu":
            problems.append(f"sweep: expected a 1-D real array, got shape {m.shape} of {m.dtype}")
            return None
        s = reader.read("sweep").astype(float)
        where = "sweep"
    elif meta.sweep.samples is not None:
        s, where = np.array(meta.sweep.samples, float), "metadata.sweep.samples"
    else:
        sw = meta.sweep
        top = max(sw.f_start_hz, sw.f_end_hz)
        if top >= 0.45 * fs:
            problems.append(f"metadata.sample_rate_hz: {fs:g} Hz cannot carry the sweep's {top:g} Hz "
                            f"(needs more than {top / 0.45:.0f} Hz)")
            return None
        s, where = chirp(sw.f_start_hz, sw.f_end_hz, sw.duration_s, fs, sw.window), "metadata.sweep"
    if len(s) < 8:
        problems.append(f"{where}: {len(s)} samples at {fs:g} Hz is too short for a sweep")
        return None
    if not np.all(np.isfinite(s)) or not np.any(s):
        problems.append(f"{where}: samples must be finite and not all zero")
        return None
    return s


def _resolve_grid(meta: RawRecordingMeta, grid: SensorGrid | None, problems: list[str]) -> SensorGrid | None:
    declared = None
    if meta.grid is not None:
        try:
            declared = grid_to_si(meta.grid, meta.units)
        except ValidationError as exc:
            problems.extend(pydantic_problems(exc, "metadata.grid."))
            return None
    if grid is not None and declared is not None and not grid.matches(declared, rtol=1e-4):
        problems.append(f"metadata.grid {declared.describe()} differs from the store's {grid.describe()}")
        return None
    return grid or declared or SensorGrid.default()


def _scan(reader: RawSource, where: str) -> list[str]:
    """One streamed pass over the signals: non-finite values, silent channels, a truncated archive."""
    m = reader.members["signals"]
    loud = np.zeros(m.shape[1], bool)
    try:
        for i, blk in reader.blocks("signals", BLOCK):
            if blk.dtype.kind == "f" and not np.all(np.isfinite(blk)):
                k, ch = np.argwhere(~np.isfinite(blk).all(axis=2))[0]
                return [f"signals: NaN or infinite values in measurement {i + k}, channel {ch}"]
            loud |= np.any(blk != 0, axis=(0, 2))
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, zlib.error) as exc:
        return [f"signals: unreadable ({short_reason(exc)}); is the file truncated?"]
    if not loud.all():
        dead = np.flatnonzero(~loud)
        return [f"signals: channel(s) {', '.join(map(str, dead[:8]))} are zero in every measurement "
                "(a dead microphone or a wrong channel map)"]
    return []
