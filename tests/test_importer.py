import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from sonarset import SonarSetError, open_store
from sonarset.errors import InputValidationError
from sonarset.ingest.images import import_recording, load_recording
from sonarset.store.validate import validate_store
from tests.conftest import TINY, make_run


def write_npz(path, meta=None, **arrays):
    np.savez(path, **arrays)
    if meta is not None:
        path.with_suffix(".json").write_text(json.dumps(meta))
    return path


def good_arrays(T=12):
    d = make_run(T, 3)
    d["range"], d["azimuth"] = TINY.range_centres(), TINY.azimuth_centres()
    return d


def test_import_npz_into_new_store_and_validate(tmp_path):
    src = write_npz(tmp_path / "rec.npz", {"name": "lab1", "split": "test"}, **good_arrays())
    run = import_recording(src, tmp_path / "out.zarr")
    assert (run.name, run.split, run.n_frames) == ("lab1", "test", 12)
    assert validate_store(tmp_path / "out.zarr") == []
    np.testing.assert_array_equal(open_store(tmp_path / "out.zarr").run("lab1").images[:], good_arrays()["images"])


def test_import_directory_of_npy_with_units_and_alignment(tmp_path):
    d = tmp_path / "rec"
    d.mkdir()
    a = good_arrays(10)
    np.save(d / "images", (a["images"] * 60 - 60))  # dB re full scale
    np.save(d / "velocity", a["velocity"] * [100, 180 / np.pi])  # cm/s, deg/s
    np.save(d / "time", a["time"] * 1000)  # ms
    np.save(d / "pose", np.c_[np.arange(10) * 10.0, np.zeros(10), np.full(10, 90.0)])  # cm, deg
    grid = {"range_min": 50, "range_max": 250, "n_range": 8, "azimuth_min": -1.2 * 180 / np.pi,
            "azimuth_max": 1.2 * 180 / np.pi, "n_azimuth": 6}
    (d / "recording.json").write_text(json.dumps({
        "grid": grid, "image_encoding": "db", "velocity_alignment": "next",
        "units": {"range": "cm", "azimuth": "deg", "linear_velocity": "cm/s", "angular_velocity": "deg/s", "time": "ms"}}))
    run = import_recording(d, tmp_path / "out.zarr")
    got = run.load()
    assert got.n_frames == 9  # frame 0 dropped by the 'next' alignment
    np.testing.assert_allclose(got.images, a["images"][1:], atol=1e-5)
    np.testing.assert_allclose(got.velocity, a["velocity"][:-1], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got.time, a["time"][1:])
    np.testing.assert_allclose(got.pose[0], [0.1, 0, np.pi / 2])
    assert open_store(tmp_path / "out.zarr").grid.matches(TINY)


def test_import_appends_to_existing_store_and_refuses_other_grid(tmp_path, store):
    src = write_npz(tmp_path / "extra.npz", None, **good_arrays())
    import_recording(src, store.location)
    assert "extra" in open_store(store.location).runs()
    with pytest.raises(SonarSetError, match="already exists"):
        import_recording(src, store.location)
    other = good_arrays()
    other["range"] = other["range"] * 2
    src2 = write_npz(tmp_path / "other.npz", None, **other)
    with pytest.raises(SonarSetError, match="differs from the data"):
        import_recording(src2, store.location)


def test_every_problem_is_reported(tmp_path):
    a = good_arrays()
    a["velocity"] = a["velocity"][:-2]
    a["time"][4] = 0
    a["images"][0, 0, 0] = np.inf
    a["azimuth"] = np.degrees(a["azimuth"])
    a["bogus"] = np.zeros(3)
    src = write_npz(tmp_path / "bad.npz", {"units": {"range": "m"}, "colour": 1}, **a)
    with pytest.raises(InputValidationError) as e:
        load_recording(src)
    text = "\n".join(e.value.problems)
    for expect in ("metadata.colour: Extra inputs", "unknown array 'bogus'", "images: NaN or infinite values"):
        assert expect in text, text


def test_unit_hints(tmp_path):
    a = good_arrays()
    a["azimuth"] = np.degrees(a["azimuth"])
    a["velocity"] = a["velocity"] * [1, 60]
    src = write_npz(tmp_path / "deg.npz", {}, **a)
    with pytest.raises(InputValidationError) as e:
        load_recording(src)
    text = "\n".join(e.value.problems)
    assert "azimuth in degrees?" in text and "turn rate up to" in text


def test_not_an_npz(tmp_path):
    p = tmp_path / "x.npz"
    p.write_bytes(b"not a zip")
    with pytest.raises(InputValidationError, match="not a readable .npz"):
        load_recording(p)


# ---- property-based: malformed inputs never raise anything but InputValidationError/SonarSetError,
# and never leave a store behind -------------------------------------------------------------------

finite = st.one_of(st.floats(-1e3, 1e3, width=32), st.sampled_from([np.nan, np.inf, -np.inf, 1e30, -0.0]))
arrays = st.one_of(
    hnp.arrays(st.sampled_from([np.float32, np.float64, np.int16, np.uint8, np.bool_, np.complex64]),
               hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=9), elements=None),
    hnp.arrays(np.float64, hnp.array_shapes(min_dims=1, max_dims=3, min_side=1, max_side=9), elements=finite),
)
keys = st.sampled_from(["images", "velocity", "time", "range", "azimuth", "pose", "snr_db", "slip", "junk"])
metas = st.one_of(
    st.none(),
    st.just({"grid": {"range_min": 0.5, "range_max": 2.5, "n_range": 8, "azimuth_min": -1.2,
                      "azimuth_max": 1.2, "n_azimuth": 6}}),
    st.dictionaries(st.sampled_from(["name", "split", "units", "grid", "image_encoding", "velocity_alignment", "x"]),
                    st.one_of(st.text(max_size=5), st.integers(), st.none(), st.just({"range": "cm"})), max_size=4),
)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(contents=st.dictionaries(keys, arrays, max_size=6), meta=metas, base=st.booleans())
def test_malformed_inputs_fail_cleanly_and_write_nothing(tmp_path, contents, meta, base):
    work = tmp_path / f"case{os.urandom(4).hex()}"
    work.mkdir()
    arrs = dict(good_arrays(6)) if base else {}
    arrs.update(contents)
    src = work / "rec.npz"
    np.savez(src, **arrs)
    if meta is not None:
        src.with_suffix(".json").write_text(json.dumps(meta))
    out = work / "out.zarr"
    try:
        import_recording(src, out)
    except SonarSetError as exc:
        assert str(exc) and "\n" not in str(exc)
        assert not out.exists(), "a failed import left a store behind"
        assert [p.name for p in work.iterdir() if p.name.startswith(".")] == []
    else:
        assert validate_store(out) == []


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=300))
def test_garbage_bytes_fail_cleanly(tmp_path, data):
    src = tmp_path / "g.npz"
    src.write_bytes(data)
    with pytest.raises(SonarSetError):
        import_recording(src, tmp_path / "never.zarr")
    assert not (tmp_path / "never.zarr").exists()


# ---- files that are not files, bad options, absurd sidecars ------------------------------------

def _cli_import(*args):
    from typer.testing import CliRunner

    from sonarset.cli.app import app

    return CliRunner().invoke(app, ["import", *map(str, args)])


def _error_lines(res) -> list[str]:
    return [line for line in res.output.splitlines() if line.strip()]


def _load_in_thread(*args, **kwargs):
    """load_recording, given 10 s: a FIFO opened for reading would block it forever."""
    import threading

    box: dict = {}

    def target():
        try:
            box["value"] = load_recording(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - handed to the test thread
            box["error"] = exc

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(10)
    assert not t.is_alive(), "load_recording blocked"
    return box


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_fifo_as_file_is_refused_without_opening_it(tmp_path):
    src = tmp_path / "rec.npz"
    os.mkfifo(src)
    box = _load_in_thread(src)
    assert isinstance(box.get("error"), InputValidationError)
    assert "not a regular file (a FIFO" in str(box["error"])
    res = _cli_import(src, tmp_path / "out.zarr")
    assert res.exit_code == 1 and len(_error_lines(res)) == 1 and "rec.npz" in res.output
    assert not (tmp_path / "out.zarr").exists()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_fifo_inside_npy_directory_and_as_sidecar_are_refused(tmp_path):
    d = tmp_path / "rec"
    d.mkdir()
    for k, v in good_arrays().items():
        np.save(d / k, v)
    os.mkfifo(d / "pose.npy")
    os.mkfifo(d / "recording.json")
    box = _load_in_thread(d)
    text = "\n".join(box["error"].problems)
    assert "pose.npy: not a regular file (a FIFO" in text
    assert "recording.json: not a regular file (a FIFO" in text
    meta = tmp_path / "meta.json"
    os.mkfifo(meta)
    box = _load_in_thread(write_npz(tmp_path / "x.npz", None, **good_arrays()), meta)
    assert "meta.json: not a regular file" in str(box["error"])


def test_device_and_socket_are_refused(tmp_path):
    import socket

    dev = tmp_path / "zero.npz"
    dev.symlink_to("/dev/zero")
    with pytest.raises(InputValidationError, match="a character device"):
        load_recording(dev)
    sock_path = tmp_path / "s.npz"
    sock = socket.socket(socket.AF_UNIX)
    try:
        sock.bind(str(sock_path))
        with pytest.raises(InputValidationError, match="a socket"):
            load_recording(sock_path)
    finally:
        sock.close()


@pytest.mark.parametrize("args, match", [
    (["--split", "TRAIN"], "split 'TRAIN': split must be lower-case letters, digits"),
    (["--split", ""], "split '': split must be lower-case letters, digits"),
    (["--name", ""], "invalid run name '': a run name is 1-128 letters"),
    (["--name", "a/b"], "invalid run name 'a/b': a run name is 1-128 letters"),
])
def test_bad_cli_values_are_one_line(tmp_path, args, match):
    src = write_npz(tmp_path / "rec.npz", {}, **good_arrays())
    res = _cli_import(src, tmp_path / "out.zarr", *args)
    assert res.exit_code == 1, res.output
    lines = _error_lines(res)
    assert len(lines) == 1 and match in lines[0], lines
    assert not (tmp_path / "out.zarr").exists()


@pytest.mark.parametrize("text, match", [
    ('{"source": ' + "[" * 100_000 + "]" * 100_000 + "}", "nested too deeply"),
    ('{"source": ' + '{"a": ' * 40 + "1" + "}" * 40 + "}", "nested too deeply"),
    ('{"dynamic_range_db": NaN}', "NaN is not valid JSON"),
    ('{"dynamic_range_db": 1e999}', "out of range"),
    ('{"name": "' + "9" * 10 + '", "n": ' + "9" * 5000 + "}", "invalid JSON"),
])
def test_absurd_sidecars_are_one_line(tmp_path, text, match):
    src = write_npz(tmp_path / "rec.npz", None, **good_arrays())
    src.with_suffix(".json").write_text(text)
    res = _cli_import(src, tmp_path / "out.zarr")
    assert res.exit_code == 1, res.output
    lines = _error_lines(res)
    assert len(lines) == 1 and match in lines[0] and "rec.json" in lines[0], lines


def test_deep_embedded_metadata_and_huge_sidecar(tmp_path, monkeypatch):
    import sonarset.ingest.metadata as sidecar

    a = good_arrays()
    src = write_npz(tmp_path / "rec.npz", None, metadata=np.array("[" * 5000 + "]" * 5000), **a)
    with pytest.raises(InputValidationError, match="nested too deeply"):
        load_recording(src)
    src = write_npz(tmp_path / "big.npz", {"source": {"note": "x" * 300}}, **a)
    monkeypatch.setattr(sidecar, "MAX_METADATA_BYTES", 200)
    with pytest.raises(InputValidationError, match="more than a metadata file holds"):
        load_recording(src)
    # embedded in the .npz, the same cap: the metadata array is no way round it
    src = write_npz(tmp_path / "embedded.npz", None, metadata=np.array(json.dumps({"source": {"note": "x" * 300}})), **a)
    with pytest.raises(InputValidationError, match="array 'metadata'.*more than metadata holds"):
        load_recording(src)


# ---- replacing a run, and a full disk ----------------------------------------------------------

def _snapshot(root) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _count_writes(monkeypatch, fn) -> int:
    import zarr.storage._local as zlocal

    n = [0]
    orig = zlocal._put

    def put(path, value, exclusive=False):
        n[0] += 1
        return orig(path, value, exclusive)

    monkeypatch.setattr(zlocal, "_put", put)
    fn()
    monkeypatch.setattr(zlocal, "_put", orig)
    return n[0]


def _disk_full_at(monkeypatch, k: int) -> None:
    """The k-th file write fails as on a full disk, after creating its folder (as zarr's does);
    the writes running beside it (zarr writes chunks concurrently) still land, slowly."""
    import errno
    import time

    import zarr.storage._local as zlocal

    n = [0]
    orig = zlocal._put

    def put(path, value, exclusive=False):
        n[0] += 1
        if n[0] == k:
            path.parent.mkdir(parents=True, exist_ok=True)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        if n[0] > k:
            time.sleep(0.02)
        return orig(path, value, exclusive)

    monkeypatch.setattr(zlocal, "_put", put)


def test_overwrite_on_full_disk_keeps_the_old_run_at_every_write(tmp_path, monkeypatch):
    out = tmp_path / "s.zarr"
    old = write_npz(tmp_path / "old.npz", {"name": "X"}, **good_arrays(12))
    new_arrays = good_arrays(150)  # three image chunks, written concurrently
    new_arrays["images"] = new_arrays["images"][::-1].copy()
    new = write_npz(tmp_path / "new.npz", {}, **new_arrays)
    import_recording(old, out)
    before = _snapshot(out)
    scratch = tmp_path / "scratch.zarr"
    import_recording(old, scratch)
    total = _count_writes(monkeypatch, lambda: import_recording(new, scratch, name="X", overwrite=True))
    assert total >= 10
    for k in range(1, total + 1):
        _disk_full_at(monkeypatch, k)
        res = _cli_import(new, out, "--name", "X", "--overwrite")
        monkeypatch.undo()
        lines = _error_lines(res)
        assert res.exit_code == 1 and len(lines) == 1, (k, res.output)
        assert "no space left on device" in lines[0] and str(out) in lines[0], lines
        assert _snapshot(out) == before, f"write {k}: the store changed"
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == [], k
    run = import_recording(new, out, name="X", overwrite=True)
    assert run.n_frames == 150
    np.testing.assert_array_equal(open_store(out).run("X").images[:], new_arrays["images"])
    assert validate_store(out) == []


def test_overwrite_never_touches_the_old_run_before_the_swap(tmp_path, monkeypatch):
    """While the replacement is written, the old run's files stay exactly as they were."""
    import zarr.storage._local as zlocal

    out = tmp_path / "s.zarr"
    import_recording(write_npz(tmp_path / "old.npz", {"name": "X"}, **good_arrays(12)), out)
    old_run = _snapshot(out / "X")
    seen = []
    orig = zlocal._put

    def put(path, value, exclusive=False):
        seen.append(_snapshot(out / "X") == old_run)
        return orig(path, value, exclusive)

    monkeypatch.setattr(zlocal, "_put", put)
    import_recording(write_npz(tmp_path / "new.npz", {}, **good_arrays(20)), out, name="X", overwrite=True)
    monkeypatch.undo()
    assert len(seen) >= 10 and all(seen[:-1])  # the last write is the consolidation after the swap
    assert open_store(out).run("X").n_frames == 20


@pytest.mark.parametrize("existing", [False, True])
def test_full_disk_new_store_or_new_run_leaves_nothing(tmp_path, monkeypatch, existing):
    out = tmp_path / "s.zarr"
    if existing:
        import_recording(write_npz(tmp_path / "first.npz", {}, **good_arrays()), out)
    before = _snapshot(out) if existing else None
    src = write_npz(tmp_path / "rec.npz", {}, **good_arrays(150))
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    total = _count_writes(monkeypatch, lambda: import_recording(src, scratch / "x.zarr"))
    for k in range(1, total + 1, 2):
        _disk_full_at(monkeypatch, k)
        res = _cli_import(src, out)
        monkeypatch.undo()
        assert res.exit_code == 1 and len(_error_lines(res)) == 1, (k, res.output)
        assert "no space left on device" in res.output
        if existing:
            assert _snapshot(out) == before, k
            assert open_store(out).runs() == ["first"]
        else:
            assert not out.exists(), k
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == [], k


def test_overwrite_without_renameat2_swaps_with_two_renames(tmp_path, monkeypatch):
    import sonarset.store.atomic as atomic

    out = tmp_path / "s.zarr"
    import_recording(write_npz(tmp_path / "old.npz", {"name": "X"}, **good_arrays(12)), out)
    monkeypatch.setattr(atomic, "_renameat2_exchange", lambda a, b: False)
    new = good_arrays(15)
    import_recording(write_npz(tmp_path / "new.npz", {}, **new), out, name="X", overwrite=True)
    np.testing.assert_array_equal(open_store(out).run("X").images[:], new["images"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.json", "new.npz", "old.json", "old.npz", "s.zarr"]
    assert validate_store(out) == []
