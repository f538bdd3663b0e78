"""Import raw microphone recordings: beamform them into energyscapes, one run of a SonarSet store.

The recording is read and checked completely first (``raw_recording``). Each measurement then goes
through the simulator's processing stage (``sim.beamform``: matched filter, DAS or DMAS3-CF,
envelope; then ``energyscape.postprocess`` or the raw log mapping with the simulator's full
scale), so an imported run holds the images the simulator would make of the same echoes. The run
is written as ``sonarset import`` writes one (``import_target``): built in a store beside OUT, then
renamed into place or swapped for the run it replaces; an object store gets it through its run
writer, invisible until committed.
"""

from __future__ import annotations

import concurrent.futures as cf
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from sonarset.errors import SonarSetError
from sonarset.ingest.target import ImportTarget, check_run_options, nominal_frame_rate, run_name_for
from sonarset.ingest.raw_recording import BLOCK, RawRecording, load_raw
from sonarset.store.run import Run
from sonarset.store.writer import DEFAULT_CHUNK_FRAMES
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.store.store import SonarStore


def resolve_processing(profile: str = "ertis", beamformer: str | None = None) -> Processing:
    """The simulator's profile ``profile`` with its beamformer, or another (profile then 'custom')."""
    try:
        proc = Processing.named(profile)
    except ValueError as exc:
        raise SonarSetError(f"--processing: {exc}") from None
    if beamformer is None or beamformer == proc.beamformer:
        return proc
    from sonarset.sensor.energyscape import BEAMFORMERS

    if beamformer not in BEAMFORMERS:
        raise SonarSetError(f"--beamformer must be one of {', '.join(BEAMFORMERS)}, got {beamformer!r}")
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
    writer = _RawRunWriter(rec, out_grid, proc, run_name_for(src, name, meta.name), split or meta.split, source,
                           workers, block, progress)
    return target.write(writer.name, writer, overwrite=overwrite, grid=out_grid, processing=proc, rig=meta.rig,
                        new_store={"processing": proc, "frame_rate_hz": nominal_frame_rate(rec.arrays["time"], meta.rig),
                                   "description": f"imported from raw microphone signals ({Path(src).name})"})


@dataclass
class _RawRunWriter:
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
