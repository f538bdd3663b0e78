"""Plausibility: values that no in-air sonar on a ground robot records, read as unit mistakes.

The format checks (``sonarset.store.validate``, ``sonarset.format.arrays``) say whether a store is well formed;
these rules say whether its numbers could be true. Each finding is a Problem at the array (or
``grid``, ``metadata``) naming the values and, where one explains them, the likely unit mistake
(``cm/s declared as m/s?``). ``validate`` applies them to a store against its own rig, ``import``
to a recording against the store it goes to (else its sidecar's rig); ``allow_implausible`` lets a
user who means it go on. spec/FORMAT.md §10 lists the rules and their thresholds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import numpy as np

from sonarset.errors import RemoteError
from sonarset.format.arrays import FRAME_INTERVAL_TOLERANCE
from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.format.sidecars import RecordingUnits
from sonarset.format.problems import Problem
from sonarset.sensor.ertis import C_SOUND

#: Commands may exceed the rig's declared limits by this fraction (controller overshoot, rounding).
COMMAND_TOLERANCE = 0.25
#: Without a rig: faster than any indoor ground robot drives or turns.
MAX_SPEED_M_S = 10.0
MAX_TURN_RAD_S = 20.0
#: The median time between frames may differ from the declared interval by this fraction: the
#: read path's own tolerance (``sonarset.format.arrays``), so an import never writes what readers refuse.
FRAME_TOLERANCE = FRAME_INTERVAL_TOLERANCE
#: Without a declared rate: frames further apart than this are not a sonar stream.
MAX_FRAME_INTERVAL_S = 60.0
#: An in-air sonar image reaches beyond 10 cm (its own ring-down and pulse length) and stays
#: within 100 m (air absorbs ~1.3 dB/m at 40 kHz: 260 dB over a 100 m round trip).
MIN_RANGE_MAX_M = 0.1
MAX_RANGE_M = 100.0
#: An imaging sonar's field of view spans tens of degrees; under 10 deg it is degrees read as radians.
MIN_AZIMUTH_SPAN_RAD = math.radians(10.0)
#: A unit mistake is suggested only when the values are this many times beyond the limit.
HINT_FACTOR = 5.0

UNIT_SCALES: dict[str, dict[str, float]] = {
    "range": {"m": 1.0, "cm": 1e-2, "mm": 1e-3},
    "azimuth": {"rad": 1.0, "deg": math.pi / 180},
    "linear_velocity": {"m/s": 1.0, "cm/s": 1e-2, "mm/s": 1e-3},
    "angular_velocity": {"rad/s": 1.0, "deg/s": math.pi / 180},
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9},
}
_SI = {"range": "m", "azimuth": "rad", "linear_velocity": "m/s", "angular_velocity": "rad/s", "time": "s"}


@dataclass(frozen=True)
class Implausible(Problem):
    """A validation problem from these rules: ``allow_implausible`` lets it pass, and readers
    accept such values (only commands no ground robot could follow are unreadable:
    ``sonarset.format.rules.command_limit_problems``)."""

    refused_by_readers: ClassVar[bool] = False


_NAMES = {"m": "metres", "cm": "centimetres", "mm": "millimetres", "rad": "radians", "deg": "degrees",
          "m/s": "m/s", "cm/s": "cm/s", "mm/s": "mm/s", "rad/s": "rad/s", "deg/s": "deg/s",
          "s": "seconds", "ms": "milliseconds", "us": "microseconds", "ns": "nanoseconds"}


def unit_hint(kind: str, value_si: float, ok: Callable[[float], bool], typical: float,
              declared: RecordingUnits | None = None) -> str:
    """The unit mistake that makes ``value_si`` plausible and closest to ``typical``, or ''.

    With ``declared`` units (an import), the values were read in the declared unit: the hint names
    the unit they were really in. Without (a store, already in SI), it names the pair a converter
    confused. A value within ``HINT_FACTOR`` of ``typical`` is a wrong limit, not a wrong unit.
    """
    if not (value_si > 0 and math.isfinite(value_si)):
        return ""
    if max(value_si / typical, typical / value_si) < HINT_FACTOR:
        return ""
    scales = UNIT_SCALES[kind]
    si = _SI[kind]
    # In a store, values equally well explained by several pairs (ms/s, us/ms...) are put down to
    # the pair with the SI unit: the unit of the file and the unit of the store.
    pairs = ([(t, declared_unit) for t in scales] if (declared_unit := getattr(declared, kind, None))
             else sorted(((t, c) for c in scales for t in scales), key=lambda p: si not in p))
    best = None
    for true, claimed in pairs:
        x = value_si * scales[true] / scales[claimed]
        if true != claimed and ok(x):
            score = abs(math.log(x / typical))
            if best is None or score < best[0] - 1e-6:  # ties: the earlier pair
                best = (score, true, claimed)
    if best is None:
        return ""
    _, true, claimed = best
    if declared is not None:
        return f"{_NAMES[true]} declared as {_NAMES[claimed]}? (set units.{kind} to '{true}')"
    return f"{_NAMES[true]} converted as {_NAMES[claimed]}?"


def command_peaks(velocity: np.ndarray) -> tuple[float | None, float | None]:
    """The largest finite ``|v|`` and ``|omega|`` of commands ``(v, omega)`` (None where there is none):
    all that the command rules look at, so a long run can be judged block by block."""
    v = np.asarray(velocity)
    if v.ndim != 2 or v.shape[-1] != 2 or v.shape[0] == 0:
        return None, None
    peaks = []
    for col in range(2):
        values = np.abs(v[:, col].astype(np.float64))
        values = values[np.isfinite(values)]
        peaks.append(float(values.max()) if values.size else None)
    return peaks[0], peaks[1]


def command_problems(velocity: np.ndarray, rig: RobotRig | None, declared: RecordingUnits | None = None) -> list[Problem]:
    """Commands ``(v, omega)`` in SI beyond the rig's limits (+ tolerance), else beyond any robot's."""
    return peak_problems(command_peaks(velocity), rig, declared)


def peak_problems(peaks: tuple[float | None, float | None], rig: RobotRig | None,
                  declared: RecordingUnits | None = None) -> list[Problem]:
    """``command_problems`` of commands whose ``command_peaks`` are ``peaks``."""
    out = []
    rows = (("linear speed", "linear_velocity", "m/s", "v_max_m_s", MAX_SPEED_M_S),
            ("turn rate", "angular_velocity", "rad/s", "omega_max_rad_s", MAX_TURN_RAD_S))
    default = RobotRig()  # typical limits where the rig is unknown
    for peak, (name, kind, unit, field, absolute) in zip(peaks, rows):
        if peak is None:
            continue
        declared_limit = getattr(rig, field) if rig is not None else None
        limit = declared_limit * (1 + COMMAND_TOLERANCE) if declared_limit is not None else absolute
        if peak <= limit:
            continue
        what = (f"the rig's limit {declared_limit:g} {unit} (+{COMMAND_TOLERANCE:.0%})" if declared_limit is not None
                else f"{absolute:g} {unit}, beyond any ground robot")
        msg = f"{name} up to {peak:.3g} {unit} exceeds {what}"
        typical = declared_limit if declared_limit is not None else getattr(default, field)
        hint = unit_hint(kind, peak, lambda x, limit=limit: x <= limit, typical, declared)
        if hint:
            msg += f": {hint}"
        elif peak > 1e3 * limit:
            msg += ": no unit mistake explains it (corrupt values?)"
        elif declared_limit is not None:
            msg += f": check the units, or the rig's {field}"
        out.append(Problem("velocity", msg))
    return out


def time_problems(time: np.ndarray, frame_interval_s: float | None, range_max_m: float,
                  declared: RecordingUnits | None = None, declared_by: str = "store") -> list[Problem]:
    """Median frame spacing (SI seconds) against the declared frame interval, else against physics."""
    t = np.asarray(time, dtype=np.float64)
    if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)):
        return []
    med = float(np.median(np.diff(t)))
    if med <= 0:
        return []  # not increasing: a format error, reported by the format checks
    if frame_interval_s:
        def ok(x: float) -> bool:
            return abs(x / frame_interval_s - 1) <= FRAME_TOLERANCE

        if ok(med):
            return []
        msg = (f"frames are {med:.4g} s apart (median) but the {declared_by} declares "
               f"{frame_interval_s:g} s ({1 / frame_interval_s:g} Hz)")
        hint = unit_hint("time", med, ok, frame_interval_s, declared)
        return [Problem("time", msg + (f": {hint}" if hint else
                                       f": the times say {1 / med:.3g} Hz; fix the times or the declared rate"))]
    round_trip = 2 * range_max_m / C_SOUND

    def ok(x: float) -> bool:
        return round_trip <= x <= MAX_FRAME_INTERVAL_S

    if ok(med):
        return []
    if med > MAX_FRAME_INTERVAL_S:
        msg = f"frames are {med:.4g} s apart (median), not a sonar stream"
    else:
        msg = (f"frames are {med:.3g} s apart (median), less than an echo from {range_max_m:g} m takes "
               f"to return ({round_trip:.3g} s)")
    hint = unit_hint("time", med, ok, RobotRig().frame_interval_s, declared)
    return [Problem("time", msg + (f": {hint}" if hint else ""))]


def grid_problems(grid: SensorGrid, declared: RecordingUnits | None = None) -> list[Problem]:
    """A sensor grid no in-air sonar images: millimetre ranges, a degree-wide field of view."""
    out = []
    rmax = grid.range_max_m

    def range_ok(x: float) -> bool:
        return MIN_RANGE_MAX_M <= x <= MAX_RANGE_M

    if not range_ok(rmax):
        hint = unit_hint("range", rmax, range_ok, 5.0, declared)
        out.append(Problem("grid", f"range {grid.range_min_m:.3g}-{rmax:.3g} m is implausible for an in-air sonar "
                                   f"(its images end between {MIN_RANGE_MAX_M:g} and {MAX_RANGE_M:g} m)"
                                   + (f": {hint}" if hint else "")))
    span = grid.azimuth_max_rad - grid.azimuth_min_rad

    def span_ok(x: float) -> bool:
        return MIN_AZIMUTH_SPAN_RAD <= x <= 2 * math.pi + 1e-6

    if not span_ok(span):
        hint = unit_hint("azimuth", span, span_ok, math.pi, declared)
        out.append(Problem("grid", f"azimuth spans only {math.degrees(grid.azimuth_min_rad):.3g}.."
                                   f"{math.degrees(grid.azimuth_max_rad):.3g} deg; an imaging sonar sees tens of degrees"
                                   + (f": {hint}" if hint else "")))
    return out


def _leaves(doc: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(doc, dict) and doc:
        out: dict[str, Any] = {}
        for k, v in doc.items():
            out.update(_leaves(v, f"{prefix}{k}."))
        return out
    return {prefix.rstrip("."): doc}


def merge_metadata(embedded: dict, sidecar: dict) -> dict:
    """The sidecar's keys over the file's embedded ones, object by object."""
    out = dict(embedded)
    for k, v in sidecar.items():
        out[k] = merge_metadata(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def metadata_conflicts(sidecar: dict, embedded: dict, sidecar_name: str, file_name: str) -> list[Problem]:
    """Keys that the sidecar and the metadata embedded in the data file both set, differently."""
    side, emb = _leaves(sidecar), _leaves(embedded)
    return [Problem("metadata", f"{key} is {side[key]!r} in {sidecar_name} but {emb[key]!r} in the metadata "
                                f"embedded in {file_name} (the sidecar's would be used)")
            for key in sorted(side.keys() & emb.keys()) if side[key] != emb[key]]


#: Rows of commands judged at a time: memory stays bounded (1 MiB as float64) whatever a run's length.
STREAM_ROWS = 65_536


def store_problems(store, check_data: bool = True, runs: list[str] | None = None) -> list[Implausible]:
    """The grid and command rules, on ``runs`` (default: every complete run) of an open store,
    against its rig. ``validate`` passes the runs whose commands the format checks let through,
    so that a declared length is plausible before it is read; each run is read ``STREAM_ROWS``
    frames at a time.

    (Time stamps against the store's frame rate are a format check: ``sonarset.format.arrays``.)
    Never raises: what cannot be read is the format checks' to report.
    """
    loc = store.location
    out = [Implausible(loc, str(p)) for p in grid_problems(store.grid)]
    if not check_data:
        return out
    try:
        rig = store.rig
        names = store.runs() if runs is None else runs
    except RemoteError:  # the server failed, not the store: never a finding
        raise
    except Exception:
        return out
    for name in names:
        try:
            peaks = _streamed_peaks(store.group[name]["velocity"])
        except RemoteError:
            raise
        except Exception:
            continue
        out += [Implausible(p.where, p.message).at(f"{loc}/{name}") for p in peak_problems(peaks, rig)]
    return out


def _streamed_peaks(velocity) -> tuple[float | None, float | None]:
    """``command_peaks`` of a stored (zarr) velocity array, read in blocks of whole chunks."""
    chunk = max(1, int(velocity.metadata.chunk_grid.chunk_shape[0]))
    step = chunk * max(1, STREAM_ROWS // chunk)
    peaks: tuple[float | None, float | None] = (None, None)
    for start in range(0, velocity.shape[0], step):
        block = command_peaks(velocity[start:start + step])
        peaks = tuple(a if b is None else b if a is None else max(a, b) for a, b in zip(peaks, block))
    return peaks
