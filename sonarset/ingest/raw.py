"""Import raw microphone recordings: beamform them into energyscapes, one run of a SonarSet store.

A raw recording is per-measurement microphone signals (T, channels, samples) in a ``.npz`` or a
directory of ``.npy`` files, with a JSON sidecar (``RawRecordingMeta``: sample rate, sweep,
microphone layout, speed of sound; read by ``metadata``). It is read and checked completely first
(``load_raw``): every problem is one line naming the file, including one streamed pass over the
signals for non-finite values and dead channels. Signals stay on disk (``files.RawSource``) and are
read in blocks of measurements, so memory does not grow with the recording's length.

Each measurement then goes through the eRTIS imaging chain (``sensor.beamform``: matched filter, DAS
or DMAS3-CF, envelope; then ``energyscape.postprocess`` or the raw log mapping with the simulator's
full scale), so an imported run holds the images the simulator would make of the same echoes. The
run is written as ``import_recording`` writes one (``target``): built in a store beside the output,
then renamed into place or swapped for the run it replaces; an object store gets it through its run
writer, invisible until committed.
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from sonarset.errors import InputValidationError, SonarSetError
from sonarset.format import plausibility
from sonarset.format.arrays import dtype_problems, layout_problems, nonfinite_problems, time_order_problems
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.format.sidecars import RawRecordingMeta
from sonarset.format.units import pose_to_si, time_to_si, velocity_to_si
from sonarset.ingest.files import RawSource, short_reason
from sonarset.ingest.metadata import emitted_sweep, microphone_layout, raw_grid, raw_meta, sidecar_for
from sonarset.ingest.target import ImportTarget, check_run_options, nominal_frame_rate, run_name_for
from sonarset.sensor.exact import MARGIN_S
from sonarset.store.run import Run
from sonarset.store.store import SonarStore
from sonarset.store.writer import DEFAULT_CHUNK_FRAMES

ARRAY_KEYS = ("signals", "velocity", "time", "pose", "sweep")
REQUIRED_KEYS = ("signals", "velocity", "time")
BLOCK = 8  # measurements read and beamformed at a time (8 x 32 x 7000 float32: 7 MB); divides a chunk


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
    meta = raw_meta(sidecar, problems)
    problems += [f"unknown array {key!r} (expected {', '.join(ARRAY_KEYS)})" for key in reader.members
                 if key not in ARRAY_KEYS]
    problems += [f"missing required array {key!r}" for key in REQUIRED_KEYS if key not in reader.members]
    T, M, n = _signals_shape(reader, problems)
    small = _small_arrays(reader, T, problems)
    if meta is None:
        raise InputValidationError(where, problems)
    _small_to_si(small, meta, problems)
    positions = microphone_layout(meta, sidecar, problems)
    if positions is not None and M is not None and M != len(positions):
        problems.append(f"signals: {M} channels but the microphone layout has {len(positions)} microphones")
    sweep = emitted_sweep(meta, reader, problems)
    out_grid = raw_grid(meta, grid, problems)
    if out_grid is not None:
        problems += grid_time_and_echo_problems(meta, out_grid, small.get("time"), n, sweep)
    if T is not None and meta.velocity_alignment == "next" and T < 2:
        problems.append("velocity_alignment 'next' needs at least 2 measurements")
    if not problems and scan:
        problems += signal_problems(reader, where)
    if problems:
        raise InputValidationError(where, problems)
    first = 1 if meta.velocity_alignment == "next" else 0
    arrays = {"time": small["time"][first:],
              "velocity": (small["velocity"][:-1] if first else small["velocity"]).astype(np.float32)}
    if "pose" in small:
        arrays["pose"] = small["pose"][first:]
    return RawRecording(where, meta, reader, positions, sweep, first, arrays), out_grid


def _signals_shape(reader: RawSource, problems: list[str]) -> tuple[int | None, int | None, int | None]:
    """(measurements, channels, samples) of the signals; Nones when they cannot be streamed."""
    sig = reader.members.get("signals")
    if sig is None:
        return None, None, None
    if len(sig.shape) != 3:
        problems.append(f"signals: expected 3-D (measurement, channel, sample), got shape {sig.shape}")
    elif dtype_problems("signals", sig):
        problems += map(str, dtype_problems("signals", sig))
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
        found = [str(p) for p in dtype_problems(key, m) or layout_problems(key, m.shape)]
        if not found and n_measurements is not None and m.shape[0] != n_measurements:
            found = [f"{key}: {m.shape[0]} rows but signals has {n_measurements} measurements"]
        if not found:
            try:
                arr = reader.read(key).astype(np.float64)
            except Exception as exc:
                found = [f"{key}: unreadable ({short_reason(exc)})"]
            else:
                found = [str(p) for p in nonfinite_problems(key, arr, unit="measurement")]
        if found:
            problems += found
            continue
        small[key] = arr
    return small


def _small_to_si(small: dict[str, np.ndarray], meta: RawRecordingMeta, problems: list[str]) -> None:
    """Convert ``small`` to SI in place, with the image importer's command and time-order rules."""
    u = meta.units
    if "velocity" in small:
        small["velocity"] = velocity_to_si(small["velocity"], u)
        problems += map(str, plausibility.command_problems(small["velocity"], meta.rig, u))
    if "time" in small:
        small["time"] = time_to_si(small["time"], u)
        problems += map(str, time_order_problems(small["time"], unit="measurement"))
    if "pose" in small:
        small["pose"] = pose_to_si(small["pose"], u)


def grid_time_and_echo_problems(meta: RawRecordingMeta, grid: SensorGrid, time: np.ndarray | None,
                                 n_samples: int | None, sweep: np.ndarray | None) -> list[str]:
    """The declared grid's and the time stamps' plausibility, and whether every measurement holds
    the echoes from the grid's first to its last range."""
    found = plausibility.grid_problems(grid, meta.units) if meta.grid is not None else []
    if time is not None:
        found += plausibility.time_problems(time, meta.rig.frame_interval_s if meta.rig else None,
                                            grid.range_max_m, meta.units, "sidecar's rig")
    out = [str(p) for p in found]
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


def signal_problems(reader: RawSource, where: str) -> list[str]:
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


def resolve_processing(profile: str = "ertis", beamformer: str | None = None) -> Processing:
    """The simulator's profile ``profile`` with its beamformer, or another (profile then 'custom')."""
    try:
        proc = Processing.named(profile)
    except ValueError as exc:
        raise SonarSetError(str(exc), parameter="processing") from None
    if beamformer is None or beamformer == proc.beamformer:
        return proc
    from sonarset.format.attrs import BEAMFORMERS

    if beamformer not in BEAMFORMERS:
        raise SonarSetError(f"beamformer must be one of {', '.join(BEAMFORMERS)}, got {beamformer!r}",
                            parameter="beamformer")
    return proc.model_copy(update={"beamformer": beamformer, "profile": "custom"})


class RawProcessor:
    """Measurements (B, M, n) -> energyscapes (B, R, A) float16, as the simulator makes them."""

    def __init__(self, rec: RawRecording, grid: SensorGrid, processing: Processing, workers: int = 2):
        from sonarset.sensor.beamform import SignalBeamformer
        from sonarset.sim.sonar import SonarModel

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


def import_raw(src: str | os.PathLike, out: str | os.PathLike, *, meta_path: str | os.PathLike | None = None,
               name: str | None = None, split: str | None = None, processing: str | Processing = "ertis",
               beamformer: str | None = None, grid: SensorGrid | None = None, overwrite: bool = False,
               workers: int = 2, block: int = BLOCK, progress: Callable[[int, int], None] | None = None) -> Run:
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
    target = ImportTarget.at(out)
    rec, out_grid = load_raw(src, meta_path, grid=target.existing.grid if target.existing is not None else grid)
    meta = rec.meta
    source = {"kind": "import-raw", "file": Path(src).name, "sample_rate_hz": meta.sample_rate_hz,
              "speed_of_sound_m_s": meta.speed_of_sound_m_s, "microphones": int(len(rec.positions)),
              "beamformer": proc.beamformer, "processing": proc.profile,
              "velocity_alignment": meta.velocity_alignment, "source": meta.source}
    writer = RawRunWriter(rec, out_grid, proc, run_name_for(src, name, meta.name), split or meta.split, source,
                           workers, block, progress)
    return target.write(writer.name, writer, overwrite=overwrite, grid=out_grid, processing=proc, rig=meta.rig,
                        new_store={"processing": proc, "frame_rate_hz": nominal_frame_rate(rec.arrays["time"], meta.rig),
                                   "description": f"imported from raw microphone signals ({Path(src).name})"})


@dataclass
class RawRunWriter:
    """Beamforms a raw recording into the run ``name`` of a store, whole store chunks at a time."""

    rec: RawRecording
    grid: SensorGrid
    processing: Processing
    name: str
    split: str
    source: dict
    workers: int
    block: int
    progress: Callable[[int, int], None] | None

    def __call__(self, store: SonarStore, replace: bool) -> None:
        rec, T = self.rec, self.rec.n_frames
        optional = ("pose",) if "pose" in rec.arrays else ()
        processor = RawProcessor(rec, self.grid, self.processing, self.workers)
        # Images are collected into whole store chunks before writing: a block smaller than a chunk
        # would make every write recompress the chunk.
        chunk = DEFAULT_CHUNK_FRAMES
        images = np.empty((min(chunk, T), *self.grid.shape), np.float16)
        try:
            with store.run_writer(self.name, T, split=self.split, source=self.source, optional=optional,
                                  overwrite=replace, consolidate=False) as w:
                start = filled = 0
                step = 1 << (max(1, min(self.block, chunk)).bit_length() - 1)  # a power of two: divides the chunk
                for i, sig in rec.reader.blocks("signals", step, start=rec.first):
                    n = len(sig)
                    images[filled:filled + n] = processor.images(sig)
                    filled += n
                    if filled == len(images) or i - rec.first + n == T:
                        w.write(start, images=images[:filled],
                                **{key: rec.arrays[key][start:start + filled] for key in ("velocity", "time", *optional)})
                        start += filled
                        filled = 0
                        if self.progress:
                            self.progress(start, T)
                w.commit()
        finally:
            processor.close()
