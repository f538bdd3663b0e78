import json

import os

import numpy as np
import pytest

from sonarset import FormatError, SonarSetError, create_store, open_store
from sonarset.errors import InputValidationError
from sonarset.format.attrs import SensorGrid
from tests.conftest import TINY, make_run


@pytest.mark.parametrize("dtype", ["float16", "float32"])
def test_round_trip_is_bit_identical(tmp_path, dtype):
    s = create_store(tmp_path / "s.zarr", TINY)
    data = make_run(37, 3, dtype)
    rng = np.random.default_rng(9)
    extra = {"pose": rng.normal(size=(37, 3)), "snr_db": rng.normal(5, 1, 37).astype(np.float32),
             "slip": rng.uniform(0.5, 1, (37, 2)).astype(np.float32)}
    s.write_run("run_000", **data, **extra, chunk_frames=8)
    run = open_store(tmp_path / "s.zarr").run("run_000")
    got = run.load()
    assert got.images.dtype == np.dtype(dtype)
    assert got.images.tobytes() == data["images"].tobytes()
    assert got.velocity.tobytes() == data["velocity"].tobytes()
    assert got.time.tobytes() == data["time"].tobytes()
    for k, v in extra.items():
        assert getattr(got, k).tobytes() == v.tobytes()
    # lazy partial read
    assert np.array_equal(run.images[10:13], data["images"][10:13])


def test_xarray_opens_a_run_with_named_dims(store):
    xr = pytest.importorskip("xarray")
    ds = store.run("run_000").to_xarray()
    assert ds["images"].dims == ("time", "range", "azimuth")
    assert ds["velocity"].dims == ("time", "velocity_component")
    np.testing.assert_allclose(ds["range"].values, TINY.range_centres())
    np.testing.assert_allclose(ds["azimuth"].values, TINY.azimuth_centres())
    # and plain xarray, knowing nothing of sonarset
    ds2 = xr.open_zarr(store.location, group="test_000", consolidated=False)
    assert ds2.sizes == {"time": 20, "range": 8, "azimuth": 6, "velocity_component": 2}


def test_runs_listing_splits_and_info(store):
    s = open_store(store.location)
    assert s.runs() == ["run_000", "run_001", "test_000"]
    assert s.runs("test") == ["test_000"]
    assert s.splits() == {"train": ["run_000", "run_001"], "test": ["test_000"]}
    assert s.n_frames() == 75 and s.grid == TINY


def test_incomplete_run_is_invisible_and_replaced(store):
    w = store.run_writer("run_002", 10)
    w.write(0, **make_run(10, 4, "float16"))
    # writer "killed" before commit: readers do not see it
    assert "run_002" not in open_store(store.location).runs()
    assert "run_002" in store.runs(include_incomplete=True)
    with pytest.raises(FormatError, match="incomplete"):
        store.run("run_002")
    # the next writer of that name replaces it without needing overwrite
    store.write_run("run_002", **make_run(10, 5))
    assert "run_002" in open_store(store.location).runs()


def test_writer_exception_removes_half_written_group(store):
    with pytest.raises(RuntimeError):
        with store.run_writer("run_009", 10) as w:
            w.write(0, **make_run(10, 4, "float16"))
            raise RuntimeError("boom")
    assert "run_009" not in store.runs(include_incomplete=True)


def test_commit_refuses_unwritten_frames(store):
    w = store.run_writer("run_010", 10)
    blk = make_run(5, 1, "float16")
    w.write(0, **blk)
    with pytest.raises(SonarSetError, match="frame 5 was never written"):
        w.commit()


def test_commit_verifies_storage_before_the_complete_flag(store):
    """A writer whose array vanished under it (another writer deleted the run) is not flagged complete."""
    import shutil

    w = store.run_writer("run_011", 10)
    w.write(0, **make_run(10, 4, "float16"))
    shutil.rmtree(os.path.join(store.location, "run_011", "images"))
    with pytest.raises(FormatError, match="run_011.*images"):
        w.commit()
    assert "run_011" not in open_store(store.location).runs()


def test_a_run_replaced_while_open_is_refused_not_mixed(store):
    """import --overwrite swaps a new run folder in; a reader holding the old run gets a clean error
    on its next read, never the new velocities beside the old images."""
    from sonarset.ingest.target import move_run_in

    reader = open_store(store.location).run("run_000")
    reader.read("images")
    move_run_in(open_store(store.location, "r+"), "run_000",
                lambda side: side.write_run("run_000", **make_run(30, 9), chunk_frames=8))
    with pytest.raises(FormatError, match="run_000: run changed while reading"):
        reader.read("velocity")
    again = open_store(store.location).run("run_000")  # opened again: the new run, whole
    np.testing.assert_array_equal(again.read("velocity"), make_run(30, 9)["velocity"])


def test_existing_run_needs_overwrite(store):
    with pytest.raises(SonarSetError, match="already exists"):
        store.write_run("run_000", **make_run(5, 1))
    store.write_run("run_000", **make_run(5, 1), overwrite=True)
    assert store.run("run_000").n_frames == 5


def test_write_run_validates_before_writing(store):
    bad = make_run(10, 1)
    bad["images"][3, 0, 0] = np.nan
    bad["velocity"] = bad["velocity"][:9]
    bad["time"][5] = 0.0
    with pytest.raises(InputValidationError) as e:
        store.write_run("run_bad", **bad)
    text = "\n".join(e.value.problems)
    assert "images: NaN or infinite values" in text and "velocity: 9 frames but images has 10" in text
    assert "not strictly increasing" in text
    assert "run_bad" not in store.runs(include_incomplete=True)


def test_grid_mismatch_refused(store):
    with pytest.raises(InputValidationError, match="does not match the grid"):
        store.write_run("x", **make_run(5, grid=SensorGrid.default()))


def test_create_refuses_existing_and_readonly(store, tmp_path):
    with pytest.raises(SonarSetError, match="already exists"):
        create_store(store.location, TINY)
    ro = open_store(store.location)
    with pytest.raises(SonarSetError, match="read-only"):
        ro.write_run("x", **make_run(5))


def test_open_errors_are_specific(tmp_path):
    with pytest.raises(FormatError, match="no such file"):
        open_store(tmp_path / "nope.zarr")
    (tmp_path / "f.txt").write_text("x")
    with pytest.raises(FormatError, match="a file, not a directory"):
        open_store(tmp_path / "f.txt")


def test_unknown_major_version_is_refused_by_name(store):
    meta = json.loads(open(f"{store.location}/zarr.json").read())
    meta["attributes"]["sonarset"]["format_version"] = "3.1"
    meta.pop("consolidated_metadata")
    open(f"{store.location}/zarr.json", "w").write(json.dumps(meta))
    with pytest.raises(FormatError, match=r"version 3\.1 is not supported"):
        open_store(store.location)


def test_fsspec_memory_url_round_trip():
    url = "memory://sonarset-test/store.zarr"
    s = create_store(url, TINY)
    data = make_run(12, 7, "float16")
    s.write_run("run_000", **data)
    back = open_store(url).run("run_000").load()
    assert back.images.tobytes() == data["images"].tobytes()


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_unit_interval_bit_test_is_exact(dtype):
    from sonarset.format.arrays import in_unit_interval

    a = np.random.default_rng(0).random(1000).astype(dtype)
    a[:3] = (0.0, -0.0, 1.0)
    assert in_unit_interval(a)
    for bad in (np.nan, np.inf, -np.inf, -1e-3, 1.001, -1.0, np.finfo(dtype).tiny * -1):
        b = a.copy()
        b[500] = bad
        assert not in_unit_interval(b), bad


def test_consolidating_a_read_only_store_with_a_current_snapshot_is_nothing_to_do(store, monkeypatch):
    """generate with nothing to do and validate --consolidate succeed on a read-only store; a
    snapshot that needs rewriting still fails with the file system's error."""
    import errno

    import zarr

    from sonarset.store import root

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    store.consolidate()
    monkeypatch.setattr(root.zarr, "consolidate_metadata", read_only)
    open_store(store.location, "r+").consolidate()  # current: no write needed
    monkeypatch.undo()
    zarr.open_group(store.location, mode="r+").create_group("run_099")  # the snapshot lacks it now
    monkeypatch.setattr(root.zarr, "consolidate_metadata", read_only)
    with pytest.raises(OSError, match="Read-only"):
        open_store(store.location, "r+").consolidate()


def _store_of_runs(path, n: int):
    """``n`` copies of one 2-frame run, consolidated: reading costs per run, so copies will do."""
    import shutil

    import zarr

    create_store(path, TINY).write_run("run_000", **make_run(2))
    for i in range(1, n):
        shutil.copytree(path / "run_000", path / f"run_{i:03d}")
    zarr.consolidate_metadata(str(path))
    return path


@pytest.mark.parametrize("command", [["info"], ["validate"], ["validate", "--quick"]])
def test_reading_a_store_costs_the_same_for_each_run(tmp_path, monkeypatch, command):
    """Opening one run used to list every run group (zarr parses each one's metadata to list it),
    so ``info`` on 411 runs took 81 s: the files a command reads must grow with the runs, not
    with their square."""
    import zarr
    from typer.testing import CliRunner

    from sonarset.cli.app import app

    reads = []
    real_get = zarr.storage.LocalStore.get

    async def counted(self, *args, **kwargs):
        reads.append(1)
        return await real_get(self, *args, **kwargs)

    monkeypatch.setattr(zarr.storage.LocalStore, "get", counted)
    per_store = {}
    for n in (5, 20):
        store = _store_of_runs(tmp_path / f"s{n}.zarr", n)
        reads.clear()
        result = CliRunner().invoke(app, [*command, str(store)])
        assert result.exit_code == 0, result.output
        per_store[n] = len(reads)
    assert per_store[20] < 4.2 * per_store[5], per_store  # 4x the runs: under 4x the reads (linear)


def test_an_atomic_write_gets_a_plain_files_permissions(tmp_path):
    """safetensors creates its file 0600: a checkpoint others on the machine cannot read."""
    import os

    from safetensors.numpy import save_file

    from sonarset.store.atomic import atomic_write

    out = atomic_write(tmp_path / "w.safetensors", lambda p: save_file({"a": np.zeros(2)}, str(p)))
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask
