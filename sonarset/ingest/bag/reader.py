"""Read a bag's sonar, command and odometry topics into arrays, every problem found one line.

ROS 1 bags, ROS 2 bags (sqlite3 or MCAP, a directory with metadata.yaml) and bare ``.mcap`` files
open through rosbags' ``AnyReader``, which registers the message types the bag defines. Topics are
chosen by name, or by message type when exactly one topic has one of the accepted types.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sonarset.errors import InputValidationError, one_line
from sonarset.format.attrs import SensorGrid
import sonarset.ingest.bag.bounds as bounds
import sonarset.ingest.bag.messages as m

STAMPS = ("header", "bag")


@dataclass
class Stream:
    """One topic's messages: time stamps (integer ns as read; seconds since the first frame once
    ``read_streams`` returns) and, per kind, the values."""

    topic: str
    msgtype: str
    times: np.ndarray
    #: per kind; a frame topic's "images" is a list of (range, azimuth) frames in their pixel type
    values: dict[str, np.ndarray | list[np.ndarray]] = field(default_factory=dict)


@dataclass
class BagStreams:
    """What a bag holds for an import: frames on ``grid``, commands, and odometry if any."""

    bag: str
    frames: Stream
    grid: SensorGrid | None  # None for microphone signals: beamformed onto the store's grid
    commands: Stream
    odometry: Stream | None
    #: what was done to fit the data to the store (azimuth order reversed, beams resampled...)
    notes: list[str] = field(default_factory=list)
    #: the first frame's stamp, ns since the epoch; every stream's ``times`` are seconds since it
    origin_ns: int = 0


#: The most one MCAP or ROS 1 chunk may inflate to, and one ROS 2 sqlite3 message may take
#: (``bounds``). Writers cut chunks at 1-4 MiB (mcap's writers 1 MiB, rosbag2 4 MiB); a chunk
#: holds at least one message, so a large microphone ping makes one larger,
#: but a chunk declaring hundreds of megabytes is a decompression bomb (2 GB of zeros fit in 64 KB of
#: zstd), refused before anything is inflated.
MAX_CHUNK_BYTES = 256 * 2**20
MCAP_MAGIC = b"\x89MCAP0\r\n"


def open_reader(bag: Path):
    """An open AnyReader of ``bag``; InputValidationError naming the bag when it cannot be read."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not bag.exists():
        raise InputValidationError(str(bag), ["no such file or directory"])
    if not (bag.is_dir() or bag.is_file()):
        raise InputValidationError(str(bag), ["not a regular file or a bag directory"])
    if bag.is_file() and bag.suffix != ".bag" and _starts_with(bag, bounds.ROS1_MAGIC):
        # rosbags tells ROS 1 bags by their name: any other is taken for a ROS 2 one and misread
        why = (["a ROS 1 bag its recorder did not close (still recording, or killed): `rosbag reindex` it, "
                "then name it *.bag"] if bag.suffix == ".active" else ["a ROS 1 bag: name it *.bag"])
        raise InputValidationError(str(bag), why)
    for path in [bag] if bag.is_file() else sorted(bag.glob("*.mcap")) + sorted(bag.glob("*.db3")):
        problem = (mcap_chunk_problem(path) or bounds.ros1_chunk_problem(path, MAX_CHUNK_BYTES)
                   if path.suffix != ".db3" else bounds.sqlite_message_problem(path, MAX_CHUNK_BYTES))
        if problem is not None:
            raise InputValidationError(str(path), [problem])
    _bound_decompression()
    bounds.bound_ros1_inflation(MAX_CHUNK_BYTES)
    store = get_typestore(Stores.ROS2_JAZZY)
    try:
        reader = AnyReader([bag], default_typestore=store)
        reader.open()
    except Exception as exc:  # rosbags raises its own reader errors for truncated or foreign files
        raise InputValidationError(str(bag), [f"cannot read as a ROS bag or MCAP file: {one_line(exc)}"]) from None
    missing = {name: t for name, t in m.shipped_types().items() if name not in reader.typestore.types}
    if missing:  # a bag that does not define them (sqlite3 bags before Iron): the shipped definitions
        reader.typestore.register(missing)
    return reader


def _starts_with(path: Path, magic: bytes) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(len(magic)) == magic
    except OSError:
        return False


def mcap_chunk_problem(path: Path, limit: int | None = None) -> str | None:
    """The first chunk of the MCAP file ``path`` that declares more than ``limit`` bytes (default
    ``MAX_CHUNK_BYTES``) uncompressed, said in one line; None when every chunk is within it or
    the file is no MCAP. Only record headers are read, seeking over their bodies."""
    import struct

    limit = MAX_CHUNK_BYTES if limit is None else limit
    try:
        with open(path, "rb") as f:
            if f.read(8) != MCAP_MAGIC:
                return None
            end = path.stat().st_size
            at = 8
            while at + 9 <= end:
                f.seek(at)
                op, length = struct.unpack("<BQ", f.read(9))
                if op == 0x06:  # Chunk: message_start_time, message_end_time, uncompressed_size (u64 each)
                    declared = struct.unpack("<QQQ", f.read(24))[2] if length >= 24 else 0
                    if declared > limit:
                        return (f"its chunk at byte {at} declares {declared / 2**20:,.0f} MiB uncompressed, over the "
                                f"{limit / 2**20:g} MiB a chunk may hold (a decompression bomb?); not inflated")
                if op == 0x0F or op == 0x02:  # DataEnd, Footer: the summary holds no chunks
                    return None
                at += 9 + length
    except (OSError, struct.error):
        return None  # unreadable or cut short: the reader says so in its own words
    return None


def _bound_decompression() -> None:
    """Make rosbags inflate an MCAP chunk no further than the size it declares (one byte more, so
    that its size check fails): a chunk that lies about its size cannot fill memory either."""
    try:
        import rosbags.rosbag2.storage_mcap as storage
    except ImportError:
        return
    table = getattr(storage, "DECOMPRESSORS", None)
    if not isinstance(table, dict) or getattr(table.get("zstd"), "bounded", False):
        return
    zstd = getattr(storage, "zstd", None)
    if zstd is not None and hasattr(zstd, "ZstdDecompressor"):
        def inflate_zstd(data: bytes, size: int) -> bytes:
            out, rest = bytearray(), data
            while rest and len(out) <= size:  # a chunk may hold several zstd frames
                d = zstd.ZstdDecompressor()
                out += d.decompress(rest, max_length=size + 1 - len(out))
                if not d.eof:
                    break
                rest = d.unused_data
            return bytes(out)

        inflate_zstd.bounded = True
        table["zstd"] = inflate_zstd
    try:
        from lz4.frame import LZ4FrameDecompressor
    except ImportError:
        return

    def inflate_lz4(data: bytes, size: int) -> bytes:
        return LZ4FrameDecompressor().decompress(data, max_length=size + 1)

    table["lz4"] = inflate_lz4


def choose_topic(reader, wanted: str | None, types: tuple[str, ...], what: str, parameter: str,
                 problems: list[str], required: bool = True):
    """The connections of the topic named ``wanted``, else of the one topic with one of ``types``."""
    topics = {name: info.msgtype or _connection_types(reader, name) for name, info in reader.topics.items()}
    if wanted is not None:
        if wanted not in topics:
            problems.append(f"no topic {wanted!r} ({what}); the bag has {_listing(topics)}")
            return None
        if topics[wanted] not in types:
            problems.append(f"topic {wanted!r} is {topics[wanted]}, not {' or '.join(types)} ({what})")
            return None
        return wanted
    found = sorted(name for name, t in topics.items() if t in types)
    if len(found) == 1:
        return found[0]
    if len(found) > 1:
        problems.append(f"several {what} topics ({', '.join(found)}): name one ({parameter})")
    elif required:
        problems.append(f"no {what} topic ({' or '.join(types)}); the bag has {_listing(topics)}")
    return None


def _connection_types(reader, topic: str) -> str:
    """A topic recorded with several message types (rosbags gives it none): them all, which no
    importer reads as one stream."""
    kinds = sorted({c.msgtype for c in reader.connections if c.topic == topic})
    return " and ".join(kinds) if kinds else "of no message type"


def default_raw_topic(bag: Path) -> str | None:
    """The microphone signal topic a bag's frames come from when none is named: its one
    MicrophoneArrayPing topic, if it has no image topic."""
    reader = open_reader(bag)
    try:
        kinds = {t: i.msgtype for t, i in reader.topics.items()}
    finally:
        reader.close()
    pings = [t for t, kind in kinds.items() if kind in m.RAW_TYPES]
    return pings[0] if len(pings) == 1 and not any(k in m.IMAGE_TYPES for k in kinds.values()) else None


def _listing(topics: dict) -> str:
    return ", ".join(f"{k} ({v})" for k, v in sorted(topics.items())) or "no topics"


def read_streams(bag: str | Path, *, images: str | None = None, commands: str | None = None,
                 odometry: str | None = None, stamps: str = "header", grid: SensorGrid | None = None,
                 raw: str | None = None) -> BagStreams:
    """Decode the bag's topics; InputValidationError listing every problem.

    ``stamps``: 'header' (the messages' own stamps; Twist has none and takes the bag's) or 'bag'
    (when the bag recorded each message). ``grid``: the grid of ``sensor_msgs/Image`` frames (a
    ProjectedSonarImage carries its own). ``raw``: a ``MicrophoneArrayPing`` topic to take the
    frames from instead of images (``default_raw_topic``); its signals stay in the bag
    (``frames.values`` holds their shape) and ``grid`` is None.
    """
    bag = Path(bag)
    where = str(bag)
    if stamps not in STAMPS:
        raise InputValidationError(where, [f"stamps must be one of {', '.join(STAMPS)}, got {stamps!r}"],
                                   parameter="stamps")
    problems: list[str] = []
    reader = open_reader(bag)
    try:
        if raw is not None and images is not None:
            problems.append("give an image topic or a microphone signal topic, not both")
        if raw is not None:
            image_topic = choose_topic(reader, raw, m.RAW_TYPES, "microphone signal", "raw", problems)
        else:
            image_topic = choose_topic(reader, images, m.IMAGE_TYPES, "sonar image", "images", problems)
        command_topic = choose_topic(reader, commands, m.COMMAND_TYPES, "velocity command", "commands", problems)
        odom_topic = choose_topic(reader, odometry, m.ODOMETRY_TYPES, "odometry", "odometry", problems,
                                  required=False)
        if problems:
            raise InputValidationError(where, problems, parameter=("images", "raw", "commands", "odometry"))
        if raw is not None:
            frames, found_grid, notes = _read_pings(reader, image_topic, stamps, problems), None, []
        else:
            frames, found_grid, notes = _read_frames(reader, image_topic, stamps, grid, problems)
        frames_failed = bool(problems)  # a frame that cannot be decoded ends the topic: say that, not "empty"
        cmds = _read_commands(reader, command_topic, stamps, problems)
        odom = _read_odometry(reader, odom_topic, stamps, problems) if odom_topic else None
    except (bounds.TooLarge, _Damaged) as exc:
        raise InputValidationError(where, [str(exc)]) from None
    finally:
        reader.close()
    streams = [s for s in (frames, cmds, odom) if s is not None]
    for stream in streams:
        if not (stream is frames and frames_failed):
            problems += _stamp_problems(stream, stamps, repeats=stream is frames)
    if problems or (found_grid is None and raw is None):
        raise InputValidationError(where, problems or ["no sensor grid"])
    # Seconds since the first frame, from integer nanoseconds: float seconds since 1970 would
    # keep only ~0.1 us, and frame intervals should come back as recorded.
    origin = int(frames.times[0])
    for stream in streams:
        stream.times = (stream.times - origin) * 1e-9
    return BagStreams(where, frames, found_grid, cmds, odom, notes, origin_ns=origin)


def _messages(reader, topic: str, problems: list[str], stamps: str):
    """(index, time, message) of ``topic``, in bag order; decoding errors become problems."""
    conns = [c for c in reader.connections if c.topic == topic]
    try:
        for i, (conn, t_ns, raw) in enumerate(reader.messages(connections=conns)):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                problems.append(f"topic {topic!r}, message {i}: cannot decode {conn.msgtype}: {one_line(exc)}")
                return
            header = getattr(msg, "header", None)
            yield i, m.stamp_ns(header.stamp) if stamps == "header" and header is not None else int(t_ns), msg
    except bounds.TooLarge:  # the bag's, not the topic's: said once
        raise
    except Exception as exc:  # a bag cut short mid-chunk: every later topic would say so again
        raise _Damaged(f"the bag ends inside a message or is damaged (reading topic {topic!r}): "
                       f"{one_line(exc)}") from None


class _Damaged(Exception):
    """The bag's storage cannot be read on: one problem, whatever topic found it."""


def _stamp_problems(stream: Stream, stamps: str, repeats: bool = False) -> list[str]:
    """The first thing wrong with a stream's stamps, in one line; with ``repeats``, two equal
    stamps too (two frames at one moment: a driver that never updates its header's stamp)."""
    t = stream.times * 1e-9
    if t.size == 0:
        return [f"topic {stream.topic!r} has no messages"]
    fix = " (stamps 'bag' uses the time the bag recorded each message)" if stamps == "header" else ""
    if np.any(t <= 0):
        k = int(np.flatnonzero(t <= 0)[0])
        return [f"topic {stream.topic!r}, message {k}: time stamp {t[k]:g} s is zero or negative{fix}"]
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        k = int(back[0]) + 1
        return [f"topic {stream.topic!r}, message {k}: time stamps go backwards ({t[k - 1]:.6f} -> {t[k]:.6f} s){fix}"]
    same = np.flatnonzero(np.diff(stream.times) == 0) if repeats else []
    if len(same):
        k = int(same[0]) + 1
        return [f"topic {stream.topic!r}, message {k}: the same time stamp as message {k - 1} ({t[k]:.6f} s); "
                f"{int(len(same))} repeat(s){fix}"]
    return []


def _read_frames(reader, topic: str, stamps: str, grid: SensorGrid | None, problems: list[str]):
    from sonarset.ingest.bag.frames import FrameDecoder

    decoder = FrameDecoder(topic, grid)
    times, frames = [], []
    for i, t, msg in _messages(reader, topic, problems, stamps):
        image = decoder.decode(i, msg, problems)
        if image is None:
            break
        times.append(t)
        frames.append(image)
    # Held frame by frame in their own pixel type, never stacked: a 20,000-frame drive of uint8
    # images is 360 MB so, where one float32 stack (and its copies) was gigabytes.
    stream = Stream(topic, decoder.msgtype or "", np.asarray(times, np.int64), {"images": frames})
    stream.values["dtype"] = np.array(decoder.dtype or "")
    return stream, decoder.grid, decoder.notes


def _read_commands(reader, topic: str, stamps: str, problems: list[str]) -> Stream:
    times, v, w = [], [], []
    msgtype = reader.topics[topic].msgtype
    for _, t, msg in _messages(reader, topic, problems, stamps):
        twist = msg.twist if msgtype == m.TWIST_STAMPED else msg
        times.append(t)
        v.append(twist.linear.x)
        w.append(twist.angular.z)
    out = Stream(topic, msgtype, np.asarray(times, np.int64), {"v": np.asarray(v, float), "omega": np.asarray(w, float)})
    bad = np.flatnonzero(~np.isfinite(out.values["v"]) | ~np.isfinite(out.values["omega"]))
    if bad.size:
        problems.append(f"topic {topic!r}, message {int(bad[0])}: the command is not finite")
    return out


def _read_odometry(reader, topic: str, stamps: str, problems: list[str]) -> Stream:
    times, pose = [], []
    for _, t, msg in _messages(reader, topic, problems, stamps):
        p = msg.pose.pose
        times.append(t)
        pose.append((p.position.x, p.position.y, m.yaw_of(p.orientation)))
    out = Stream(topic, m.ODOMETRY, np.asarray(times, np.int64), {"pose": np.asarray(pose, float).reshape(-1, 3)})
    if not np.isfinite(out.values["pose"]).all():
        problems.append(f"topic {topic!r}: a pose is not finite")
    return out


def _read_pings(reader, topic: str, stamps: str, problems: list[str]) -> Stream:
    """Times and the common (channels, samples) shape and rate of a MicrophoneArrayPing topic, the
    samples checked for size; the signals themselves are streamed later (``bag.raw``)."""
    times, shape, rate = [], None, None
    for i, t, msg in _messages(reader, topic, problems, stamps):
        where = f"topic {topic!r}, message {i}"
        here = (int(msg.channel_count), int(msg.sample_count))
        if len(msg.samples) != here[0] * here[1]:
            problems.append(f"{where}: {len(msg.samples)} samples, {here[0]} channels x {here[1]} need "
                            f"{here[0] * here[1]}")
            break
        if shape is None:
            shape, rate = here, float(msg.sample_rate_hz)
        elif here != shape or float(msg.sample_rate_hz) != rate:
            problems.append(f"{where}: {here[0]} channels x {here[1]} samples at {msg.sample_rate_hz:g} Hz, the "
                            f"first ping had {shape[0]} x {shape[1]} at {rate:g} Hz")
            break
        times.append(t)
    return Stream(topic, m.MICROPHONES, np.asarray(times, np.int64),
                  {"shape": np.array(shape or (0, 0)), "sample_rate_hz": np.array(rate or 0.0)})
