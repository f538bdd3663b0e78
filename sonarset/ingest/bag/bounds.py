"""Size limits for ROS 1 bags and ROS 2 sqlite3 bags, as ``reader`` sets them for MCAP chunks.

A ROS 1 bag's chunk record declares its uncompressed ``size``; rosbags inflates a chunk whole
(bz2 or lz4) without looking at it, and 2 GB of zeros fit in a few kilobytes of bz2. A ROS 2
sqlite3 bag holds each message as a blob that rosbags reads whole. Both are checked before
anything is inflated or decoded: the first chunk or message over the limit is said in one line,
naming where it is. A chunk that lies about its size is inflated no further than the limit (a
byte more, so that it fails).
"""

from __future__ import annotations

import struct
from pathlib import Path

ROS1_MAGIC = b"#ROSBAG V2.0\n"


class TooLarge(ValueError):
    """A chunk inflated past the limit (one line): the whole bag is refused, not a topic."""
ROS1_CHUNK = 0x05


def _size(n: int) -> str:
    return f"{n / 2**20:,.0f} MiB" if n >= 2**20 else f"{n:,} bytes"


def _over(declared: int, limit: int, what: str) -> str:
    return (f"{what} declares {_size(declared)} uncompressed, over the {_size(limit)} a chunk may hold (a "
            "decompression bomb?); not inflated")


def ros1_chunk_problem(path: Path, limit: int) -> str | None:
    """The first chunk of the ROS 1 bag ``path`` whose header declares more than ``limit`` bytes
    uncompressed, in one line; None when every chunk is within it or the file is no ROS 1 bag.
    Only record headers are read, seeking over their data."""
    try:
        with open(path, "rb") as f:
            if f.read(len(ROS1_MAGIC)) != ROS1_MAGIC:
                return None
            end = path.stat().st_size
            at = len(ROS1_MAGIC)
            while at + 8 <= end:
                f.seek(at)
                (header_len,) = struct.unpack("<I", f.read(4))
                if header_len > min(end - at, 2**20):
                    return None  # damaged: the reader says so in its own words
                fields = _fields(f.read(header_len))
                (data_len,) = struct.unpack("<I", f.read(4))
                if fields.get("op") == bytes([ROS1_CHUNK]) and len(fields.get("size", b"")) == 4:
                    declared = struct.unpack("<I", fields["size"])[0]
                    if declared > limit:
                        return _over(declared, limit, f"its chunk at byte {at}")
                at += 8 + header_len + data_len
    except (OSError, struct.error):
        return None
    return None


def _fields(header: bytes) -> dict[str, bytes]:
    """A ROS 1 record header's ``name=value`` fields, each prefixed by its u32 length."""
    out, at = {}, 0
    while at + 4 <= len(header):
        (n,) = struct.unpack_from("<I", header, at)
        name, _, value = header[at + 4:at + 4 + n].partition(b"=")
        out[name.decode("latin-1")] = value
        at += 4 + n
    return out


def sqlite_message_problem(path: Path, limit: int) -> str | None:
    """The first message of the ROS 2 sqlite3 database ``path`` larger than ``limit`` bytes, in one
    line; None when every one is within it or the file is no such database. SQLite gives a blob's
    length from its record header, without reading the blob."""
    import sqlite3

    try:
        con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    except sqlite3.Error:
        return None
    try:
        row = con.execute("SELECT id, length(data) FROM messages WHERE length(data) > ? LIMIT 1", (limit,)).fetchone()
    except sqlite3.Error:
        return None  # not a rosbag2 database: the reader says so
    finally:
        con.close()
    if row is None:
        return None
    return f"its message {row[0]} is {_size(row[1])}, over the {_size(limit)} a message may hold; not read"


def bound_ros1_inflation(limit: int) -> None:
    """Make rosbags inflate a ROS 1 chunk (bz2, lz4) no further than ``limit`` bytes and a byte: a
    chunk that declares a small size and inflates past it cannot fill memory."""
    try:
        import rosbags.rosbag1.reader as ros1
    except ImportError:
        return
    table = getattr(ros1, "decompressors", None)
    if not isinstance(table, dict):
        return

    def too_far() -> TooLarge:
        return TooLarge(f"a chunk inflates past the {_size(limit)} a chunk may hold (a decompression bomb?); "
                          "not inflated further")

    def inflate_bz2(data: bytes) -> bytes:
        import bz2

        out = bz2.BZ2Decompressor().decompress(data, max_length=limit + 1)
        if len(out) > limit:
            raise too_far()
        return out

    table["bz2"] = inflate_bz2
    try:
        from lz4.frame import LZ4FrameDecompressor
    except ImportError:
        return

    def inflate_lz4(data: bytes) -> bytes:
        out = LZ4FrameDecompressor().decompress(data, max_length=limit + 1)
        if len(out) > limit:
            raise too_far()
        return out

    table["lz4"] = inflate_lz4
