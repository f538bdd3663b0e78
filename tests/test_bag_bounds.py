"""ROS 1 bags and ROS 2 sqlite3 bags under the size limit MCAP chunks have (issue 52): a chunk or
message declared over it is refused in one line before anything is inflated or decoded, and a
ROS 1 chunk that lies about its size is inflated no further than the limit."""

from __future__ import annotations

import struct

import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2.writer")

from sonarset.cli.app import app  # noqa: E402
from tests.bag_drives import Drive, write_bag  # noqa: E402


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
