"""ROS 1 bags and ROS 2 sqlite3 bags under the size limit MCAP chunks have (issue 52): a chunk or
message declared over it is refused in one line before anything is inflated or decoded, and a
ROS 1 chunk that lies about its size is inflated no further than the limit."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2.writer")

from sonarset.cli.app import app  # noqa: E402
from tests.test_bag import Drive  # noqa: E402


def write_bag(drive: Drive, path, kind: str, compression=None):
    """``drive`` as a ROS 1 bag or a ROS 2 sqlite3 bag, by rosbags' writers."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from sonarset.ingest.bag.messages import shipped_types

    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    store.register(shipped_types())
    T = store.types
    writer = Writer1(path) if kind == "ros1" else Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3)
    if compression is not None:
        writer.set_compression(getattr(Writer1.CompressionFormat, compression))
    serialize = store.serialize_ros1 if kind == "ros1" else store.serialize_cdr

    def header(t):
        kw = {"stamp": T["builtin_interfaces/msg/Time"](sec=int(t // 10**9), nanosec=int(t % 10**9)), "frame_id": "x"}
        return T["std_msgs/msg/Header"](seq=0, **kw) if kind == "ros1" else T["std_msgs/msg/Header"](**kw)

    vec = T["geometry_msgs/msg/Vector3"]
    az = drive.grid.azimuth_centres()
    with writer as w:
        ci = w.add_connection("/sonar", "marine_acoustic_msgs/msg/ProjectedSonarImage", typestore=store)
        cc = w.add_connection("/cmd", "geometry_msgs/msg/TwistStamped", typestore=store)
        for k, t in enumerate(drive.frame_ns):
            msg = T["marine_acoustic_msgs/msg/ProjectedSonarImage"](
                header=header(t), ping_info=T["marine_acoustic_msgs/msg/PingInfo"](
                    frequency=0.0, sound_speed=343.0, tx_beamwidths=np.zeros(0, np.float32),
                    rx_beamwidths=np.zeros(0, np.float32)),
                beam_directions=[vec(x=0.0, y=-math.sin(a), z=math.cos(a)) for a in az],
                ranges=drive.grid.range_centres().astype(np.float32),
                image=T["marine_acoustic_msgs/msg/SonarImageData"](is_bigendian=False, dtype=0, beam_count=len(az),
                                                                   data=drive.images[k].ravel()))
            w.write(ci, int(t), serialize(msg, ci.msgtype))
        for t, v, om in zip(drive.command_ns, drive.v, drive.w):
            msg = T["geometry_msgs/msg/TwistStamped"](header=header(t), twist=T["geometry_msgs/msg/Twist"](
                linear=vec(x=v, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=om)))
            w.write(cc, int(t), serialize(msg, cc.msgtype))
    return path


def _one_line_refusal(tmp_path, bag, says: str) -> str:
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr")])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 1 and len(lines) == 1 and "Traceback" not in res.output, res.output
    assert lines[0].startswith("error: ") and says in lines[0], lines[0]
    assert not (tmp_path / "s.zarr").exists()
    return lines[0]


@pytest.mark.parametrize("compression", [None, "BZ2", "LZ4"])
def test_a_ros1_chunk_declared_over_the_limit_is_refused_in_one_line(tmp_path, monkeypatch, compression):
    import sonarset.ingest.bag.reader as reader

    bag = write_bag(Drive(n_frames=10), tmp_path / "d.bag", "ros1", compression)
    monkeypatch.setattr(reader, "MAX_CHUNK_BYTES", 1000)
    line = _one_line_refusal(tmp_path, bag, "uncompressed, over the 1,000 bytes a chunk may hold")
    assert f"{bag}: its chunk at byte " in line


def test_a_ros1_chunk_lying_about_its_size_is_inflated_no_further_than_the_limit(tmp_path, monkeypatch):
    import sonarset.ingest.bag.reader as reader

    bag = write_bag(Drive(n_frames=10), tmp_path / "d.bag", "ros1", "BZ2")
    data = bytearray(bag.read_bytes())
    at = data.find(b"size=")  # the chunk header's uncompressed size: said to be 10 bytes
    while at >= 0:
        data[at + 5:at + 9] = struct.pack("<I", 10)
        at = data.find(b"size=", at + 9)
    bag.write_bytes(bytes(data))
    monkeypatch.setattr(reader, "MAX_CHUNK_BYTES", 1000)
    _one_line_refusal(tmp_path, bag, "a chunk inflates past the 1,000 bytes a chunk may hold")


def test_a_ros1_bag_within_the_limit_imports_with_bz2_chunks(tmp_path):
    drive = Drive(n_frames=10)
    res = CliRunner().invoke(app, ["import-bag", str(write_bag(drive, tmp_path / "d.bag", "ros1", "BZ2")),
                                   str(tmp_path / "s.zarr")])
    assert res.exit_code == 0, res.output


def test_a_sqlite3_message_over_the_limit_is_refused_in_one_line(tmp_path, monkeypatch):
    import sonarset.ingest.bag.reader as reader

    bag = write_bag(Drive(n_frames=10), tmp_path / "d", "sqlite3")
    monkeypatch.setattr(reader, "MAX_CHUNK_BYTES", 300)
    line = _one_line_refusal(tmp_path, bag, "bytes, over the 300 bytes a message may hold; not read")
    assert line.startswith(f"error: {bag / 'd.db3'}: its message 1 is ")
