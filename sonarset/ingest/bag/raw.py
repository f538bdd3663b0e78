"""Microphone signals from a bag (``sonarset_msgs/MicrophoneArrayPing``), beamformed as
``import-raw`` beamforms a file: the same sidecar (sample rate, sweep, microphones, speed of
sound), the same checks, the same processing, streamed a block of pings at a time."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from sonarset.errors import InputValidationError
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.ingest.files import ArrayMember
from sonarset.ingest.metadata import emitted_sweep, microphone_layout, raw_grid, raw_meta, sidecar_for
from sonarset.ingest.raw import RawRecording, RawRunWriter, grid_time_and_echo_problems, signal_problems


class BagSignals:
    """What ``import-raw``'s writer reads (``RawSource``'s face) over the pings ``start..stop-1`` of
    a bag topic: ``signals`` (pings, channels, samples) float32, decoded a block at a time."""

    def __init__(self, bag: Path, topic: str, start: int, stop: int, shape: tuple[int, int]):
        self.bag, self.topic, self.start, self.stop = bag, topic, start, stop
        self.members = {"signals": ArrayMember((stop - start, *shape), np.dtype(np.float32), False, bag)}
        self.problems: list[str] = []

    def read(self, key: str) -> np.ndarray:
        raise KeyError(key)  # only signals come from the bag: small arrays are aligned beforehand

    def blocks(self, key: str, block: int, start: int = 0) -> Iterator[tuple[int, np.ndarray]]:
        from sonarset.ingest.bag.reader import open_reader

        shape = self.members["signals"].shape
        reader = open_reader(self.bag)
        try:
            conns = [c for c in reader.connections if c.topic == self.topic]
            rows, first = [], start
            for i, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
                k = i - self.start
                if k < start:
                    continue
                if k >= shape[0]:
                    break
                msg = reader.deserialize(raw, conn.msgtype)
                rows.append(np.asarray(msg.samples, np.float32).reshape(shape[1:]))
                if len(rows) == block:
                    yield first, np.stack(rows)
                    first, rows = first + len(rows), []
            if rows:
                yield first, np.stack(rows)
        finally:
            reader.close()


def raw_sidecar(bag: Path, meta_path) -> tuple[object, Path]:
    """The raw sidecar (``BAG.json`` unless given): sample rate, sweep, microphones..."""
    problems: list[str] = []
    sidecar = Path(meta_path) if meta_path is not None else sidecar_for(bag)
    meta = raw_meta(sidecar, problems)
    if meta is None:
        raise InputValidationError(str(bag), problems)
    return meta, sidecar


def raw_runs(rec, meta, sidecar: Path, grid: SensorGrid | None, processing: Processing, split: str,
             workers: int, progress) -> tuple[SensorGrid, list[tuple[str, RawRunWriter]]]:
    """One ``import-raw`` run writer per run of the bag recording ``rec`` (``importer.BagRecording``),
    after the checks ``import-raw`` makes: the sidecar against the pings, the grid, every signal."""
    frames = rec.streams.frames
    channels, samples = (int(v) for v in frames.values["shape"])
    problems: list[str] = []
    rate = float(frames.values["sample_rate_hz"])
    if abs(rate - meta.sample_rate_hz) > 1e-6 * meta.sample_rate_hz:
        problems.append(f"topic {frames.topic!r}: pings sampled at {rate:g} Hz, the sidecar says "
                        f"{meta.sample_rate_hz:g} Hz")
    positions = microphone_layout(meta, sidecar, problems)
    if positions is not None and channels != len(positions):
        problems.append(f"topic {frames.topic!r}: {channels} channels but the microphone layout has "
                        f"{len(positions)} microphones")
    all_pings = BagSignals(Path(rec.source), frames.topic, 0, len(frames.times), (channels, samples))
    sweep = emitted_sweep(meta, all_pings, problems)
    out_grid = raw_grid(meta, grid, problems)
    if out_grid is not None:
        problems += grid_time_and_echo_problems(meta, out_grid, None, samples, sweep)
    if not problems:
        problems += [f"topic {frames.topic!r}: {p}" for p in signal_problems(all_pings, frames.topic)]
    if problems:
        raise InputValidationError(rec.source, problems)
    source = {**rec.attrs, "sample_rate_hz": meta.sample_rate_hz, "speed_of_sound_m_s": meta.speed_of_sound_m_s,
              "microphones": int(len(positions)), "beamformer": processing.beamformer,
              "processing": processing.profile}
    writers = []
    for name, arrays in rec.runs.items():
        a, b = rec.frames[name]
        pings = BagSignals(Path(rec.source), frames.topic, a, b, (channels, samples))
        one = RawRecording(rec.source, meta, pings, positions, sweep, 0, dict(arrays))
        writers.append((name, RawRunWriter(one, out_grid, processing, name, split, source, workers, 8, progress)))
    return out_grid, writers
