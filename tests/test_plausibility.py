"""Plausibility: unit mistakes and impossible values are refused by import and validate, named,
and let through only with --allow-implausible."""

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from sonarset import open_store
from sonarset.cli.app import app
from sonarset.errors import InputValidationError
from sonarset.ingest.images import import_recording, load_recording
from sonarset.format.plausibility import Implausible, command_problems, grid_problems, time_problems
from sonarset.format.problems import Problem
from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.store.store import create_store
from sonarset.store.validate import validate_store
from tests.conftest import TINY, make_run


def recording(tmp_path, meta, name="rec", **changes):
    a = make_run(20, 3)
    a.update(changes)
    if "grid" not in meta:
        a["range"], a["azimuth"] = TINY.range_centres(), TINY.azimuth_centres()
    src = tmp_path / f"{name}.npz"
    np.savez(src, **a)
    src.with_suffix(".json").write_text(json.dumps(meta))
    return src


def problems_of(src, **kw) -> str:
    with pytest.raises(InputValidationError) as e:
        load_recording(src, **kw)
    return "\n".join(e.value.problems)


def cli(*args):
    return CliRunner().invoke(app, [*map(str, args)])


# ---- import: each rule names the likely unit mistake ------------------------------------------

def test_range_in_metres_declared_as_millimetres(tmp_path):
    grid = {"range_min": 0.5, "range_max": 5.0, "n_range": 8, "azimuth_min": -1.2, "azimuth_max": 1.2, "n_azimuth": 6}
    src = recording(tmp_path, {"grid": grid, "units": {"range": "mm"}})
    text = problems_of(src)
    assert "grid: range 0.0005-0.005 m is implausible" in text
    assert "metres declared as millimetres? (set units.range to 'm')" in text


def test_azimuth_in_radians_declared_as_degrees(tmp_path):
    grid = {"range_min": 0.5, "range_max": 2.5, "n_range": 8, "azimuth_min": -1.57, "azimuth_max": 1.57, "n_azimuth": 6}
    text = problems_of(recording(tmp_path, {"grid": grid, "units": {"azimuth": "deg"}}))
    assert "azimuth spans only -1.57..1.57 deg" in text and "radians declared as degrees?" in text


def test_times_in_milliseconds_declared_as_seconds(tmp_path):
    src = recording(tmp_path, {}, time=np.arange(20) * 200.0)
    text = problems_of(src)
    assert "frames are 200 s apart" in text and "milliseconds declared as seconds? (set units.time to 'ms')" in text
    # declared correctly, it imports
    src = recording(tmp_path, {"units": {"time": "ms"}}, name="ok", time=np.arange(20) * 200.0)
    run = import_recording(src, tmp_path / "s.zarr")
    assert open_store(tmp_path / "s.zarr").attrs.frame_rate_hz == 5.0 and run.n_frames == 20


def test_time_spacing_against_the_store_frame_rate(tmp_path):
    out = tmp_path / "s.zarr"
    import_recording(recording(tmp_path, {}, name="five"), out)
    assert open_store(out).attrs.frame_rate_hz == 5.0
    ten = recording(tmp_path, {}, name="ten", time=np.arange(20) * 0.1)
    with pytest.raises(InputValidationError, match="0.1 s apart .* store declares 0.2 s .* the times say 10 Hz"):
        import_recording(ten, out)
    # A frame-rate disagreement is not waved through: readers would refuse the run.
    with pytest.raises(InputValidationError, match="the times say 10 Hz"):
        import_recording(ten, out, allow_implausible=True)
    # Within the tolerance (jitter) it imports.
    jitter = np.arange(20) * 0.2 + np.random.default_rng(0).uniform(-0.004, 0.004, 20)
    import_recording(recording(tmp_path, {}, name="jitter", time=jitter), out)
    assert validate_store(out) == []


def test_new_store_takes_its_frame_rate_from_the_rig_or_the_times(tmp_path):
    ten = recording(tmp_path, {}, name="ten", time=np.arange(20) * 0.1)
    import_recording(ten, tmp_path / "a.zarr")
    assert open_store(tmp_path / "a.zarr").attrs.frame_rate_hz == 10.0
    assert validate_store(tmp_path / "a.zarr") == []
    rigged = recording(tmp_path, {"rig": {"frame_interval_s": 0.1}}, name="rigged", time=np.arange(20) * 0.1)
    import_recording(rigged, tmp_path / "b.zarr")
    store = open_store(tmp_path / "b.zarr")
    assert store.attrs.frame_rate_hz == 10.0 and store.rig.frame_interval_s == 0.1
    assert validate_store(tmp_path / "b.zarr") == []
    with pytest.raises(InputValidationError, match="sidecar's rig declares 0.2 s"):
        load_recording(recording(tmp_path, {"rig": {"frame_interval_s": 0.2}}, name="c", time=np.arange(20) * 0.1))


def test_commands_beyond_the_rig_limits(tmp_path):
    rig = {"rig": {"v_max_m_s": 0.3, "omega_max_rad_s": 1.0}}
    v = make_run(20, 3)["velocity"]
    cm = v * [100, 1]
    text = problems_of(recording(tmp_path, rig, name="cm", velocity=cm))
    # beyond any robot too: said once, as the error no flag lets through, with the unit's hint
    assert "linear speed up to" in text and "exceeds 10 m/s, beyond any ground robot" in text
    assert "the rig's limit" not in text and "allow" not in text
    assert "cm/s declared as m/s? (set units.linear_velocity to 'cm/s')" in text
    deg = v * [1, 180 / math.pi]
    assert "deg/s declared as rad/s?" in problems_of(recording(tmp_path, rig, name="deg", velocity=deg))
    # The tolerance: 20% over the limit passes, 60% over does not, and no unit explains it.
    over = v.copy()
    over[5] = [0.36, 1.2]
    load_recording(recording(tmp_path, rig, name="within", velocity=over))
    over[5] = [0.48, 0.0]
    text = problems_of(recording(tmp_path, rig, name="beyond", velocity=over))
    assert "up to 0.48 m/s" in text and "check the units, or the rig's v_max_m_s" in text


def test_velocity_of_1e30(tmp_path):
    v = make_run(20, 3)["velocity"]
    v[4, 0] = 1e30
    text = problems_of(recording(tmp_path, {}, velocity=v))
    assert "1e+30 m/s exceeds 10 m/s, beyond any ground robot: no unit mistake explains it" in text


def test_embedded_metadata_conflicting_with_the_sidecar_is_named(tmp_path):
    a = make_run(20, 3)
    a["range"], a["azimuth"] = TINY.range_centres(), TINY.azimuth_centres()
    src = tmp_path / "rec.npz"
    np.savez(src, metadata=np.array(json.dumps({"units": {"time": "ms"}, "name": "lab7", "split": "val"})),
             **{**a, "time": np.arange(20) * 200.0})
    src.with_suffix(".json").write_text(json.dumps({"units": {"time": "s"}, "split": "val"}))
    text = problems_of(src)
    assert "metadata: units.time is 's' in rec.json but 'ms' in the metadata embedded in rec.npz" in text
    # Keys only one of them sets are merged; equal keys are no conflict.
    src.with_suffix(".json").write_text(json.dumps({"split": "val"}))
    rec = load_recording(src)
    assert (rec.meta.name, rec.meta.split, rec.meta.units.time) == ("lab7", "val", "ms")


def test_allow_implausible_imports_with_warnings(tmp_path):
    grid = {"range_min": 0.5, "range_max": 5.0, "n_range": 8, "azimuth_min": -1.2, "azimuth_max": 1.2, "n_azimuth": 6}
    src = recording(tmp_path, {"grid": grid, "units": {"range": "mm"}})
    res = cli("import", src, tmp_path / "s.zarr")
    assert res.exit_code == 1 and "--allow-implausible" in res.output
    assert not (tmp_path / "s.zarr").exists()
    res = cli("import", src, tmp_path / "s.zarr", "--allow-implausible")
    assert res.exit_code == 0, res.output
    assert "warning:" in res.output and "metres declared as millimetres?" in res.output
    assert open_store(tmp_path / "s.zarr").run("rec").n_frames == 20


# ---- validate ------------------------------------------------------------------------------------

def test_validate_reports_implausible_values_and_allows_them_on_request(tmp_path):
    store = create_store(tmp_path / "s.zarr", TINY, rig=RobotRig())
    store.write_run("ok", **make_run(20, 1))
    bad = make_run(20, 2)
    bad["velocity"][7, 0] = 3.0  # 10x the rig's limit, within what a ground robot could do: readable
    store.write_run("bad", **bad)
    problems = validate_store(tmp_path / "s.zarr")
    assert [type(p) for p in problems] == [Implausible]
    assert problems[0].where.endswith("s.zarr/bad/velocity") and "3 m/s" in problems[0].message
    res = cli("validate", tmp_path / "s.zarr")
    assert res.exit_code == 1 and "implausible:" in res.output and "bad/velocity" in res.output
    res = cli("validate", tmp_path / "s.zarr", "--allow-implausible")
    assert res.exit_code == 0 and "warning:" in res.output and "1 implausible value(s) allowed" in res.output
    assert validate_store(tmp_path / "s.zarr", plausibility=False) == []


def test_commands_beyond_the_rig_are_flagged_but_readable_those_beyond_any_robot_are_not(tmp_path):
    """--allow-implausible is a user's word: a run it let in stays readable by eval and train. Commands
    no ground robot could follow are corrupt, and no reader uses them."""
    from sonarset import FormatError

    store = create_store(tmp_path / "s.zarr", TINY, rig=RobotRig(v_max_m_s=0.3))
    fast = make_run(20, 1)
    fast["velocity"][3, 0] = 0.9  # 3x the declared limit
    store.write_run("fast", **fast)
    absurd = make_run(20, 2)
    absurd["velocity"][3, 0] = 50.0  # 180 km/h
    store.write_run("absurd", **absurd)
    problems = validate_store(tmp_path / "s.zarr")
    flagged = {p.where.split("/")[-2] for p in problems}
    assert flagged == {"fast", "absurd"}
    # what readers refuse, validate reports as invalid, not as implausible (--allow-implausible keeps it out)
    assert {p.where.split("/")[-2]: type(p) for p in problems} == {"fast": Implausible, "absurd": Problem}
    store = open_store(tmp_path / "s.zarr")
    np.testing.assert_array_equal(store.run("fast").read("velocity"), fast["velocity"])
    with pytest.raises(FormatError, match="absurd.*50 m/s exceeds 10 m/s, beyond any ground robot"):
        store.run("absurd").read("velocity")


def test_validate_checks_the_grid(tmp_path):
    grid = SensorGrid(range_min_m=0.0005, range_max_m=0.005, n_range=8, azimuth_min_rad=-1.2,
                      azimuth_max_rad=1.2, n_azimuth=6)
    store = create_store(tmp_path / "s.zarr", grid)
    store.write_run("r", **make_run(10, 1, grid=grid))
    [p] = validate_store(tmp_path / "s.zarr", check_data=False)
    assert isinstance(p, Implausible) and "metres converted as millimetres?" in p.message


# ---- the rules themselves ------------------------------------------------------------------------

def test_rules_accept_what_a_real_robot_records():
    assert grid_problems(SensorGrid.default()) == []
    assert grid_problems(TINY) == []
    v = np.c_[np.linspace(-0.3, 0.3, 50), np.linspace(-1, 1, 50)]
    assert command_problems(v, RobotRig()) == [] and command_problems(v, None) == []
    assert time_problems(np.arange(50) * 0.2, 0.2, 5.0) == [] and time_problems(np.arange(50) * 0.2, None, 5.0) == []
    # Frames faster than an echo returns from the grid's end: seconds declared as milliseconds.
    [problem] = time_problems(np.arange(50) * 0.2e-3, None, 5.0)
    line = str(problem)
    assert "less than an echo from 5 m takes to return" in line and "seconds converted as milliseconds?" in line


def test_stored_commands_are_judged_in_bounded_blocks(monkeypatch):
    """``validate`` reads a run's commands a block of whole chunks at a time, and judges them as
    the whole array: a peak in any block, a block of only NaN, or none, change nothing."""
    import zarr

    from sonarset.format import plausibility

    v = np.c_[np.linspace(-0.3, 0.3, 50), np.linspace(-1, 1, 50)].astype(np.float32)
    v[13, 0], v[41, 1] = 3.0, np.inf  # a peak in the second block, an infinite turn rate in the last
    v[24:32] = np.nan  # a whole block of NaN
    arr = zarr.create_array(store={}, shape=v.shape, chunks=(4, 2), dtype="float32", fill_value=np.nan)
    arr[:] = v
    seen = []
    real = plausibility.command_peaks
    monkeypatch.setattr(plausibility, "STREAM_ROWS", 9)  # blocks of 8 rows: two chunks
    monkeypatch.setattr(plausibility, "command_peaks", lambda block: seen.append(len(block)) or real(block))
    assert plausibility._streamed_peaks(arr) == real(v) == (3.0, 1.0)
    assert seen == [8] * 6 + [2]
    assert plausibility.peak_problems(real(v), RobotRig()) == command_problems(v, RobotRig())
    [problem] = command_problems(v, RobotRig())  # the infinite turn rate is the format's to refuse
    assert str(problem).startswith("velocity: linear speed up to 3 m/s exceeds the rig's limit 0.3 m/s")
