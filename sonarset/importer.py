"""Import external recordings (``.npz``, or a directory of ``.npy`` files) into a SonarSet store.

Everything is read and checked before anything is written; every problem found is reported,
one line each. A new store is built beside its destination and renamed into place, so an
import that fails or is killed never leaves a partial store behind.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from .errors import InputValidationError, SonarSetError
from .schema import Processing, RecordingMeta, SensorGrid, pydantic_problems
from .store import Run, _is_url, create_store, open_or_create_store, open_store

ARRAY_KEYS = ("images", "velocity", "time", "range", "azimuth", "pose", "snr_db", "slip")
REQUIRED_KEYS = ("images", "velocity", "time")
SIDECAR_NAME = "recording.json"

_RANGE = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
_ANGLE = {"rad": 1.0, "deg": math.pi / 180}
_LINV = {"m/s": 1.0, "cm/s": 1e-2, "mm/s": 1e-3}
_ANGV = {"rad/s": 1.0, "deg/s": math.pi / 180}
_TIME = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}

# Plausibility limits for a ground robot with an in-air sonar; values beyond them almost always
# mean a unit was declared wrongly (cm as m, degrees as radians).
MAX_RANGE_M = 100.0
MAX_SPEED_M_S = 10.0
MAX_TURN_RAD_S = 20.0


@dataclass
class Recording:
    """A validated recording in SonarSet conventions (SI units, velocity[k] moved k-1 -> k)."""

    source: str
    meta: RecordingMeta
    grid: SensorGrid
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.arrays["images"].shape[0])


def _read_arrays(src: Path) -> tuple[dict[str, Any], dict | None, list[str]]:
    """Raw arrays and embedded metadata of ``src``, plus problems reading them."""
    problems: list[str] = []
    arrays: dict[str, Any] = {}
    embedded: dict | None = None
    if src.is_dir():
        for path in sorted(src.glob("*.npy")):
            try:
                arrays[path.stem] = np.load(path, allow_pickle=False, mmap_mode="r")
            except Exception as exc:
                problems.append(f"{path.name}: not a readable .npy file ({_why(exc)})")
        if not arrays and not problems:
            problems.append("directory holds no .npy files")
        return arrays, embedded, problems
    if src.suffix != ".npz":
        return arrays, embedded, ["unsupported input (expected a .npz file or a directory of .npy files)"]
    try:
        with np.load(src, allow_pickle=False) as npz:
            for key in npz.files:
                try:
                    arrays[key] = npz[key]
                except Exception as exc:
                    problems.append(f"array {key!r}: unreadable ({_why(exc)})")
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        return {}, None, [f"not a readable .npz file ({_why(exc)})"]
    if "metadata" in arrays:
        raw = arrays.pop("metadata")
        try:
            embedded = json.loads(str(raw[()] if getattr(raw, "ndim", 1) == 0 else raw))
            if not isinstance(embedded, dict):
                raise ValueError("not a JSON object")
        except (ValueError, TypeError) as exc:
            problems.append(f"array 'metadata': must hold a JSON object string ({_why(exc)})")
            embedded = None
    return arrays, embedded, problems


def _why(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[:160]


def _sidecar_for(src: Path) -> Path:
    return src / SIDECAR_NAME if src.is_dir() else src.with_suffix(".json")


def load_recording(src: str | os.PathLike, meta_path: str | os.PathLike | None = None) -> Recording:
    """Read and validate a recording; raise InputValidationError listing every problem."""
    src = Path(src)
    where = str(src)
    if not src.exists():
        raise InputValidationError(where, ["no such file or directory"])
    arrays, embedded, problems = _read_arrays(src)
    if problems and not arrays:
        raise InputValidationError(where, problems)  # nothing readable: further checks only echo it

    meta_doc: dict | None = None
    sidecar = Path(meta_path) if meta_path is not None else _sidecar_for(src)
    if meta_path is not None and not sidecar.is_file():
        problems.append(f"{sidecar}: metadata file not found")
    elif sidecar.is_file():
        try:
            meta_doc = json.loads(sidecar.read_text())
            if not isinstance(meta_doc, dict):
                raise ValueError("top level must be a JSON object")
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            problems.append(f"{sidecar.name}: invalid JSON ({_why(exc)})")
            meta_doc = None
    if meta_doc is None:
        meta_doc = embedded or {}
    try:
        meta = RecordingMeta.model_validate(meta_doc)
    except ValidationError as exc:
        problems += pydantic_problems(exc, "metadata.")
        meta = None

    for key in arrays:
        if key not in ARRAY_KEYS:
            problems.append(f"unknown array {key!r} (expected {', '.join(ARRAY_KEYS)})")
    for key in REQUIRED_KEYS:
        if key not in arrays:
            problems.append(f"missing required array {key!r}")
    conv: dict[str, np.ndarray] = {}
    for key in ARRAY_KEYS:
        if key not in arrays:
            continue
        arr = arrays[key]
        if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
            problems.append(f"{key}: dtype {getattr(arr, 'dtype', type(arr).__name__)} is not a real number type")
            continue
        arr = np.asarray(arr)
        if arr.size and not np.all(np.isfinite(arr)):
            problems.append(f"{key}: contains NaN or infinite values")
            continue
        conv[key] = arr
    if meta is None:
        raise InputValidationError(where, problems)

    u = meta.units
    shapes_ok = _check_shapes(conv, problems)
    images = conv.get("images")
    T = images.shape[0] if images is not None and images.ndim == 3 else None

    # Units to SI.
    out: dict[str, np.ndarray] = {}
    if "velocity" in conv and conv["velocity"].ndim == 2 and conv["velocity"].shape[-1] == 2:
        v = conv["velocity"].astype(np.float64)
        v = v * np.array([_LINV[u.linear_velocity], _ANGV[u.angular_velocity]])
        if v.size:
            if np.abs(v[:, 0]).max() > MAX_SPEED_M_S:
                problems.append(f"velocity: linear speed up to {np.abs(v[:, 0]).max():.3g} m/s is implausible "
                                f"(declared units.linear_velocity={u.linear_velocity!r})")
            if np.abs(v[:, 1]).max() > MAX_TURN_RAD_S:
                problems.append(f"velocity: turn rate up to {np.abs(v[:, 1]).max():.3g} rad/s is implausible "
                                f"(declared units.angular_velocity={u.angular_velocity!r}; degrees?)")
        out["velocity"] = v
    if "time" in conv and conv["time"].ndim == 1:
        t = conv["time"].astype(np.float64) * _TIME[u.time]
        if t.size > 1:
            bad = np.flatnonzero(np.diff(t) <= 0)
            if bad.size:
                problems.append(f"time: not strictly increasing (first at frame {int(bad[0]) + 1})")
        out["time"] = t
    if "pose" in conv and conv["pose"].ndim == 2 and conv["pose"].shape[-1] == 3:
        out["pose"] = conv["pose"].astype(np.float64) * np.array([_RANGE[u.range], _RANGE[u.range], _ANGLE[u.azimuth]])
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

    grid = _resolve_grid(meta, conv, images, problems)
    if images is not None and images.ndim == 3:
        img = _encode_images(images, meta, problems)
        if img is not None:
            out["images"] = img

    if meta.velocity_alignment == "next" and T is not None and shapes_ok:
        # Their velocity[k] acts after frame k; ours moved the robot into frame k. Frame 0 has no
        # command that led to it, so it is dropped along with the command after the last frame.
        if T < 2:
            problems.append("velocity_alignment 'next' needs at least 2 frames")
        else:
            for key in list(out):
                if key == "velocity":
                    out[key] = out[key][:-1]
                elif key in ("images", "time", "pose", "snr_db", "slip"):
                    out[key] = out[key][1:]
    if problems or grid is None:
        raise InputValidationError(where, problems or ["no sensor grid"])
    return Recording(where, meta, grid, out)


def _check_shapes(conv: dict[str, np.ndarray], problems: list[str]) -> bool:
    before = len(problems)
    images = conv.get("images")
    if images is not None and images.ndim != 3:
        problems.append(f"images: expected 3-D (time, range, azimuth), got shape {images.shape}")
        images = None
    if images is not None and images.shape[0] < 1:
        problems.append("images: no frames")
    T = images.shape[0] if images is not None else None
    expect = {"velocity": 2, "time": None, "pose": 3, "snr_db": None, "slip": 2}
    for key, last in expect.items():
        if key not in conv:
            continue
        arr = conv[key]
        ndim = 1 if last is None else 2
        if arr.ndim != ndim or (last is not None and arr.shape[-1] != last):
            want = "(T,)" if last is None else f"(T, {last})"
            problems.append(f"{key}: expected shape {want}, got {arr.shape}")
        elif T is not None and arr.shape[0] != T:
            problems.append(f"{key}: {arr.shape[0]} frames but images has {T}")
    for key, axis in (("range", 1), ("azimuth", 2)):
        if key in conv:
            arr = conv[key]
            if arr.ndim != 1:
                problems.append(f"{key}: expected a 1-D array of bin centres, got shape {arr.shape}")
            elif images is not None and arr.shape[0] != images.shape[axis]:
                problems.append(f"{key}: {arr.shape[0]} values but images has {images.shape[axis]} {key} bins")
    return len(problems) == before


def _resolve_grid(meta: RecordingMeta, conv: dict[str, np.ndarray], images, problems: list[str]) -> SensorGrid | None:
    r_scale, a_scale = _RANGE[meta.units.range], _ANGLE[meta.units.azimuth]
    from_meta = from_arrays = None
    if meta.grid is not None:
        g = meta.grid
        try:
            from_meta = SensorGrid(
                range_min_m=g.range_min * r_scale, range_max_m=g.range_max * r_scale, n_range=g.n_range,
                azimuth_min_rad=g.azimuth_min * a_scale, azimuth_max_rad=g.azimuth_max * a_scale,
                n_azimuth=g.n_azimuth,
            )
        except ValidationError as exc:
            problems += [_unit_hint(line, meta) for line in pydantic_problems(exc, "metadata.grid.")]
    if "range" in conv and "azimuth" in conv and conv["range"].ndim == 1 and conv["azimuth"].ndim == 1:
        try:
            from_arrays = SensorGrid.from_centres(conv["range"] * r_scale, conv["azimuth"] * a_scale)
        except (ValidationError, ValueError) as exc:
            lines = pydantic_problems(exc, "range/azimuth: ") if isinstance(exc, ValidationError) else [str(exc)]
            problems += [_unit_hint(line, meta) for line in lines]
    elif ("range" in conv) != ("azimuth" in conv):
        problems.append("range and azimuth arrays must be given together")
    grid = from_meta or from_arrays
    if from_meta is not None and from_arrays is not None and not from_meta.matches(from_arrays, rtol=1e-4):
        problems.append(f"metadata grid {from_meta.describe()} disagrees with the range/azimuth arrays "
                        f"{from_arrays.describe()}")
    if grid is None and meta.grid is None and "range" not in conv:
        problems.append("no sensor grid: give metadata 'grid' or 'range' and 'azimuth' arrays")
    if grid is not None:
        if grid.range_max_m > MAX_RANGE_M:
            problems.append(f"grid: range up to {grid.range_max_m:g} m is implausible for in-air sonar "
                            f"(declared units.range={meta.units.range!r})")
        if images is not None and images.ndim == 3 and images.shape[1:] != grid.shape:
            problems.append(f"images: frame shape {images.shape[1:]} does not match the grid {grid.shape}")
    return grid


def _unit_hint(line: str, meta: RecordingMeta) -> str:
    if "azimuth" in line and meta.units.azimuth == "rad":
        return line + " (azimuth in degrees? set units.azimuth to 'deg')"
    return line


def _encode_images(images: np.ndarray, meta: RecordingMeta, problems: list[str]) -> np.ndarray | None:
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


def import_recording(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    meta_path: str | os.PathLike | None = None,
    name: str | None = None,
    split: str | None = None,
    overwrite: bool = False,
) -> Run:
    """Validate ``src`` completely, then write it as one run of the store ``out``.

    ``out`` is created when missing (atomically: built aside, then renamed) or must already be a
    store with the same grid. The run is named ``name``, else metadata ``name``, else the stem.
    The sidecar's ``processing`` and ``rig`` are recorded in a new store (processing default:
    profile 'unknown'); an existing store must match those the sidecar declares.
    """
    rec = load_recording(src, meta_path)
    run_name = name or rec.meta.name or Path(src).stem
    run_split = split or rec.meta.split
    source = {"kind": "import", "file": Path(src).name, "source": rec.meta.source,
              "image_encoding": rec.meta.image_encoding, "velocity_alignment": rec.meta.velocity_alignment}
    opt = {k: rec.arrays.get(k) for k in ("pose", "snr_db", "slip")}
    out_s = os.fspath(out)
    if _is_url(out_s) or (Path(out_s) / "zarr.json").exists():
        store = open_or_create_store(out_s, rec.grid, processing=rec.meta.processing, rig=rec.meta.rig)
        if run_name in store.runs() and not overwrite:
            raise SonarSetError(f"{out_s}: run {run_name!r} already exists (use --overwrite or --name)")
        return store.write_run(run_name, rec.arrays["images"], rec.arrays["velocity"], rec.arrays["time"],
                               split=run_split, source=source, overwrite=overwrite, **opt)
    dest = Path(out_s)
    if dest.exists() and (dest.is_file() or any(dest.iterdir())):
        raise SonarSetError(f"{out_s}: exists and is not a SonarSet store")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent))
    try:
        store = create_store(tmp / "store.zarr", rec.grid, rig=rec.meta.rig,
                             processing=rec.meta.processing or Processing(profile="unknown"))
        store.write_run(run_name, rec.arrays["images"], rec.arrays["velocity"], rec.arrays["time"],
                        split=run_split, source=source, **opt)
        if dest.exists():
            dest.rmdir()  # an empty directory, checked above
        os.replace(tmp / "store.zarr", dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return open_store(dest).run(run_name)
