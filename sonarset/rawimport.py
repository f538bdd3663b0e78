"""Import raw microphone recordings: beamform them into energyscapes, one run of a SonarSet store.

A recording is per-measurement microphone signals (T, channels, samples) in a ``.npz`` or a
directory of ``.npy`` files, with a JSON sidecar (``schema.RawRecordingMeta``: sample rate, sweep,
microphone layout, speed of sound). Each measurement goes through the simulator's processing stage
(``sim.beamform``: matched filter, DAS or DMAS3-CF, envelope; then ``energyscape.postprocess`` or
the raw log mapping with the simulator's full scale), so an imported run holds the images the
simulator would make of the same echoes.

As ``sonarset import``: everything is read and checked before anything is written (including one
streamed pass over the signals for non-finite values and dead channels), every problem is one
line naming the file, and the run is written atomically with the image importer's helpers (built
in a store beside OUT, then renamed into place or swapped for the run it replaces; an object store
gets it through its run writer, invisible until committed). Signals are streamed in blocks of measurements, so memory does not grow with the
recording's length: a ``.npy`` is memory-mapped, a ``.npz`` member is read sequentially from the
archive.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from pydantic import ValidationError

from .errors import InputValidationError, SonarSetError
from . import plausibility
from .importer import (
    _ANGLE, _ANGV, _LINV, _RANGE, _TIME, _frame_rate, _move_run_in, _sidecar_for, _why, check_run_options,
    write_new_store,
)
from .schema import RUN_NAME_RE, Processing, RawRecordingMeta, SensorGrid, pydantic_problems
from .store import DEFAULT_CHUNK_FRAMES, Run, _is_url, open_or_create_store, open_store

ARRAY_KEYS = ("signals", "velocity", "time", "pose", "sweep")
REQUIRED_KEYS = ("signals", "velocity", "time")
BLOCK = 8  # measurements read and beamformed at a time (8 x 32 x 7000 float32: 7 MB); divides a chunk
MAX_LAYOUT_M = 1.0  # microphones farther from the emitter than this: probably not metres


# ---- reading: small arrays whole, the signals in blocks ----------------------------------------

@dataclass
class _Member:
    """One array of the input: its header, and how to read it."""

    shape: tuple
    dtype: np.dtype
    fortran: bool
    path: Path  # the .npy, or the .npz holding it
    member: str | None = None  # name inside the .npz


def _npy_header(f) -> tuple[tuple, bool, np.dtype]:
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(f)
    if version == (2, 0):
        return np.lib.format.read_array_header_2_0(f)
    raise ValueError(f"unsupported .npy format version {version}")


class RawSource:
    """The arrays of a ``.npz`` or of a directory of ``.npy`` files, read lazily."""

    def __init__(self, src: Path):
        self.src = src
        self.members: dict[str, _Member] = {}
        self.problems: list[str] = []
        if src.is_dir():
            for path in sorted(src.glob("*.npy")):
                try:
                    with open(path, "rb") as f:
                        shape, fortran, dtype = _npy_header(f)
                        offset = f.tell()
                    need = offset + int(np.prod(shape)) * dtype.itemsize
                    if path.stat().st_size < need:
                        raise ValueError(f"truncated: {path.stat().st_size} bytes, the header needs {need}")
                    self.members[path.stem] = _Member(tuple(shape), dtype, fortran, path)
                except Exception as exc:
                    self.problems.append(f"{path.name}: not a readable .npy file ({_why(exc)})")
            if not self.members and not self.problems:
                self.problems.append("directory holds no .npy files")
        elif src.suffix != ".npz":
            self.problems.append("unsupported input (expected a .npz file or a directory of .npy files)")
        else:
            try:
                with zipfile.ZipFile(src) as zf:
                    for info in zf.infolist():
                        if not info.filename.endswith(".npy"):
                            continue
                        key = info.filename[:-4]
                        try:
                            with zf.open(info) as f:
                                shape, fortran, dtype = _npy_header(f)
                            self.members[key] = _Member(tuple(shape), dtype, fortran, src, info.filename)
                        except Exception as exc:
                            self.problems.append(f"array {key!r}: unreadable ({_why(exc)})")
            except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
                self.problems.append(f"not a readable .npz file ({_why(exc)})")

    def read(self, key: str) -> np.ndarray:
        """A whole (small) array."""
        m = self.members[key]
        if m.member is None:
            return np.load(m.path, allow_pickle=False)
        with zipfile.ZipFile(m.path) as zf, zf.open(m.member) as f:
            return np.lib.format.read_array(f, allow_pickle=False)

    def blocks(self, key: str, block: int, start: int = 0) -> Iterator[tuple[int, np.ndarray]]:
        """(first index, rows) of ``key`` from ``start``, ``block`` rows at a time, never more in memory."""
        m = self.members[key]
        T = m.shape[0]
        row = int(np.prod(m.shape[1:])) * m.dtype.itemsize
        if m.member is None:
            arr = np.load(m.path, mmap_mode="r", allow_pickle=False)
            for i in range(start, T, block):
                yield i, np.array(arr[i:i + block])
            return
        with zipfile.ZipFile(m.path) as zf, zf.open(m.member) as f:
            _npy_header(f)
            left = start * row
            while left > 0:  # a sequential archive member: skip by reading
                left -= len(f.read(min(left, 1 << 24)))
            for i in range(start, T, block):
                n = min(block, T - i)
                buf = f.read(n * row)
                if len(buf) != n * row:
                    raise EOFError(f"{key}: the archive ends inside measurement {i + len(buf) // max(row, 1)}")
                yield i, np.frombuffer(buf, m.dtype).reshape(n, *m.shape[1:])


# ---- validation ---------------------------------------------------------------------------------

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


def chirp(f0: float, f1: float, duration: float, fs: float, window: str = "hann") -> np.ndarray:
    """A linear FM sweep sampled at fs, as ``sim.sonar.sweep`` makes the eRTIS one."""
    from scipy import signal

    t = np.arange(int(round(duration * fs))) / fs
    s = signal.chirp(t, f0, duration, f1)
    return s * signal.windows.hann(len(t)) if window == "hann" else s


def _layout(meta: RawRecordingMeta, sidecar: Path, problems: list[str]) -> np.ndarray | None:
    from .sim.beamform import read_layout_csv

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
            problems.append(f"{path.name}: not a microphone layout CSV ({_why(exc)})")
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
        g, rs, az = meta.grid, _RANGE[meta.units.range], _ANGLE[meta.units.azimuth]
        try:
            declared = SensorGrid(range_min_m=g.range_min * rs, range_max_m=g.range_max * rs, n_range=g.n_range,
                                  azimuth_min_rad=g.azimuth_min * az, azimuth_max_rad=g.azimuth_max * az,
                                  n_azimuth=g.n_azimuth)
        except ValidationError as exc:
            problems.extend(pydantic_problems(exc, "metadata.grid."))
            return None
    if grid is not None and declared is not None and not grid.matches(declared, rtol=1e-4):
        problems.append(f"metadata.grid {declared.describe()} differs from the store's {grid.describe()}")
        return None
    return grid or declared or SensorGrid.default()


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
    sidecar = Path(meta_path) if meta_path is not None else _sidecar_for(src)
    meta = None
    if not sidecar.is_file():
        problems.append(f"{sidecar.name}: metadata file not found (the sidecar with sample rate, sweep, microphones)")
    else:
        try:
            doc = json.loads(sidecar.read_text())
            if not isinstance(doc, dict):
                raise ValueError("top level must be a JSON object")
            meta = RawRecordingMeta.model_validate(doc)
        except ValidationError as exc:
            problems += pydantic_problems(exc, f"{sidecar.name}: ")
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            problems.append(f"{sidecar.name}: invalid JSON ({_why(exc)})")

    for key in reader.members:
        if key not in ARRAY_KEYS:
            problems.append(f"unknown array {key!r} (expected {', '.join(ARRAY_KEYS)})")
    for key in REQUIRED_KEYS:
        if key not in reader.members:
            problems.append(f"missing required array {key!r}")
    sig = reader.members.get("signals")
    T = M = n = None
    if sig is not None:
        if len(sig.shape) != 3:
            problems.append(f"signals: expected 3-D (measurement, channel, sample), got shape {sig.shape}")
        elif sig.dtype.kind not in "fiu":
            problems.append(f"signals: dtype {sig.dtype} is not a real number type")
        elif 0 in sig.shape:
            problems.append(f"signals: empty, shape {sig.shape}")
        elif sig.fortran and sig.member is not None:
            problems.append("signals: stored in Fortran order, which a .npz cannot stream; save it C-ordered "
                            "(np.ascontiguousarray) or as a .npy")
        else:
            T, M, n = sig.shape

    small: dict[str, np.ndarray] = {}
    for key, width in (("velocity", 2), ("time", None), ("pose", 3)):
        m = reader.members.get(key)
        if m is None:
            continue
        want = (T,) if width is None else (T, width)
        if m.dtype.kind not in "fiu":
            problems.append(f"{key}: dtype {m.dtype} is not a real number type")
            continue
        if len(m.shape) != len(want) or (width is not None and m.shape[-1] != width):
            problems.append(f"{key}: expected shape {'(T,)' if width is None else f'(T, {width})'}, got {m.shape}")
            continue
        if T is not None and m.shape[0] != T:
            problems.append(f"{key}: {m.shape[0]} rows but signals has {T} measurements")
            continue
        try:
            arr = reader.read(key).astype(np.float64)
        except Exception as exc:
            problems.append(f"{key}: unreadable ({_why(exc)})")
            continue
        if not np.all(np.isfinite(arr)):
            problems.append(f"{key}: contains NaN or infinite values")
            continue
        small[key] = arr
    if meta is None:
        raise InputValidationError(where, problems)

    u = meta.units
    if "velocity" in small:
        v = small["velocity"] * np.array([_LINV[u.linear_velocity], _ANGV[u.angular_velocity]])
        problems += plausibility.command_problems(v, meta.rig, u)  # the image importer's rules
        small["velocity"] = v
    if "time" in small:
        t = small["time"] * _TIME[u.time]
        bad = np.flatnonzero(np.diff(t) <= 0)
        if bad.size:
            problems.append(f"time: not strictly increasing (first at measurement {int(bad[0]) + 1})")
        small["time"] = t
    if "pose" in small:
        small["pose"] = small["pose"] * np.array([_RANGE[u.range], _RANGE[u.range], _ANGLE[u.azimuth]])

    from .sim.beamform import MARGIN_S

    positions = _layout(meta, sidecar, problems)
    if positions is not None and M is not None and M != len(positions):
        problems.append(f"signals: {M} channels but the microphone layout has {len(positions)} microphones")
    sweep = _sweep(meta, reader, problems)
    out_grid = _resolve_grid(meta, grid, problems)
    if out_grid is not None and meta.grid is not None:
        problems += plausibility.grid_problems(out_grid, u)
    if out_grid is not None and "time" in small:
        problems += plausibility.time_problems(small["time"], meta.rig.frame_interval_s if meta.rig else None,
                                               out_grid.range_max_m, u, "sidecar's rig")
    fs, c = meta.sample_rate_hz, meta.speed_of_sound_m_s
    if out_grid is not None and n is not None and sweep is not None:
        reach = (n - len(sweep)) / fs + meta.start_time_s  # the last echo whose sweep ends in the record
        need = 2 * out_grid.range_max_m / c
        if reach < need:
            problems.append(f"signals: {n} samples at {fs:g} Hz hold complete echoes out to "
                            f"{max(reach, 0) * c / 2:.2f} m; the grid reaches {out_grid.range_max_m:g} m")
        if 2 * out_grid.range_min_m / c - MARGIN_S < meta.start_time_s:
            problems.append(f"metadata.start_time_s: {meta.start_time_s:g} s is after the echoes of the grid's "
                            f"first range ({out_grid.range_min_m:g} m)")
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
        return [f"signals: unreadable ({_why(exc)}); is the file truncated?"]
    if not loud.all():
        dead = np.flatnonzero(~loud)
        return [f"signals: channel(s) {', '.join(map(str, dead[:8]))} are zero in every measurement "
                "(a dead microphone or a wrong channel map)"]
    return []


# ---- processing and writing ----------------------------------------------------------------------

def resolve_processing(profile: str = "ertis", beamformer: str | None = None) -> Processing:
    """The simulator's profile ``profile`` with its beamformer, or another (profile then 'custom')."""
    try:
        proc = Processing.named(profile)
    except ValueError as exc:
        raise SonarSetError(f"--processing: {exc}") from None
    if beamformer is None or beamformer == proc.beamformer:
        return proc
    from .sim.energyscape import BEAMFORMERS

    if beamformer not in BEAMFORMERS:
        raise SonarSetError(f"--beamformer must be one of {', '.join(BEAMFORMERS)}, got {beamformer!r}")
    return proc.model_copy(update={"beamformer": beamformer, "profile": "custom"})


class RawProcessor:
    """Measurements (B, M, n) -> energyscapes (B, R, A) float16, as the simulator makes them."""

    def __init__(self, rec: RawRecording, grid: SensorGrid, processing: Processing, workers: int = 2):
        from .sim.beamform import SignalBeamformer
        from .sim.sonar import SonarModel

        meta = rec.meta
        self.bf = SignalBeamformer(grid, rec.positions, rec.sweep, meta.sample_rate_hz, rec.n_samples,
                                   processing.beamformer, meta.speed_of_sound_m_s, meta.start_time_s)
        self.model = SonarModel(grid, processing=processing)  # the simulator's full scale and mapping
        self.raw = processing.beamformer == "das" and not processing.post_processed
        self.scale = np.float32(1 / meta.amplitude_scale)
        self.workers = max(1, int(workers))
        self.pool = cf.ThreadPoolExecutor(self.workers) if self.workers > 1 else None

    def amplitudes(self, block: np.ndarray) -> np.ndarray:
        one = lambda k: self.bf.amplitude(block[k])  # noqa: E731 - the compiled parts release the GIL
        rows = list(self.pool.map(one, range(len(block)))) if self.pool else [one(k) for k in range(len(block))]
        return np.stack(rows) * self.scale

    def images(self, block: np.ndarray) -> np.ndarray:
        amp = self.amplitudes(block)
        out = np.empty(amp.shape, np.float16)
        if self.raw:
            return self.model.encode(amp * amp, out=out)
        return self.model.pixels(amp, out)

    def close(self) -> None:
        if self.pool:
            self.pool.shutdown()


def import_raw(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    meta_path: str | os.PathLike | None = None,
    name: str | None = None,
    split: str | None = None,
    processing: str | Processing = "ertis",
    beamformer: str | None = None,
    grid: SensorGrid | None = None,
    overwrite: bool = False,
    workers: int = 2,
    block: int = BLOCK,
    progress: Callable[[int, int], None] | None = None,
) -> Run:
    """Validate the raw recording ``src`` completely, beamform it and write it as one run of ``out``.

    ``processing``: a profile ('ertis', the default, or 'raw') or settings; ``beamformer`` overrides
    the profile's. A new store gets the sidecar's grid (default: the 200 x 90 grid; ``grid``
    overrides) and records the processing and the sidecar's rig; an existing store must have the
    same grid, processing and rig. ``workers`` threads beamform a block's measurements.

    Written as ``sonarset import`` writes: a new store is built beside ``out`` and renamed into
    place; a run for an existing local store is built in a store beside it and renamed in (swapped
    for the run it replaces, with ``overwrite``). A failed or killed import leaves ``out`` as it was.
    """
    check_run_options(name, split)
    proc = processing if isinstance(processing, Processing) else resolve_processing(processing, beamformer)
    out_s = os.fspath(out).removeprefix("file://")
    existing = open_store(out_s) if _is_url(out_s) or (Path(out_s) / "zarr.json").exists() else None
    rec, out_grid = load_raw(src, meta_path, grid=existing.grid if existing is not None else grid)
    meta = rec.meta
    run_name = name or meta.name or Path(src).stem
    if not RUN_NAME_RE.match(run_name):
        raise SonarSetError(f"{src}: {run_name!r} is not a valid run name; pass --name")
    run_split = split or meta.split
    source = {"kind": "import-raw", "file": Path(src).name, "sample_rate_hz": meta.sample_rate_hz,
              "speed_of_sound_m_s": meta.speed_of_sound_m_s, "microphones": int(len(rec.positions)),
              "beamformer": proc.beamformer, "processing": proc.profile,
              "velocity_alignment": meta.velocity_alignment, "source": meta.source}
    optional = ("pose",) if "pose" in rec.arrays else ()

    def write(store, replace: bool = False) -> None:
        _write(store, rec, out_grid, proc, run_name, run_split, source, optional, replace, workers, block, progress)

    if existing is not None:
        store = open_or_create_store(out_s, out_grid, processing=proc, rig=meta.rig)
        if run_name in store.runs() and not overwrite:
            raise SonarSetError(f"{out_s}: run {run_name!r} already exists (use --overwrite or --name)")
        if _is_url(out_s):  # no rename in object stores: the run writer keeps it invisible until complete
            write(store, overwrite)
        else:
            # The import's own helper: built in a store beside, then renamed in (or swapped for the
            # run it replaces), so a failed or killed import leaves the store as it was.
            _move_run_in(store, run_name, write)
        return open_store(out_s).run(run_name)
    dest = write_new_store(out_s, run_name, write, grid=out_grid, processing=proc, rig=meta.rig,
                           frame_rate_hz=_frame_rate(rec, meta.rig),
                           description=f"imported from raw microphone signals ({Path(src).name})")
    return open_store(dest).run(run_name)


def _write(store, rec: RawRecording, grid: SensorGrid, proc: Processing, name: str, split: str, source: dict,
           optional: tuple, overwrite: bool, workers: int, block: int, progress) -> None:
    T = rec.n_frames
    proc_ = RawProcessor(rec, grid, proc, workers)
    # Images are collected into whole store chunks before writing: a block smaller than a chunk
    # would make every write recompress the chunk.
    chunk = DEFAULT_CHUNK_FRAMES
    images = np.empty((min(chunk, T), *grid.shape), np.float16)
    try:
        with store.run_writer(name, T, split=split, source=source, optional=optional, overwrite=overwrite) as w:
            start = filled = 0
            step = 1 << (max(1, min(block, chunk)).bit_length() - 1)  # a power of two: divides the chunk
            for i, sig in rec.reader.blocks("signals", step, start=rec.first):
                n = len(sig)
                images[filled:filled + n] = proc_.images(sig)
                filled += n
                if filled == len(images) or i - rec.first + n == T:
                    w.write(start, images=images[:filled],
                            **{key: rec.arrays[key][start:start + filled] for key in ("velocity", "time", *optional)})
                    start += filled
                    filled = 0
                    if progress:
                        progress(start, T)
            w.commit()
    finally:
        proc_.close()
