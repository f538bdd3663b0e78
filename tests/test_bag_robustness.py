"""Bags that are long, killed, inflated, implausible or full of gaps: what import-bag keeps, splits
or refuses in one line (sonarset.ingest.bag)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2.writer")

from sonarset import open_store  # noqa: E402
from sonarset.cli.app import app  # noqa: E402
from sonarset.errors import InputValidationError  # noqa: E402
from sonarset.format.attrs import SensorGrid  # noqa: E402
from sonarset.ingest.bag import import_bag  # noqa: E402
from sonarset.store.validate import validate_store  # noqa: E402

from tests.bag_drives import BASE_NS, Drive, jittery_times  # noqa: E402


def test_a_jittery_drive_with_lost_pings_stays_one_run_in_one_line_validates_and_no_window_spans_a_gap(tmp_path):
    from sonarset.windows import RunLayout, WindowIndex

    t = jittery_times(300, seed=3)
    dt = np.diff(t)
    lost_at = int(np.sum(dt > 1.5 * np.median(dt)))
    bag = Drive(times_s=t).write(tmp_path / "drive.mcap")
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), "--name", "drive"])
    assert res.exit_code == 0, res.output
    [summary] = [ln for ln in res.output.splitlines() if "lost ping" in ln]  # one line, not one per gap
    assert f"at {lost_at} gap(s)" in summary and "1 run(s)" in summary, summary
    assert len([ln for ln in res.output.splitlines() if ln.strip()]) == 2, res.output  # the note, the result
    store = open_store(tmp_path / "s.zarr")
    assert validate_store(tmp_path / "s.zarr") == []
    interval = float(np.median(dt[dt < 1.5 * np.median(dt)]))
    assert abs(1 / store.attrs.frame_rate_hz - interval) < 0.01 * interval  # the median, gaps left out
    [run] = [store.run(n) for n in store.runs()]
    assert run.n_frames == 300  # every frame kept
    time = run.read("time")
    gaps = [k for k, _ in run.attrs.model_extra["gaps"]]
    assert gaps == (np.flatnonzero(np.diff(time) > 1.5 * interval) + 1).tolist() and len(gaps) == lost_at
    for n_in, horizon in ((3, 1), (3, 5)):
        index = WindowIndex.build(RunLayout.of(store), n_in, horizon)
        steps = np.diff(time[index.rows()], axis=1)
        assert steps.max() < 1.5 * interval  # no window spans a lost ping
        # and every window that does not span one is there
        span = n_in + horizon
        free = [i for i in range(300 - span + 1) if not any(i < k < i + span for k in gaps)]
        assert index.starts.tolist() == free


def test_a_run_whose_rate_strays_is_split_at_its_gaps_and_the_off_rate_stretch_dropped():
    from sonarset.ingest.bag.align import MAX_LOST, split_at_gaps

    steady = np.arange(40) * 0.14
    after = steady[-1] + (MAX_LOST + 2) * 0.14 + np.arange(6) * 0.14  # a long gap, then 6 steady frames,
    wobbly = after[-1] + 0.28 + np.arange(10) * 0.17  # a lost ping and 10 frames 0.17 s apart: 21 % slow
    segments, [note], interval = split_at_gaps(np.concatenate([steady, after, wobbly]))
    assert [(s.start, s.stop, s.gaps) for s in segments] == [(0, 40, ()), (40, 46, ())]
    assert abs(interval - 0.14) < 1e-9
    assert "10 frame(s) dropped in 1 stretch(es)" in note and "1 whose jitter" in note, note


def test_jitter_alone_records_no_gap_and_a_steady_drive_none():
    from sonarset.ingest.bag.align import split_at_gaps

    rng = np.random.default_rng(0)
    t = np.arange(500) / 7.1 + rng.normal(0, 0.05 / 7.1, 500)
    segments, notes, _ = split_at_gaps(np.sort(t))
    assert [(s.start, s.stop, s.gaps) for s in segments] == [(0, 500, ())] and notes == []


KILL_ON_SECOND_RUN = """
import os, signal, sys
from sonarset.ingest.bag import importer
write, calls = importer.ImageRunWriter.__call__, []
def dying(self, store, replace):
    calls.append(self.name)
    if len(calls) == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    write(self, store, replace)
importer.ImageRunWriter.__call__ = dying
from sonarset.cli.app import app
app(sys.argv[1:])
"""


@pytest.mark.parametrize("into", ["a new store", "an existing store"])
def test_an_import_of_several_runs_killed_midway_leaves_the_store_as_it_was_and_reruns(tmp_path, into):
    import subprocess
    import sys

    keep = np.ones(30, bool)
    keep[12:20] = False  # 8 pings lost in a row: two runs
    drive = Drive()
    drive.frame_ns, drive.images = drive.frame_ns[keep], drive.images[keep]
    bag = drive.write(tmp_path / "d.mcap")
    out = tmp_path / "s.zarr"
    if into == "an existing store":
        import_bag(Drive(n_frames=10).write(tmp_path / "first.mcap"), out, name="first")
    args = ["import-bag", str(bag), str(out), "--name", "j"]
    killed = subprocess.run([sys.executable, "-c", KILL_ON_SECOND_RUN, *args], capture_output=True, text=True)
    assert killed.returncode == -9, killed.stderr
    if into == "a new store":
        assert not out.exists()
    else:
        assert open_store(out).runs() == ["first"] and validate_store(out) == []
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert sorted(open_store(out).runs()) == sorted(["j_000", "j_001"] + (["first"] if into != "a new store" else []))
    assert validate_store(out) == []
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # the killed run's aside: gone


def with_zero_chunk(bag: Path, zeros: int, declared: int | None = None) -> Path:
    """``bag`` (an MCAP file) with one more chunk that inflates to ``zeros`` zero bytes and says it
    holds ``declared`` (default: the truth), its summary dropped so that a reader meets the chunk."""
    import struct

    from backports import zstd

    data = bag.read_bytes()
    at = 8
    while data[at] != 0x0F:  # up to DataEnd: header and chunks stay
        at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
    packer, block = zstd.ZstdCompressor(level=1), bytes(2**20)
    body = b"".join(packer.compress(block[:min(2**20, zeros - k)]) for k in range(0, zeros, 2**20))
    body += packer.flush()
    chunk = struct.pack("<QQQI", BASE_NS, BASE_NS, zeros if declared is None else declared, 0)
    chunk += struct.pack("<I", 4) + b"zstd" + struct.pack("<Q", len(body)) + body
    tail = struct.pack("<BQI", 0x0F, 4, 0) + struct.pack("<BQQQI", 0x02, 20, 0, 0, 0) + data[:8]
    bag.write_bytes(data[:at] + struct.pack("<BQ", 0x06, len(chunk)) + chunk + tail)
    return bag


@pytest.mark.parametrize("declared", ["truly", "lying"])
def test_a_chunk_that_inflates_too_far_is_refused_in_one_line(tmp_path, monkeypatch, declared):
    import sonarset.ingest.bag.reader as reader

    monkeypatch.setattr(reader, "MAX_CHUNK_BYTES", 2**20)
    bag = with_zero_chunk(Drive(n_frames=10).write(tmp_path / "d.mcap"), 2 * 2**20,
                          declared=None if declared == "truly" else 1000)
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr")])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 1 and len(lines) == 1 and "Traceback" not in res.output, res.output
    assert str(bag) in lines[0]
    # said before inflating; one that lies is inflated no further than it says (a byte more)
    assert ("declares 2 MiB uncompressed" if declared == "truly" else "got 1001") in lines[0], lines[0]
    assert not (tmp_path / "s.zarr").exists()


PEAKS_OF_IMPORTS = """
import sys, tracemalloc
from pathlib import Path
from sonarset.ingest.bag import import_bag
warm, *bags = map(Path, sys.argv[1:])
import_bag(warm, warm.with_suffix(".zarr"))  # lazy imports and first-call caches are not the drive's
tracemalloc.start()
for bag in bags:
    tracemalloc.reset_peak()
    import_bag(bag, bag.with_suffix(".zarr"))
    print(tracemalloc.get_traced_memory()[1])
"""


def test_a_long_drive_is_held_in_its_pixel_type_and_written_a_chunk_at_a_time(tmp_path):
    """Twice the drive costs its frames in their pixel type, not the drive again as float32: the
    difference of two peaks, because one peak moves by several MB between runs (the codec threads'
    timing), measured in a fresh interpreter (what earlier tests leave behind moves it too)."""
    from sonarset.ingest.bag.reader import read_streams

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=200, azimuth_min_rad=-1.5, azimuth_max_rad=1.5,
                      n_azimuth=90)
    short, long = Drive(n_frames=400, grid=grid), Drive(n_frames=800, grid=grid)
    bags = [d.write(tmp_path / f"{name}.mcap") for name, d in (("400", short), ("800", long))]
    assert read_streams(bags[0]).frames.values["images"][0].dtype == np.uint8
    warm = Drive(n_frames=20, grid=grid).write(tmp_path / "warm.mcap")
    done = subprocess.run([sys.executable, "-c", PEAKS_OF_IMPORTS, str(warm), *map(str, bags)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    peak_short, peak_long = (int(v) for v in done.stdout.split()[-2:])
    as_float32 = 400 * 200 * 90 * 4  # 29 MB: 400 more frames as float32 (as uint8: 7 MB)
    assert peak_long - peak_short < 0.75 * as_float32, f"{peak_short / 1e6:.1f} -> {peak_long / 1e6:.1f} MB"
    store = open_store(tmp_path / "800.zarr")
    [run] = [store.run(n) for n in store.runs()]
    np.testing.assert_allclose(run.read("images", 790, 800), long.images[790:] / 255.0, atol=1e-6)


def test_implausible_commands_are_refused_in_one_line_as_import_does_unless_allowed(tmp_path):
    """Commands in cm/s (a Twist's 0.3 m/s logged as 30) are beyond any ground robot: refused in one
    line, flag or not (no reader takes such a run). Commands beyond the rig's limits but not any
    robot's are implausible: ``import``'s refusal and its --allow-implausible."""
    import json

    drive = Drive(n_frames=10)
    drive.v = drive.v * 100
    bag = drive.write(tmp_path / "d.mcap")
    for flags in ([], ["--allow-implausible"]):
        res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), *flags])
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert res.exit_code == 1 and len(lines) == 1 and "Traceback" not in res.output, res.output
        assert lines[0].startswith(f"error: {bag}: topic '/cmd_vel': linear speed up to"), lines[0]
        assert "beyond any ground robot" in lines[0] and "cm/s" in lines[0] and "allow" not in lines[0], lines[0]
        assert not (tmp_path / "s.zarr").exists()
    drive = Drive(n_frames=10)
    drive.v = drive.v * 3  # up to 0.9 m/s: over the rig's 0.3
    bag = drive.write(tmp_path / "r.mcap")
    meta = tmp_path / "r.json"
    meta.write_text(json.dumps({"rig": {"v_max_m_s": 0.3}}))
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), "--meta", str(meta)])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 1 and len(lines) == 1 and "the rig's limit 0.3 m/s" in lines[0], res.output
    assert "(--allow-implausible imports it as is)" in lines[0], lines[0]
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), "--meta", str(meta),
                                   "--allow-implausible"])
    assert res.exit_code == 0, res.output
    [warning] = [ln for ln in res.output.splitlines() if ln.startswith("warning:")]
    assert "linear speed up to" in warning and str(bag) in warning
    assert open_store(tmp_path / "s.zarr").runs() == ["r"]


def test_a_grid_in_millimetres_is_implausible_too(tmp_path):
    grid = SensorGrid(range_min_m=500.0, range_max_m=3000.0, n_range=20, azimuth_min_rad=-1.0, azimuth_max_rad=1.0,
                      n_azimuth=10)
    bag = Drive(n_frames=10, grid=grid).write(tmp_path / "d.mcap")
    with pytest.raises(InputValidationError, match=r"range 500-3e\+03 m is implausible") as exc:
        import_bag(bag, tmp_path / "s.zarr")
    assert exc.value.parameter == "allow_implausible"
    warnings = []
    import_bag(bag, tmp_path / "s.zarr", allow_implausible=True, warn=warnings.append)
    assert len(warnings) == 2 and "implausible for an in-air sonar" in warnings[0], warnings
    assert "less than an echo from 3000 m takes to return" in warnings[1], warnings


def test_a_drive_of_only_short_stretches_between_long_gaps_is_refused_in_one_line(tmp_path):
    from sonarset.ingest.bag.align import MAX_LOST

    drive = Drive(n_frames=30)
    keep = np.zeros(30, bool)
    keep[[0, 1, 2, 10 + MAX_LOST, 11 + MAX_LOST, 12 + MAX_LOST]] = True  # 3 frames, the sensor off, 3 frames
    drive.frame_ns, drive.images = drive.frame_ns[keep], drive.images[keep]
    with pytest.raises(InputValidationError, match="no run of 4 frames at a steady rate") as exc:
        import_bag(drive.write(tmp_path / "d.mcap"), tmp_path / "s.zarr")
    assert len(exc.value.problems) == 1 and not (tmp_path / "s.zarr").exists()


def test_a_topic_whose_pixels_or_beams_change_mid_drive_is_refused_and_a_byte_order_flip_read(tmp_path):
    """One run has one pixel type and one sensor grid: a later message of another pixel type (its
    values would be scaled by the first's full scale) or with its beams in another order (its
    pixels would land in other columns) is refused; each message's byte order is its own."""

    def wider_pixels(k, msg):
        if k >= 4:
            msg["image"] = {**msg["image"], "dtype": 2, "data": np.frombuffer(msg["image"]["data"], np.uint8)
                            .astype("<u2").tobytes()}
        return msg

    def beams_reversed(k, msg):
        if k >= 4:
            msg["beam_directions"] = msg["beam_directions"][::-1]
        return msg

    drive = Drive(n_frames=10)
    cases = {"wider": (wider_pixels, "topic '/sonar/image', message 4: pixels are uint16, the first message's uint8"),
             "beams": (beams_reversed, "message 4: the ranges or beams (their number, directions or order) differ")}
    for name, (edit, says) in cases.items():
        with pytest.raises(InputValidationError, match=re.escape(says)):
            import_bag(drive.write(tmp_path / f"{name}.mcap", edit=edit), tmp_path / f"{name}.zarr")
        assert not (tmp_path / f"{name}.zarr").exists()

    def big_endian(k, msg):
        if k >= 4:
            data = np.frombuffer(msg["image"]["data"], "<u2").astype(">u2").tobytes()
            msg["image"] = {**msg["image"], "is_bigendian": True, "data": data}
        return msg

    import_bag(drive.write(tmp_path / "flip.mcap", image_dtype=2, edit=big_endian), tmp_path / "flip.zarr")
    import_bag(drive.write(tmp_path / "same.mcap", image_dtype=2), tmp_path / "same.zarr")
    flipped = open_store(tmp_path / "flip.zarr").run("flip").read("images")
    assert np.array_equal(flipped, open_store(tmp_path / "same.zarr").run("same").read("images"))
    assert flipped.max() > 0.5


def test_the_first_stamp_is_the_first_imported_frames_and_a_lone_frame_is_no_run(tmp_path):
    drive = Drive(n_frames=12)
    late = drive.command_ns > drive.frame_ns[2]  # frames 0..2 before the first command: dropped
    drive.command_ns, drive.v, drive.w = drive.command_ns[late], drive.v[late], drive.w[late]
    import_bag(drive.write(tmp_path / "late.mcap"), tmp_path / "late.zarr")
    run = open_store(tmp_path / "late.zarr").run("late")
    assert run.attrs.source["first_stamp_ns"] == int(drive.frame_ns[3]) and run.read("time")[0] == 0.0
    lone = Drive(n_frames=12)
    keep = lone.command_ns > lone.frame_ns[10]  # one command, reaching the last frame alone
    lone.command_ns, lone.v, lone.w = lone.command_ns[keep][:1], lone.v[keep][:1], lone.w[keep][:1]
    with pytest.raises(InputValidationError, match=r"no run of 4 frames at a steady rate \(1 frame\(s\) left"):
        import_bag(lone.write(tmp_path / "lone.mcap"), tmp_path / "lone.zarr")


def test_sidecar_fields_a_bag_cannot_apply_and_commands_beyond_any_robot_are_refused(tmp_path):
    import json

    from sonarset import SonarSetError

    bag = Drive(n_frames=10).write(tmp_path / "d.mcap")
    meta = tmp_path / "d.json"
    meta.write_text(json.dumps({"units": {"linear_velocity": "cm/s"}, "velocity_alignment": "next"}))
    with pytest.raises(InputValidationError, match="metadata: units.linear_velocity 'cm/s', velocity_alignment "
                                                   "'next' do not apply to a bag"):
        import_bag(bag, tmp_path / "s.zarr", meta_path=meta)
    with pytest.raises(SonarSetError, match="command timeout must be a finite time > 0 s, got inf"):
        import_bag(bag, tmp_path / "s.zarr", command_timeout_s=float("inf"))
    fast = Drive(n_frames=10)
    fast.v = fast.v * 100 + 15  # beyond any ground robot: allowed, no reader would take the run
    with pytest.raises(InputValidationError, match="linear speed up to .* exceeds 10 m/s, beyond any ground robot"):
        import_bag(fast.write(tmp_path / "f.mcap"), tmp_path / "f.zarr", allow_implausible=True)
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps({"rig": {"v_max_m_s": 0.3}}))
    with pytest.raises(InputValidationError) as exc:  # beyond the rig's limit too: said once, with no flag to try
        import_bag(tmp_path / "f.mcap", tmp_path / "f.zarr", meta_path=rig)
    assert len(exc.value.problems) == 1 and "beyond any ground robot" in exc.value.problems[0]
    assert exc.value.parameter is None
    assert not (tmp_path / "s.zarr").exists() and not (tmp_path / "f.zarr").exists()


def test_frames_of_one_stamp_are_named_not_blamed_on_the_commands(tmp_path):
    """A driver that never updates its header's stamp: the frames' stamps repeat (no interval to
    hold a command over), said as such, with the way out."""
    drive = Drive(times_s=[0.0, 0.2, 0.4, 0.6, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6])
    with pytest.raises(InputValidationError, match=r"topic '/sonar/image', message 4: the same time stamp as message 3 "
                                                   r"\(.*\); 1 repeat\(s\) \(stamps 'bag' uses") as exc:
        import_bag(drive.write(tmp_path / "d.mcap"), tmp_path / "s.zarr")
    assert len(exc.value.problems) == 1


def test_a_drive_at_another_rate_than_the_store_is_told_so(tmp_path):
    import_bag(Drive(n_frames=10, hz=5.0).write(tmp_path / "a.mcap"), tmp_path / "s.zarr")
    with pytest.raises(InputValidationError, match=r"no run of 4 frames at a steady rate \(the frames are 0\.1 s apart, "
                                                   r"the store declares 0\.2 s frames\)"):
        import_bag(Drive(n_frames=20, hz=10.0).write(tmp_path / "b.mcap"), tmp_path / "s.zarr")
    assert open_store(tmp_path / "s.zarr").runs() == ["a"]


def test_what_was_dropped_is_said_before_a_refusal_that_follows(tmp_path):
    """The note of dropped frames comes out even when the import is then refused (here: into a
    store of another frame rate), so the refusal can be read with it."""
    import_bag(Drive(n_frames=12, hz=5.0).write(tmp_path / "five.mcap"), tmp_path / "s.zarr")
    drive = Drive(n_frames=12, hz=8.0)
    late = drive.command_ns > drive.frame_ns[2]
    drive.command_ns, drive.v, drive.w = drive.command_ns[late], drive.v[late], drive.w[late]
    bag = drive.write(tmp_path / "eight.mcap")
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr")])
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert res.exit_code != 0 and len(lines) == 2, res.output
    assert "eight.mcap" in lines[0] and "frames 0..2 dropped: before the first command" in lines[0], res.output
    assert "the store declares 0.2 s frames" in lines[1] and "Traceback" not in res.output, res.output
    assert open_store(tmp_path / "s.zarr").runs() == ["five"]


def test_integer_pixels_follow_a_declared_encoding(tmp_path):
    """Integer pixels are a fraction of full scale unless the sidecar says they are decibels or
    linear energy: then they map as ``import`` maps them, or are refused when they cannot be that."""
    import json

    drive = Drive(n_frames=10)
    bag = drive.write(tmp_path / "lin.mcap", image_dtype=2)
    (tmp_path / "lin.json").write_text(json.dumps({"image_encoding": "linear", "dynamic_range_db": 40}))
    import_bag(bag, tmp_path / "lin.zarr")
    run = open_store(tmp_path / "lin.zarr").run("lin")
    energy = drive.images.astype(np.float64) * 257
    with np.errstate(divide="ignore"):
        expected = np.clip((10 * np.log10(energy / energy.max()) + 40) / 40, 0, 1)
    np.testing.assert_allclose(run.read("images"), expected, atol=2e-3)
    assert run.attrs.source["value_rule"] == "uint16 linear, mapped over 40 dB"
    bag = drive.write(tmp_path / "db.mcap")
    (tmp_path / "db.json").write_text(json.dumps({"image_encoding": "db"}))
    with pytest.raises(InputValidationError, match="decibel values must be <= 0 dB re full scale, found up to 255"):
        import_bag(bag, tmp_path / "db.zarr")
