"""Chunk checksums (format 1.2, issue 52): one flipped bit anywhere in a stored chunk is caught.

Before 1.2 a bit flipped in an image chunk read silently at 26 of 40 offsets and ``validate``
called the store valid. Each array now ends its codec chain with zarr's crc32c codec; readers and
``validate`` refuse a chunk that fails it with one line naming the store, the array and the chunk.
Stores of format 1.0 and 1.1, without checksums, still read and validate.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from sonarset.cli.app import app
from sonarset.errors import FormatError
from sonarset.format.attrs import FORMAT_VERSION
from sonarset.store.store import create_store, open_store
from sonarset.store.validate import validate_store
from tests.conftest import TINY, make_run
from sonarset.testing import strip_checksums

CHUNK = Path("test_000") / "images" / "c" / "1" / "0" / "0"


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("checksums") / "s.zarr"
    s = create_store(path, TINY)
    s.write_run("run_000", **make_run(12, 0), chunk_frames=4)
    s.write_run("test_000", **make_run(12, 1), split="test", chunk_frames=4)
    return path


@pytest.fixture
def copy(base, tmp_path) -> Path:
    shutil.copytree(base, tmp_path / "s.zarr")
    return tmp_path / "s.zarr"


def _flip(path: Path, offset: int, bit: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 1 << bit
    path.write_bytes(bytes(data))


def _read_all(location: Path) -> None:
    store = open_store(location, check=True)
    for name in store.runs():
        store.run(name).load()


def test_new_stores_checksum_every_array(base):
    assert FORMAT_VERSION == "1.2"
    assert json.loads((base / "zarr.json").read_text())["attributes"]["sonarset"]["format_version"] == "1.2"
    for meta in base.glob("*/*/zarr.json"):
        codecs = json.loads(meta.read_text())["codecs"]
        assert codecs[-1] == {"name": "crc32c"}, (meta, codecs)
    assert validate_store(base) == []


def test_every_bit_flip_is_caught(copy):
    """Flips at 48 offsets spread over an image chunk (the blosc header, the payload, the checksum
    itself): every one fails ``validate`` and the read, naming the run, the array and the chunk."""
    chunk = copy / CHUNK
    size = chunk.stat().st_size
    offsets = sorted(set(np.linspace(0, size - 1, 48).round().astype(int)) | {0, 4, 8, 12, 15, size - 4, size - 1})
    missed = []
    for i, offset in enumerate(offsets):
        _flip(chunk, offset, i % 8)
        problems = [str(p) for p in validate_store(copy)]
        try:
            _read_all(copy)
            read = None
        except FormatError as exc:
            read = str(exc)
        _flip(chunk, offset, i % 8)  # restored
        found = [p for p in problems if "test_000/images: chunk c/1/0/0" in p and "checksum mismatch" in p]
        said = read is not None and read.startswith(f"{copy}/test_000/images: chunk c/1/0/0") and \
            "checksum mismatch" in read and "\n" not in read
        if not (found and said):
            missed.append((offset, problems, read))
    assert not missed, missed
    assert validate_store(copy) == []  # every flip undone: intact again


def test_cli_says_checksum_mismatch_in_one_line(copy, tmp_path):
    _flip(copy / CHUNK, 100, 3)
    runner = CliRunner()
    r = runner.invoke(app, ["validate", str(copy)])
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    lines = [line for line in r.output.splitlines() if line.startswith("invalid:")]
    assert len(lines) == 1 and "test_000/images: chunk c/1/0/0 is corrupt or truncated: checksum mismatch" in lines[0]
    r = runner.invoke(app, ["eval", str(copy), "--models", "persistence", "--samples", "5", "--horizons", "1",
                            "--out", str(tmp_path / "eval"), "--no-figures"])
    errors = [line for line in r.output.splitlines() if line.startswith("error:")]
    assert r.exit_code != 0 and "Traceback" not in r.output and len(errors) == 1, r.output
    assert f"{copy}/test_000/images: chunk c/1/0/0" in errors[0] and "checksum mismatch" in errors[0]
    # the quick pass reads no chunk, so it cannot see the flip
    assert runner.invoke(app, ["validate", str(copy), "--quick"]).exit_code == 0


def test_truncated_checksummed_chunk_says_both(copy):
    chunk = copy / CHUNK
    chunk.write_bytes(chunk.read_bytes()[:-10])
    problems = [str(p) for p in validate_store(copy)]
    assert any("chunk c/1/0/0 is corrupt or truncated: its blosc header declares" in p and "with its checksum" in p
               and p.endswith("; checksum mismatch") for p in problems), problems


@pytest.mark.parametrize("version", ["1.0", "1.1"])
def test_older_stores_without_checksums_stay_valid(copy, version):
    strip_checksums(copy, version)
    assert json.loads((copy / "test_000" / "images" / "zarr.json").read_text())["codecs"][-1]["name"] != "crc32c"
    assert validate_store(copy) == []
    _read_all(copy)
    # a run added by this writer is checksummed; the store keeps its version and stays valid
    store = open_store(copy, "r+")
    store.write_run("run_001", **make_run(8, 5), chunk_frames=4)
    assert open_store(copy).format_version == version and validate_store(copy) == []


def test_a_1_2_store_without_checksums_is_invalid_but_reads(copy):
    strip_checksums(copy, "1.2")
    problems = validate_store(copy)
    assert problems and all(not p.refused_by_readers for p in problems)
    assert any("test_000/images: chunks carry no crc32c checksum: format 1.2 requires" in str(p) for p in problems)
    _read_all(copy)
