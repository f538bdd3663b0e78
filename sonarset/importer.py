"""Import external recordings (``.npz``, or a directory of ``.npy`` files) into a SonarSet store.

Everything is read and checked before anything is written; every problem found is reported,
one line each. Only regular files are opened (a FIFO or a device would block or never end). The
run is built aside and moved in whole: a new store is built beside its destination and renamed
into place; a run for an existing local store is built in a store beside it and renamed into
the store, or swapped in atomically for the run it replaces. An import that fails (a full disk)
or is killed therefore never leaves a partial run behind, and never loses the run it replaces.
"""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
import stat
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from pydantic import ValidationError

from . import plausibility as plaus
from .atomic import aside_dir, exchange, settle_zarr_writes
from .errors import InputValidationError, SonarSetError
from .schema import RUN_NAME_RE, SPLIT_RE, Processing, RecordingMeta, RobotRig, SensorGrid, pydantic_problems
from .store import Run, _is_url, create_store, open_or_create_store, open_store

ARRAY_KEYS = ("images", "velocity", "time", "range", "azimuth", "pose", "snr_db", "slip")
REQUIRED_KEYS = ("images", "velocity", "time")
SIDECAR_NAME = "recording.json"

_RANGE = plaus.UNIT_SCALES["range"]
_ANGLE = plaus.UNIT_SCALES["azimuth"]
_LINV = plaus.UNIT_SCALES["linear_velocity"]
_ANGV = plaus.UNIT_SCALES["angular_velocity"]
_TIME = plaus.UNIT_SCALES["time"]

# Kept here for the importers that share them (sonarset.rawimport); the rules are in plausibility.
MAX_RANGE_M = plaus.MAX_RANGE_M
MAX_SPEED_M_S = plaus.MAX_SPEED_M_S
MAX_TURN_RAD_S = plaus.MAX_TURN_RAD_S

#: A metadata file is a few kilobytes; anything this large is not one (and would be read whole).
MAX_METADATA_BYTES = 16 * 2**20
#: Metadata nests a few levels (units, grid, rig, source); deeper documents are refused before
#: they reach code that recurses (pydantic, the JSON encoder writing zarr.json, every reader).
MAX_METADATA_DEPTH = 32
IMPLAUSIBLE_NOTE = " (--allow-implausible to import it as is)"


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


def _read_arrays(src: Path) -> tuple[dict[str, Any], dict | None, list[str]]:
    """Raw arrays and embedded metadata of ``src``, plus problems reading them."""
    problems: list[str] = []
    arrays: dict[str, Any] = {}
    embedded: dict | None = None
    if src.is_dir():
        for path in sorted(src.glob("*.npy")):
            irregular = regular_file_problem(path)
            if irregular:
                problems.append(f"{path.name}: {irregular}")
                continue
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
            embedded = parse_metadata(str(raw[()] if getattr(raw, "ndim", 1) == 0 else raw))
        except (ValueError, TypeError) as exc:
            problems.append(f"array 'metadata': must hold a JSON object string ({_why(exc)})")
            embedded = None
    return arrays, embedded, problems


def _why(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[:160]


def regular_file_problem(path: Path) -> str | None:
    """Why ``path`` must not be opened (a FIFO would block, a device never end), else None."""
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if stat.S_ISREG(mode):
        return None
    kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "a character device" if stat.S_ISCHR(mode)
            else "a block device" if stat.S_ISBLK(mode) else "not a plain file")
    return f"not a regular file ({kind}); only regular files are imported"


def parse_metadata(text: str) -> dict:
    """A metadata JSON object: strict JSON (no NaN, no Infinity), at most MAX_METADATA_DEPTH deep."""
    def constant(name: str):
        raise ValueError(f"{name} is not valid JSON")

    def number(token: str) -> float:
        value = float(token)
        if not math.isfinite(value):
            raise ValueError(f"number {token[:20]} is out of range")
        return value

    try:
        doc = json.loads(text, parse_constant=constant, parse_float=number)
    except RecursionError:
        raise ValueError(f"nested too deeply (at most {MAX_METADATA_DEPTH} levels)") from None
    if not isinstance(doc, dict):
        raise ValueError("top level must be a JSON object")
    stack = [(doc, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_METADATA_DEPTH:
            raise ValueError(f"nested too deeply (at most {MAX_METADATA_DEPTH} levels)")
        children = node.values() if isinstance(node, dict) else node
        stack += [(c, depth + 1) for c in children if isinstance(c, (dict, list))]
    return doc


def _sidecar_for(src: Path) -> Path:
    return src / SIDECAR_NAME if src.is_dir() else src.with_suffix(".json")


def load_recording(src: str | os.PathLike, meta_path: str | os.PathLike | None = None, *,
                   rig: RobotRig | None = None, frame_interval_s: float | None = None,
                   allow_implausible: bool = False) -> Recording:
    """Read and validate a recording; raise InputValidationError listing every problem.

    Besides the format, the values must be plausible (``sonarset.plausibility``) against ``rig``
    and ``frame_interval_s`` (the destination store's; default: the sidecar's rig). With
    ``allow_implausible`` those findings become the recording's ``warnings``; time stamps that
    disagree with a declared frame rate stay errors, since readers refuse such a run.
    """
    src = Path(src)
    where = str(src)
    if not src.exists():
        raise InputValidationError(where, ["no such file or directory"])
    if not src.is_dir():
        irregular = regular_file_problem(src)
        if irregular:
            raise InputValidationError(where, [irregular])
    arrays, embedded, problems = _read_arrays(src)
    if problems and not arrays:
        raise InputValidationError(where, problems)  # nothing readable: further checks only echo it
    implausible: list[str] = []

    meta_doc: dict | None = None
    sidecar = Path(meta_path) if meta_path is not None else _sidecar_for(src)
    if sidecar.exists() or sidecar.is_symlink():
        meta_doc = _read_sidecar(sidecar, problems)
    elif meta_path is not None:
        problems.append(f"{sidecar}: metadata file not found")
    if meta_doc is not None and embedded:
        # The sidecar completes and overrides the file's own metadata; a key both set differently
        # is reported, naming both, rather than silently decided.
        implausible += plaus.metadata_conflicts(meta_doc, embedded, sidecar.name, src.name)
        meta_doc = plaus.merge_metadata(embedded, meta_doc)
    if meta_doc is None:
        meta_doc = embedded or {}
    try:
        meta = RecordingMeta.model_validate(meta_doc)
    except ValidationError as exc:
        problems += pydantic_problems(exc, "metadata.")
        meta = None
    except RecursionError:
        problems.append(f"metadata: nested too deeply (at most {MAX_METADATA_DEPTH} levels)")
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
        raise InputValidationError(where, problems + [line + IMPLAUSIBLE_NOTE for line in implausible])

    u = meta.units
    shapes_ok = _check_shapes(conv, problems)
    images = conv.get("images")
    T = images.shape[0] if images is not None and images.ndim == 3 else None

    # Units to SI.
    out: dict[str, np.ndarray] = {}
    if "velocity" in conv and conv["velocity"].ndim == 2 and conv["velocity"].shape[-1] == 2:
        v = conv["velocity"].astype(np.float64)
        v = v * np.array([_LINV[u.linear_velocity], _ANGV[u.angular_velocity]])
        implausible += plaus.command_problems(v, rig or meta.rig, u)
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
    if grid is not None:
        implausible += plaus.grid_problems(grid, u)
        if "time" in out:
            interval = frame_interval_s or (meta.rig.frame_interval_s if meta.rig is not None else None)
            by = "store" if frame_interval_s else "sidecar's rig"
            found = plaus.time_problems(out["time"], interval, grid.range_max_m, u, declared_by=by)
            # Against a declared rate it is a format error (readers refuse the run); without one,
            # the new store takes its rate from the times, and only physics can object.
            (problems if interval else implausible).extend(found)
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
    if not allow_implausible:
        problems += [line + IMPLAUSIBLE_NOTE for line in implausible]
    if problems or grid is None:
        raise InputValidationError(where, problems or ["no sensor grid"])
    return Recording(where, meta, grid, out, warnings=implausible)


def _read_sidecar(path: Path, problems: list[str]) -> dict | None:
    irregular = regular_file_problem(path)
    if irregular:
        problems.append(f"{path.name}: {irregular}")
        return None
    try:
        if path.stat().st_size > MAX_METADATA_BYTES:
            raise ValueError(f"{path.stat().st_size} bytes, more than a metadata file holds "
                             f"({MAX_METADATA_BYTES // 2**20} MiB)")
        return parse_metadata(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        problems.append(f"{path.name}: invalid JSON ({_why(exc)})")
        return None


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


def check_run_options(name: str | None, split: str | None) -> None:
    """One-line errors for a bad ``--name`` or ``--split``, before any file is read."""
    if name is not None and not RUN_NAME_RE.match(name):
        raise SonarSetError(f"--name {name!r}: a run name is 1-128 letters, digits, '_', '.' or '-', "
                            "starting with a letter or digit")
    if split is not None and not SPLIT_RE.match(split):
        raise SonarSetError(f"--split {split!r}: a split is 1-32 lower-case letters, digits, '_' or '-', "
                            "starting with a letter (e.g. 'train', 'val', 'test')")


def import_recording(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    meta_path: str | os.PathLike | None = None,
    name: str | None = None,
    split: str | None = None,
    overwrite: bool = False,
    allow_implausible: bool = False,
    warn: Callable[[str], None] | None = None,
) -> Run:
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
    out_s = os.fspath(out).removeprefix("file://")  # a local path: renamed into, not written through fsspec
    existing = None
    if _is_url(out_s) or (Path(out_s) / "zarr.json").exists():
        existing = open_store(out_s, "r")
    rec = load_recording(src, meta_path, rig=existing.rig if existing is not None else None,
                         frame_interval_s=1 / existing.attrs.frame_rate_hz if existing is not None else None,
                         allow_implausible=allow_implausible)
    for line in rec.warnings:
        if warn is not None:
            warn(f"{src}: {line}")
    run_name = name or rec.meta.name or Path(src).stem
    if not RUN_NAME_RE.match(run_name):
        raise SonarSetError(f"{src}: {run_name!r} is not a valid run name; pass --name")
    run_split = split if split is not None else rec.meta.split
    source = {"kind": "import", "file": Path(src).name, "source": rec.meta.source,
              "image_encoding": rec.meta.image_encoding, "velocity_alignment": rec.meta.velocity_alignment}
    opt = {k: rec.arrays.get(k) for k in ("pose", "snr_db", "slip")}

    def write(store) -> None:
        store.write_run(run_name, rec.arrays["images"], rec.arrays["velocity"], rec.arrays["time"],
                        split=run_split, source=source, consolidate=False, **opt)

    if existing is not None:
        store = open_or_create_store(out_s, rec.grid, processing=rec.meta.processing, rig=rec.meta.rig)
        if run_name in store.runs() and not overwrite:
            raise SonarSetError(f"{out_s}: run {run_name!r} already exists (use --overwrite or --name)")
        if _is_url(out_s):  # object stores have no rename: the run writer keeps it invisible until complete
            replaced = overwrite and run_name in store.group.group_keys()
            with _no_space(out_s, run_name, "the run it replaced is gone" if replaced else "nothing was changed"):
                store.write_run(run_name, rec.arrays["images"], rec.arrays["velocity"], rec.arrays["time"],
                                split=run_split, source=source, overwrite=overwrite, **opt)
            return store.run(run_name)
        _move_run_in(store, run_name, write)
        return open_store(out_s).run(run_name)

    rig = rec.meta.rig
    dest = write_new_store(out_s, run_name, write, grid=rec.grid, rig=rig, frame_rate_hz=_frame_rate(rec, rig),
                           processing=rec.meta.processing or Processing(profile="unknown"))
    return open_store(dest).run(run_name)


def write_new_store(out_s: str, run_name: str, write: Callable, **create) -> Path:
    """A new store at ``out_s`` holding the run ``write(store)`` writes, made by ``create_store(**create)``
    beside it and renamed into place: a failed or killed import leaves nothing that looks like a store."""
    dest = Path(out_s)
    dest = dest.resolve() if dest.is_symlink() else dest  # the store goes where the link points
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise SonarSetError(f"{out_s}: exists and is not a SonarSet store")
    tmp = aside_dir(dest)
    try:
        with _no_space(out_s, run_name):
            store = create_store(tmp / "store.zarr", **create)
            write(store)
            store.consolidate()
        if dest.exists():
            dest.rmdir()  # an empty directory, checked above
        os.replace(tmp / "store.zarr", dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


def _frame_rate(rec: Recording, rig: RobotRig | None) -> float:
    if rig is not None:
        return 1.0 / rig.frame_interval_s
    t = rec.arrays["time"]
    if t.size > 1:
        dt = float(np.median(np.diff(t)))
        if dt > 0:
            return float(f"{1.0 / dt:.3g}")  # nominal: jitter must not give 4.9975 Hz
    return 1.0 / RobotRig().frame_interval_s


def _move_run_in(store, run_name: str, write: Callable) -> None:
    """Build the run in a store beside ``store``, then rename it in, or swap it for the run it replaces."""
    root = Path(store.location)
    tmp = aside_dir(root)
    try:
        with _no_space(store.location, run_name):
            side = create_store(tmp / "store.zarr", store.grid, processing=store.processing, rig=store.attrs.rig,
                                frame_rate_hz=store.attrs.frame_rate_hz)
            write(side)
        new, target = tmp / "store.zarr" / run_name, root / run_name
        # Anything at the run's path (the run replaced, or what a killed writer left) is swapped
        # out whole and deleted with the aside directory.
        swapped = target.exists() or target.is_symlink()
        if swapped:
            exchange(new, target)
        else:
            os.rename(new, target)
        try:
            with _no_space(store.location, run_name):
                store.consolidate()
        except BaseException:
            # Without its consolidated metadata the store would list another run than it holds:
            # put back what was there.
            if swapped:
                exchange(new, target)
            else:
                os.rename(target, new)
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


class _no_space:
    """Turn a write failure (a full disk, a read-only file system) into one line naming the store."""

    def __init__(self, where: str, run_name: str, outcome: str = "nothing was changed"):
        self.where, self.run_name, self.outcome = where, run_name, outcome

    def __enter__(self) -> None:
        return None

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            settle_zarr_writes()
        if exc_type is not None and issubclass(exc_type, OSError) and not isinstance(exc, SonarSetError):
            # The run writer's clean-up can fail on the same disk (or race the writes still in
            # flight) and raise its own error; the first failure is the one to report.
            while isinstance(exc.__context__, OSError):
                exc = exc.__context__
            why = exc.strerror or str(exc) or type(exc).__name__
            if exc.errno == errno.ENOSPC:
                why = "no space left on device"
            raise SonarSetError(f"{self.where}: cannot write run {self.run_name!r}: {why} ({self.outcome})") from None
        return False
