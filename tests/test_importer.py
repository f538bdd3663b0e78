import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from sonarset import SonarSetError, open_store
from sonarset.errors import InputValidationError
from sonarset.importer import import_recording, load_recording
from sonarset.validate import validate_store
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
    for expect in ("metadata.colour: Extra inputs", "unknown array 'bogus'", "images: contains NaN"):
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
