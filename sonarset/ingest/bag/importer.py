"""``import_bag``: a ROS bag (ROS 1, ROS 2 sqlite3 or MCAP) as runs of a SonarSet store.

Everything is read and checked before anything is written, as ``import`` does: the bag's topics
(``reader``), the frames on one grid (``frames``), commands and poses on the frames and the
gaps at lost pings (``align``: a few lost pings are recorded in the run, which windows never
span; a long gap splits the run). Then the runs are written together, a store chunk of frames at
a time (each block checked against the format as it is written), built aside and published at
the end (``ImportTarget.write_runs``): a drive split into several runs is imported whole or not
at all.

Pixel values become the store's [0, 1] energyscape by one recorded rule (``source.value_rule``):
integer pixels are divided by their type's full scale (255 for uint8) and float pixels are taken
as an energyscape already, unless the sidecar's ``image_encoding`` says 'db' (decibels re full
scale) or 'linear' (energy), which map either over ``dynamic_range_db`` as for ``import``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from pydantic import ValidationError

from sonarset.errors import InputValidationError, SonarSetError
from sonarset.format.arrays import FRAME_INTERVAL_TOLERANCE
from sonarset.format.attrs import Processing, RobotRig, SensorGrid
from sonarset.format.problems import pydantic_problems
from sonarset.format.rules import command_limit_problems
from sonarset.format.units import grid_to_si
import sonarset.ingest.bag.align as align
from sonarset.ingest.bag.clock import command_clock, offset_hint, offset_warning
from sonarset.ingest.bag.plausible import IMPLAUSIBLE_NOTE, bag_implausible
from sonarset.ingest.bag.reader import BagStreams, read_streams
from sonarset.ingest.images import encode_images
from sonarset.ingest.metadata import recording_meta
from sonarset.ingest.target import ImportTarget, check_run_options, run_name_for
from sonarset.store.run import Run
from sonarset.store.writer import DEFAULT_CHUNK_FRAMES
from sonarset.windows import RUN_GAPS


@dataclass
class BagRecording:
    """A bag's runs, checked and in SonarSet conventions, ready to write."""

    source: str
    grid: SensorGrid | None  # None for microphone signals (beamformed onto the store's grid)
    runs: dict[str, dict[str, np.ndarray]]
    frame_interval_s: float
    notes: list[str]
    attrs: dict
    #: each run's frames as message indices start..stop-1 of the frame topic
    frames: dict[str, tuple[int, int]] = field(default_factory=dict)
    streams: BagStreams | None = None
    #: maps a block of frames (their pixel type) to the store's energyscape; None for signals
    to_energyscape: Callable[[np.ndarray], np.ndarray] | None = None
    #: each run's recorded gaps, ``[[k, lost], ...]`` (the run attribute ``gaps``)
    gaps: dict[str, list[list[int]]] = field(default_factory=dict)
    #: plausibility findings ``allow_implausible`` let through, and a command clock that looks off
    warnings: list[str] = field(default_factory=list)


def load_bag(bag: str | os.PathLike, *, images: str | None = None, commands: str | None = None,
             odometry: str | None = None, stamps: str = "header", command_offset_s: float = 0.0,
             command_timeout_s: float = align.COMMAND_TIMEOUT_S, meta_path: str | os.PathLike | None = None,
             name: str | None = None, grid: SensorGrid | None = None, raw: str | None = None,
             sidecar_meta=None, frame_interval_s: float | None = None, rig: RobotRig | None = None,
             allow_implausible: bool = False, note: Callable[[str], None] | None = None) -> tuple[BagRecording, object]:
    """Read and check a bag into runs; InputValidationError listing every problem. Returns the runs
    and the sidecar's metadata (``RecordingMeta``; for microphone signals, ``sidecar_meta``, the
    raw sidecar already read). ``frame_interval_s``: the interval the store to be written declares,
    which every run must keep to (default: the bag's median). The values must be plausible
    (``plausible``, as ``import`` checks them) against ``rig`` (the store's; default: the
    sidecar's); ``allow_implausible`` lets the findings through, as the recording's ``warnings``.
    A bag refused after frames were dropped tells ``note`` which (a success: ``notes``)."""
    bag = Path(bag)
    where = str(bag)
    problems: list[str] = []
    implausible: list[str] = []
    if not np.isfinite(command_offset_s):
        raise SonarSetError(f"command offset must be finite, got {command_offset_s}", parameter="command_offset_s")
    if not (0 < command_timeout_s < np.inf):
        raise SonarSetError(f"command timeout must be a finite time > 0 s, got {command_timeout_s}",
                            parameter="command_timeout_s")
    meta = sidecar_meta or recording_meta(bag, meta_path, None, problems, implausible)
    if meta is None:
        raise InputValidationError(where, problems)
    # a bag's commands are geometry_msgs' m/s and rad/s at their own stamps (REP 103): a sidecar
    # saying otherwise was written for `sonarset import`'s arrays, and would not be applied here
    units = meta.units
    unapplied = [f"units.{k} {getattr(units, k)!r}" for k, si in (("linear_velocity", "m/s"), ("angular_velocity", "rad/s"),
                                                                 ("time", "s")) if getattr(units, k) != si]
    unapplied += [f"velocity_alignment {meta.velocity_alignment!r}"] * (meta.velocity_alignment != "previous")
    if unapplied:
        raise InputValidationError(where, [f"metadata: {', '.join(unapplied)} do not apply to a bag, whose commands "
                                           "are in m/s and rad/s at their own time stamps; remove them"])
    if meta.grid is not None and sidecar_meta is None:
        try:
            grid = grid_to_si(meta.grid, meta.units)
        except ValidationError as exc:
            raise InputValidationError(where, list(map(str, pydantic_problems(exc, "metadata.grid.")))) from None
    streams = read_streams(bag, images=images, commands=commands, odometry=odometry, stamps=stamps, grid=grid,
                           raw=raw)
    base = run_name_for(bag, name, meta.name)
    to_energyscape = _energyscape_rule(streams, meta, problems) if streams.grid is not None else None
    clock = command_clock(streams, command_offset_s, command_timeout_s) if streams.grid is not None else None
    runs, frames, notes, interval, gaps = _runs(streams, base, command_offset_s, command_timeout_s,
                                                frame_interval_s, problems)
    if not problems:
        implausible += bag_implausible(runs, streams.grid, rig or meta.rig, interval, streams.commands.topic,
                                       streams.frames.topic)
    if runs and not problems:  # beyond any robot: no reader takes such a run, so no flag lets it through
        velocity = np.concatenate([r["velocity"] for r in runs.values()])
        beyond = [f"topic {streams.commands.topic!r}: {p.message}" for p in command_limit_problems(velocity)]
        if beyond:  # said once, and without a flag that could not help
            problems += beyond
            implausible = [line for line in implausible if not line.startswith(f"topic {streams.commands.topic!r}:")]
    if implausible and not allow_implausible:
        problems += [line + IMPLAUSIBLE_NOTE for line in implausible]
    hint = offset_hint(clock, command_offset_s)  # commands that reach no frame: a clock offset says why
    problems = [p + hint if p.startswith(f"topic {streams.commands.topic!r}: no command") else p for p in problems]
    if problems:
        if note is not None and notes:  # the frames dropped or split off may be why no run is left
            note(f"{bag}: {'; '.join(notes)}")
        named = (("allow_implausible",) * bool(implausible and not allow_implausible)
                 + ("command_offset_s",) * bool(hint))
        raise InputValidationError(where, problems, parameter=named[0] if len(named) == 1 else named or None)
    warnings = implausible + [line for line in [offset_warning(clock, interval, command_offset_s)] if line]
    # time 0 is the first imported frame's, after any frames before the first command were dropped
    name, (a, _) = next(iter(frames.items()))
    first_ns = streams.origin_ns + round(1e9 * (float(streams.frames.times[a]) - float(runs[name]["time"][0])))
    attrs = {"kind": "import-bag", "file": bag.name, "images_topic": streams.frames.topic,
             "images_type": streams.frames.msgtype, "commands_topic": streams.commands.topic,
             "commands_type": streams.commands.msgtype, "stamps": stamps, "command_offset_s": command_offset_s,
             "command_timeout_s": command_timeout_s, "frame_interval_s": interval, "first_stamp_ns": first_ns,
             "source": meta.source,
             "command_offset_estimate": clock.as_attr() if clock is not None else None}
    if streams.grid is not None:
        attrs["value_rule"] = _value_rule(streams, meta)
    if streams.odometry is not None:
        attrs["odometry_topic"] = streams.odometry.topic
    return BagRecording(where, streams.grid, runs, interval, streams.notes + notes, attrs, frames, streams,
                        to_energyscape, gaps, warnings), meta


def _runs(streams: BagStreams, base: str, offset_s: float, timeout_s: float, reference_s: float | None,
          problems: list[str]) -> tuple[dict, dict, list[str], float, dict]:
    """Each run's small arrays (velocity, time, pose), its frames' span of the frame topic and its
    recorded gaps."""
    times = streams.frames.times
    cmd_t = streams.commands.times + offset_s
    notes: list[str] = []
    if len(times) < align.MIN_SEGMENT:
        problems.append(f"topic {streams.frames.topic!r}: {len(times)} frame(s), a run needs at least "
                        f"{align.MIN_SEGMENT}")
        return {}, {}, notes, 0.0, {}
    edges = align.frame_edges(times)
    covered = align.command_coverage(cmd_t, edges, timeout_s) if cmd_t.size else np.zeros(len(times), bool)
    if not covered.any():
        problems.append(f"topic {streams.commands.topic!r}: no command reaches any frame interval (commands "
                        f"{_span(cmd_t)}, frames {_span(times)}; a clock offset? command_offset_s shifts them)")
        return {}, {}, notes, 0.0, {}
    first = int(np.argmax(covered))
    if first:
        notes.append(f"frames 0..{first - 1} dropped: before the first command")
    uncovered = np.flatnonzero(~covered[first:]) + first
    if uncovered.size:
        k = int(uncovered[0])
        problems.append(f"topic {streams.commands.topic!r}: no command over frame {k}'s interval "
                        f"({times[k - 1] - times[0] if k else 0:.3f}..{times[k] - times[0]:.3f} s after the first frame;"
                        f" a command older than {timeout_s:g} s has stopped the robot)")
        return {}, {}, notes, 0.0, {}
    velocity = np.stack([align.held_mean(cmd_t, streams.commands.values[k], edges, timeout_s)
                         for k in ("v", "omega")], axis=1).astype(np.float32)
    pose = None
    if streams.odometry is not None:
        ot, half = streams.odometry.times, 0.5 * float(np.median(np.diff(times)))
        outside = (times < ot[0] - half) | (times > ot[-1] + half)
        if outside[first:].any():
            k = int(np.flatnonzero(outside[first:])[0]) + first
            problems.append(f"topic {streams.odometry.topic!r}: odometry ({_span(ot)}) does not cover frame {k} "
                            f"at {times[k]:.3f} s")
        else:
            pose = align.poses_at(times, ot, streams.odometry.values["pose"])
    # a hair inside the format's tolerance: the store declares the rate rounded to 4 digits
    segments, split_notes, interval = align.split_at_gaps(times[first:], FRAME_INTERVAL_TOLERANCE - 1e-3,
                                                          reference_s)
    notes += split_notes
    if not segments:
        problems.append(f"topic {streams.frames.topic!r}: no run of {align.MIN_SEGMENT} frames at a steady rate "
                        f"({split_notes[0] if split_notes else 'too few frames'})")
        return {}, {}, notes, 0.0, {}
    runs: dict[str, dict[str, np.ndarray]] = {}
    frames: dict[str, tuple[int, int]] = {}
    gaps: dict[str, list[list[int]]] = {}
    for i, seg in enumerate(segments):
        a, b = seg.start + first, seg.stop + first
        run = {"velocity": velocity[a:b], "time": times[a:b] - times[first]}
        if pose is not None:
            run["pose"] = pose[a:b]
        name = base if len(segments) == 1 else f"{base}_{i:03d}"
        runs[name], frames[name], gaps[name] = run, (a, b), [list(g) for g in seg.gaps]
    return runs, frames, notes, interval, gaps


def _span(t: np.ndarray) -> str:
    return f"{t[0]:.3f}..{t[-1]:.3f} s" if t.size else "none"


def _energyscape_rule(streams: BagStreams, meta, problems: list[str]) -> Callable[[np.ndarray], np.ndarray] | None:
    """The mapping of a block of frames to the store's [0, 1] energyscape (``source.value_rule``),
    fixed over the whole topic (linear energy is normalised to the topic's peak) and checked as
    ``import`` checks images, without holding the frames as float at once: the blocks are mapped
    as they are written."""
    frames = streams.frames.values["images"]
    dtype = np.dtype(str(streams.frames.values["dtype"]) or "f4")
    if dtype.kind in "iu" and meta.image_encoding == "energyscape":
        full = np.float32(np.iinfo(dtype).max)
        return lambda block: np.clip(block / full, 0.0, 1.0, dtype=np.float32)
    if not frames:
        return None
    bad = next((k for k, f in enumerate(frames) if not np.isfinite(f).all()), None)
    if bad is not None:
        problems.append(f"topic {streams.frames.topic!r}, message {bad}: NaN or infinite pixel values")
        return None
    lo, hi = min(float(np.min(f)) for f in frames), max(float(np.max(f)) for f in frames)
    found: list[str] = []
    encode_images(np.array([[[lo, hi]]], np.float32), meta, found)  # the same checks, on the extremes
    problems += [f"topic {streams.frames.topic!r}: {p}" for p in found]
    if found:
        return None
    dr = meta.dynamic_range_db
    if meta.image_encoding == "db":  # as ``encode_images`` maps a whole recording
        return lambda block: np.clip((block.astype(np.float64) + dr) / dr, 0.0, 1.0).astype(np.float32)
    if meta.image_encoding == "linear":
        def linear(block: np.ndarray) -> np.ndarray:
            with np.errstate(divide="ignore"):
                db = 10.0 * np.log10(block.astype(np.float64) / hi)
            return np.clip((db + dr) / dr, 0.0, 1.0).astype(np.float32)

        return linear
    return lambda block: block.astype(np.float32)


def _value_rule(streams: BagStreams, meta) -> str:
    dtype = np.dtype(str(streams.frames.values["dtype"]) or "f4")
    if meta.image_encoding == "energyscape":
        if dtype.kind in "iu":
            return f"{dtype.name} / {np.iinfo(dtype).max} (full scale)"
        return "float, taken as an energyscape in [0, 1]"
    kind = dtype.name if dtype.kind in "iu" else "float"
    return f"{kind} {meta.image_encoding}, mapped over {meta.dynamic_range_db:g} dB"


def import_bag(bag: str | os.PathLike, out: str | os.PathLike, *, images: str | None = None,
               raw: str | None = None, commands: str | None = None, odometry: str | None = None,
               stamps: str = "header", command_offset_s: float = 0.0,
               command_timeout_s: float = align.COMMAND_TIMEOUT_S, meta_path: str | os.PathLike | None = None,
               name: str | None = None, split: str | None = None, overwrite: bool = False,
               processing: str | Processing = "ertis", beamformer: str | None = None, workers: int = 2,
               allow_implausible: bool = False, note: Callable[[str], None] | None = None,
               warn: Callable[[str], None] | None = None,
               progress: Callable[[int, int], None] | None = None) -> list[Run]:
    """Validate the bag ``bag`` completely, then write it as runs of the store ``out``: ``NAME``,
    or ``NAME_000``, ``NAME_001``... when a gap of over ``align.MAX_LOST`` lost pings splits it;
    shorter gaps stay in their run, recorded in its attribute ``gaps``, which windows never span.

    ``images``, ``commands``, ``odometry``: topic names (default: the one topic of an accepted type;
    odometry is optional). ``raw``: a ``sonarset_msgs/MicrophoneArrayPing`` topic to beamform
    instead (the default when the bag has no image topic and one such topic), with ``import-raw``'s
    sidecar, ``processing`` and ``beamformer``, on ``workers`` threads. ``stamps``: 'header' or
    'bag'. ``command_offset_s`` is added to every command time (a known clock offset). The sidecar
    (``meta_path``; default ``BAG.json`` beside a bag file, ``BAG/recording.json`` in a bag
    directory; ``export_bag`` writes one) gives what ``import`` (or ``import-raw``) takes from one:
    name, split, grid (needed for ``sensor_msgs/Image``), rig, processing, image encoding. A new
    store records the sidecar rig's frame interval where the bag's measured one agrees with it,
    else the measured one; an existing store must have the same grid and frame rate. ``note``
    receives, in one line, what was done to fit the data (gaps recorded and splits at lost pings,
    dropped frames, resampling). Every run is built aside and the runs are published together: an
    import killed or failed midway leaves ``out`` as it was.
    The values must be plausible, as for ``import``: ``allow_implausible`` imports what the rules
    question, passing each finding to ``warn``.
    """
    from sonarset.ingest.bag.reader import default_raw_topic
    from sonarset.ingest.raw import resolve_processing

    check_run_options(name, split)
    target = ImportTarget.at(out)
    have = target.existing
    bag = Path(bag)
    if raw is None and images is None:  # the kind of frames decides which sidecar applies
        raw = default_raw_topic(bag)
    sidecar_meta = sidecar = None
    if raw is not None:
        from sonarset.ingest.bag.raw import raw_sidecar

        sidecar_meta, sidecar = raw_sidecar(bag, meta_path)
    rec, meta = load_bag(bag, images=images, commands=commands, odometry=odometry, stamps=stamps,
                         command_offset_s=command_offset_s, command_timeout_s=command_timeout_s,
                         meta_path=meta_path, name=name, grid=have.grid if have is not None else None,
                         raw=raw, sidecar_meta=sidecar_meta,
                         frame_interval_s=1.0 / have.attrs.frame_rate_hz if have is not None else None,
                         rig=have.rig if have is not None else None, allow_implausible=allow_implausible, note=note)
    for line in rec.warnings:
        if warn is not None:
            warn(f"{bag}: {line}")
    # The store's nominal rate and its rig's interval are one fact (the format checks that they
    # agree): the sidecar rig's where the bag's median agrees with it, else the bag's, rounded.
    rate_hz = float(f"{1.0 / rec.frame_interval_s:.4g}")
    rig = meta.rig
    if meta.rig is not None and abs(meta.rig.frame_interval_s - rec.frame_interval_s) <= \
            FRAME_INTERVAL_TOLERANCE * meta.rig.frame_interval_s:
        rate_hz = 1.0 / meta.rig.frame_interval_s
    elif meta.rig is not None:
        rig = meta.rig.model_copy(update={"frame_interval_s": 1.0 / rate_hz})
        rec.notes.append(f"the sidecar's rig says {meta.rig.frame_interval_s:g} s frames; the bag's are "
                         f"{rec.frame_interval_s:.4g} s (median), which the store records")
    if have is not None:
        declared = 1.0 / have.attrs.frame_rate_hz
        if abs(declared - rec.frame_interval_s) > FRAME_INTERVAL_TOLERANCE * declared:
            raise InputValidationError(rec.source, [f"frames are {rec.frame_interval_s:.4g} s apart (median), the store "
                                                    f"{have.location} declares {declared:g} s frames; import into "
                                                    "another store"])
    run_split = split if split is not None else meta.split
    if raw is not None:
        from sonarset.ingest.bag.raw import raw_runs

        proc = processing if isinstance(processing, Processing) else resolve_processing(processing, beamformer)
        grid, writers = raw_runs(rec, meta, sidecar, have.grid if have is not None else None, proc, run_split,
                                 workers, progress)
        description = f"imported from raw microphone signals in the ROS bag {bag.name}"
    else:
        proc, grid = meta.processing, rec.grid
        writers = [(n, ImageRunWriter(n, arrays, rec.frames[n], rec.streams.frames.values["images"],
                                      rec.to_energyscape, run_split, rec.attrs)) for n, arrays in rec.runs.items()]
        description = f"imported from the ROS bag {bag.name}"
    writers = [(n, GapRecorder(write, rec.gaps.get(n, []))) for n, write in writers]
    if note is not None and rec.notes:  # one line, however much was done: a drive can lose a hundred pings
        note(f"{bag}: {'; '.join(rec.notes)}")
    # every run is built aside and published at the end: a killed import leaves the store as it was
    return target.write_runs(writers, overwrite=overwrite, grid=grid, processing=proc,
                             rig=rig if have is None else None,
                             new_store={"frame_rate_hz": rate_hz,
                                        "processing": proc or Processing(profile="unknown"),
                                        "description": description})


@dataclass
class ImageRunWriter:
    """Writes one run of a bag's frames (``span`` of the topic's ``frames``), a store chunk at a
    time, each block mapped to the energyscape as it goes: a long drive is never float32 at once."""

    name: str
    arrays: dict[str, np.ndarray]  # velocity, time and pose, if any
    span: tuple[int, int]
    frames: list[np.ndarray]
    to_energyscape: Callable[[np.ndarray], np.ndarray]
    split: str
    source: dict

    def __call__(self, store, replace: bool) -> None:
        a, n = self.span[0], self.span[1] - self.span[0]
        optional = ("pose",) if "pose" in self.arrays else ()
        with store.run_writer(self.name, n, split=self.split, source=self.source, optional=optional,
                              image_dtype="float32", overwrite=replace, consolidate=False) as w:
            for start in range(0, n, DEFAULT_CHUNK_FRAMES):
                stop = min(n, start + DEFAULT_CHUNK_FRAMES)
                images = self.to_energyscape(np.stack(self.frames[a + start:a + stop]))
                w.write(start, images=images, **{k: v[start:stop] for k, v in self.arrays.items()})
            w.commit()


@dataclass
class GapRecorder:
    """A run writer (``ImageRunWriter`` or ``import-raw``'s) whose run records ``gaps`` in its
    attributes (``sonarset.windows.RUN_GAPS``), written with them by its ``commit``."""

    write: Callable
    gaps: list[list[int]]

    def __call__(self, store, replace: bool) -> None:
        self.write(_RecordingGaps(store, self.gaps) if self.gaps else store, replace)


class _RecordingGaps:
    """A store whose run writers commit the run with its gaps; everything else is the store's."""

    def __init__(self, store, gaps: list[list[int]]):
        self._store, self._gaps = store, gaps

    def run_writer(self, *args, **kwargs):
        writer = self._store.run_writer(*args, **kwargs)
        writer.attrs = writer.attrs.model_copy(update={RUN_GAPS: self._gaps})
        return writer

    def __getattr__(self, name: str):
        return getattr(self._store, name)
