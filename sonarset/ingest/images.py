"""Import external recordings (``.npz``, or a directory of ``.npy`` files) into a SonarSet store.

Everything is read and checked before anything is written; every problem found is reported,
one line each. Only regular files are opened (``files``), the sidecar is read strictly
(``metadata``), the arrays pass the format's checks (``format.arrays``) and the plausibility rules
(``format.plausibility``), and the run is written as ``target`` writes it: built aside and moved
in whole, so an import that fails or is killed never leaves a partial run, nor loses the run it
replaces.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from pydantic import ValidationError

from sonarset.format import plausibility as plaus
from sonarset.format.arrays import (
    ARRAYS, FRAME_ARRAYS, OPTIONAL_ARRAYS, REQUIRED_FRAME_ARRAYS, dtype_problems, frame_count_problems,
    layout_problems, nonfinite_problems, time_order_problems,
)
from sonarset.errors import InputValidationError
from sonarset.ingest.target import ImportTarget, check_run_options, nominal_frame_rate, run_name_for
from sonarset.ingest.files import read_arrays, regular_file_problem, short_reason
from sonarset.format.units import angle_scale, grid_to_si, pose_to_si, range_scale, time_to_si, velocity_to_si
from sonarset.store.run import Run
from sonarset.format.attrs import Processing, RobotRig, SensorGrid
from sonarset.format.problems import pydantic_problems
from sonarset.format.sidecars import RecordingMeta
from sonarset.ingest.metadata import parse_metadata, recording_meta

IMPLAUSIBLE_NOTE = " (allow_implausible imports it as is)"


@dataclass
class Recording:
    """A validated recording in SonarSet conventions (SI units, velocity[k] moved k-1 -> k)."""

    source: str
    meta: RecordingMeta
    grid: SensorGrid
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    #: Plausibility findings let through by ``allow_implausible``.
    warnings: list[str] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return int(self.arrays["images"].shape[0])


def load_recording(src: str | os.PathLike, meta_path: str | os.PathLike | None = None, *,
                   rig: RobotRig | None = None, frame_interval_s: float | None = None,
                   allow_implausible: bool = False) -> Recording:
    """Read and validate a recording; raise InputValidationError listing every problem.

    Besides the format, the values must be plausible (``sonarset.format.plausibility``) against ``rig``
    and ``frame_interval_s`` (the destination store's; default: the sidecar's rig). With
    ``allow_implausible`` those findings become the recording's ``warnings``; time stamps that
    disagree with a declared frame rate stay errors, since readers refuse such a run.
    """
    src = Path(src)
    where = str(src)
    arrays, embedded, problems = _read_input(src)
    implausible: list[str] = []
    meta = recording_meta(src, meta_path, embedded, problems, implausible)
    conv = _numeric_arrays(arrays, problems)

    def allow() -> str | None:
        """The parameter that would let the implausible lines through (the CLI names its flag)."""
        return "allow_implausible" if implausible and not allow_implausible else None

    if meta is None:
        raise InputValidationError(where, problems + [line + IMPLAUSIBLE_NOTE for line in implausible],
                                   parameter=allow())
    shapes_ok = _check_shapes(conv, problems)
    out = _to_si(conv, meta, rig, problems, implausible)
    images = conv.get("images")
    grid = _resolve_grid(meta, conv, images, problems)
    if grid is not None:
        implausible += map(str, plaus.grid_problems(grid, meta.units))
        if "time" in out:
            _check_times(out["time"], meta, grid, frame_interval_s, problems, implausible)
    if images is not None and images.ndim == 3:
        img = encode_images(images, meta, problems)
        if img is not None:
            out["images"] = img
        if meta.velocity_alignment == "next" and shapes_ok:
            _align_commands_after(out, images.shape[0], problems)
    if not allow_implausible:
        problems += [line + IMPLAUSIBLE_NOTE for line in implausible]
    if problems or grid is None:
        raise InputValidationError(where, problems or ["no sensor grid"], parameter=allow())
    return Recording(where, meta, grid, out, warnings=implausible)


def _read_input(src: Path) -> tuple[dict[str, Any], dict | None, list[str]]:
    """The arrays of ``src``, its embedded metadata and the problems reading them; raises when
    nothing could be read (every further check would only echo that)."""
    where = str(src)
    if not src.exists():
        raise InputValidationError(where, ["no such file or directory"])
    if not src.is_dir():
        irregular = regular_file_problem(src)
        if irregular:
            raise InputValidationError(where, [irregular])
    arrays, raw_meta, problems = read_arrays(src)
    embedded = None
    if raw_meta is not None:
        try:
            embedded = parse_metadata(str(raw_meta[()] if getattr(raw_meta, "ndim", 1) == 0 else raw_meta))
        except (ValueError, TypeError) as exc:
            problems.append(f"array 'metadata': must hold a JSON object string ({short_reason(exc)})")
    if problems and not arrays:
        raise InputValidationError(where, problems)
    return arrays, embedded, problems


def _numeric_arrays(arrays: dict[str, Any], problems: list[str]) -> dict[str, np.ndarray]:
    """The known arrays that hold finite real numbers; a line in ``problems`` for every other one."""
    problems += [f"unknown array {key!r} (expected {', '.join(ARRAYS)})" for key in arrays if key not in ARRAYS]
    problems += [f"missing required array {key!r}" for key in REQUIRED_FRAME_ARRAYS if key not in arrays]
    conv: dict[str, np.ndarray] = {}
    for key in ARRAYS:
        if key not in arrays:
            continue
        arr = arrays[key]
        found = dtype_problems(key, arr)
        if not found:
            arr = np.asarray(arr)
            found = nonfinite_problems(key, np.atleast_1d(arr))
        if found:
            problems += map(str, found)
            continue
        conv[key] = arr
    return conv


def _check_shapes(conv: dict[str, np.ndarray], problems: list[str]) -> bool:
    """The spec's layout of every array, frame counts against the images' and coordinates against
    their bins; True when all agree."""
    before = len(problems)
    images = conv.get("images")
    found = layout_problems("images", images.shape) if images is not None else []
    if found:
        problems += map(str, found)
        images = None
    if images is not None and images.shape[0] < 1:
        problems.append("images: no frames")
    T = images.shape[0] if images is not None else None
    for key in FRAME_ARRAYS:
        if key == "images" or key not in conv:
            continue
        found = layout_problems(key, conv[key].shape)
        if not found and T is not None:
            found = frame_count_problems(key, conv[key].shape[0], T)
        problems += map(str, found)
    for key, axis in (("range", 1), ("azimuth", 2)):
        if key in conv:
            arr = conv[key]
            found = layout_problems(key, arr.shape)
            if found:
                problems += map(str, found)
            elif images is not None and arr.shape[0] != images.shape[axis]:
                problems.append(f"{key}: {arr.shape[0]} values but images has {images.shape[axis]} {key} bins")
    return len(problems) == before


def _to_si(conv: dict[str, np.ndarray], meta: RecordingMeta, rig: RobotRig | None, problems: list[str],
           implausible: list[str]) -> dict[str, np.ndarray]:
    """The per-frame vectors in SI units and the store's dtypes, with the command and time checks."""
    u = meta.units
    out: dict[str, np.ndarray] = {}
    if "velocity" in conv and not layout_problems("velocity", conv["velocity"].shape):
        out["velocity"] = velocity_to_si(conv["velocity"].astype(np.float64), u)
        # beyond any ground robot no reader takes (rules.command_limit_problems): an error, whatever
        # the flags; beyond the rig's limits, a finding allow_implausible lets through
        beyond = list(map(str, plaus.command_problems(out["velocity"], None, u)))
        problems += beyond
        if (rig or meta.rig) and not beyond:  # said once, and without a flag that could not help
            implausible += map(str, plaus.command_problems(out["velocity"], rig or meta.rig, u))
    if "time" in conv and conv["time"].ndim == 1:
        out["time"] = time_to_si(conv["time"].astype(np.float64), u)
        problems += map(str, time_order_problems(out["time"]))
    if "pose" in conv and not layout_problems("pose", conv["pose"].shape):
        out["pose"] = pose_to_si(conv["pose"].astype(np.float64), u)
    for key in ("snr_db", "slip"):
        if key in conv:
            out[key] = conv[key].astype(np.float64)
    for key, arr in out.items():
        if arr.size and np.abs(arr).max() > np.finfo(np.float32).max:
            problems.append(f"{key}: values exceed the float32 range")
            out[key] = np.zeros_like(arr)
    for key in ("velocity", "snr_db", "slip"):
        if key in out:
            out[key] = out[key].astype(np.float32)
    return out


def _check_times(time: np.ndarray, meta: RecordingMeta, grid: SensorGrid, frame_interval_s: float | None,
                 problems: list[str], implausible: list[str]) -> None:
    """Time stamps against the declared frame interval (the store's, else the sidecar's rig)."""
    interval = frame_interval_s or (meta.rig.frame_interval_s if meta.rig is not None else None)
    by = "store" if frame_interval_s else "sidecar's rig"
    found = plaus.time_problems(time, interval, grid.range_max_m, meta.units, declared_by=by)
    # Against a declared rate it is a format error (readers refuse the run); without one, the new
    # store takes its rate from the times, and only physics can object.
    (problems if interval else implausible).extend(map(str, found))


def _align_commands_after(out: dict[str, np.ndarray], n_frames: int, problems: list[str]) -> None:
    """Shift commands given as acting after each frame (alignment 'next') to ours, which moved the
    robot into frame k: frame 0 has no command that led to it, so it is dropped along with the
    command after the last frame."""
    if n_frames < 2:
        problems.append("velocity_alignment 'next' needs at least 2 frames")
        return
    for key in list(out):
        out[key] = out[key][:-1] if key == "velocity" else out[key][1:]


def _resolve_grid(meta: RecordingMeta, conv: dict[str, np.ndarray], images, problems: list[str]) -> SensorGrid | None:
    """The grid the metadata declares and the coordinate arrays give, which must agree."""
    from_meta = from_arrays = None
    if meta.grid is not None:
        try:
            from_meta = grid_to_si(meta.grid, meta.units)
        except ValidationError as exc:
            problems += [_unit_hint(str(p), meta) for p in pydantic_problems(exc, "metadata.grid.")]
    if "range" in conv and "azimuth" in conv and conv["range"].ndim == 1 and conv["azimuth"].ndim == 1:
        try:
            from_arrays = SensorGrid.from_centres(conv["range"] * range_scale(meta.units),
                                                  conv["azimuth"] * angle_scale(meta.units))
        except (ValidationError, ValueError) as exc:
            found = pydantic_problems(exc, "range/azimuth: ") if isinstance(exc, ValidationError) else [exc]
            problems += [_unit_hint(str(p), meta) for p in found]
    elif ("range" in conv) != ("azimuth" in conv):
        problems.append("range and azimuth arrays must be given together")
    grid = from_meta or from_arrays
    if from_meta is not None and from_arrays is not None and not from_meta.matches(from_arrays, rtol=1e-4):
        problems.append(f"metadata grid {from_meta.describe()} disagrees with the range/azimuth arrays "
                        f"{from_arrays.describe()}")
    if grid is None and meta.grid is None and "range" not in conv:
        problems.append("no sensor grid: give metadata 'grid' or 'range' and 'azimuth' arrays")
    if grid is not None:
        if images is not None and images.ndim == 3 and images.shape[1:] != grid.shape:
            problems.append(f"images: frame shape {images.shape[1:]} does not match the grid {grid.shape}")
    return grid


def _unit_hint(line: str, meta: RecordingMeta) -> str:
    if "azimuth" in line and meta.units.azimuth == "rad":
        return line + " (azimuth in degrees? set units.azimuth to 'deg')"
    return line


def encode_images(images: np.ndarray, meta: RecordingMeta, problems: list[str]) -> np.ndarray | None:
    """Images in the sidecar's ``image_encoding`` as the store's [0, 1] energyscape, or None and a
    problem when their values do not fit that encoding (the bag importer checks its extremes here)."""
    dr = meta.dynamic_range_db
    if images.size == 0:
        return None
    lo, hi = float(images.min()), float(images.max())
    if meta.image_encoding == "energyscape":
        if lo < 0 or hi > 1:
            problems.append(f"images: energyscape values must lie in [0, 1], found {lo:g}..{hi:g} "
                            "(set image_encoding to 'db' or 'linear')")
            return None
        return images if images.dtype in (np.float16, np.float32) else images.astype(np.float32)
    if meta.image_encoding == "db":
        if hi > 1e-6:
            problems.append(f"images: decibel values must be <= 0 dB re full scale, found up to {hi:g} dB")
            return None
        db = images.astype(np.float64)
    else:
        if lo < 0:
            problems.append(f"images: linear energy must be non-negative, found {lo:g}")
            return None
        if hi <= 0:
            problems.append("images: linear energy is zero everywhere")
            return None
        with np.errstate(divide="ignore"):
            db = 10.0 * np.log10(images.astype(np.float64) / hi)
    return np.clip((db + dr) / dr, 0.0, 1.0).astype(np.float32)


def import_recording(src: str | os.PathLike, out: str | os.PathLike, *, meta_path: str | os.PathLike | None = None,
                     name: str | None = None, split: str | None = None, overwrite: bool = False,
                     allow_implausible: bool = False, warn: Callable[[str], None] | None = None) -> Run:
    """Validate ``src`` completely, then write it as one run of the store ``out``.

    ``out`` is created when missing (atomically: built aside, then renamed) or must already be a
    store with the same grid. The run is named ``name``, else metadata ``name``, else the stem.
    The sidecar's ``processing`` and ``rig`` are recorded in a new store (processing default:
    profile 'unknown'; frame rate: the rig's, else the recording's median time step); an existing
    store must match those the sidecar declares, and its rig and frame rate are what the values
    are checked against. ``allow_implausible`` imports values the plausibility rules question,
    passing each finding to ``warn``.

    A run for an existing local store is built in a store beside it and moved in: renamed, or
    swapped atomically for the run it replaces (``overwrite``). Until then the store is untouched;
    a failure, a full disk included, leaves it as it was.
    """
    check_run_options(name, split)
    target = ImportTarget.at(out)
    have = target.existing
    rec = load_recording(src, meta_path, rig=have.rig if have is not None else None,
                         frame_interval_s=1 / have.attrs.frame_rate_hz if have is not None else None,
                         allow_implausible=allow_implausible)
    for line in rec.warnings:
        if warn is not None:
            warn(f"{src}: {line}")
    run_name = run_name_for(src, name, rec.meta.name)
    run_split = split if split is not None else rec.meta.split
    source = {"kind": "import", "file": Path(src).name, "source": rec.meta.source,
              "image_encoding": rec.meta.image_encoding, "velocity_alignment": rec.meta.velocity_alignment}
    optional = {k: rec.arrays.get(k) for k in OPTIONAL_ARRAYS}

    def write(store, replace: bool) -> None:
        store.write_run(run_name, rec.arrays["images"], rec.arrays["velocity"], rec.arrays["time"],
                        split=run_split, source=source, overwrite=replace, consolidate=False, **optional)

    rig = rec.meta.rig
    return target.write(run_name, write, overwrite=overwrite, grid=rec.grid, processing=rec.meta.processing, rig=rig,
                        new_store={"frame_rate_hz": nominal_frame_rate(rec.arrays["time"], rig),
                                   "processing": rec.meta.processing or Processing(profile="unknown")})
