"""ROS bags in and out (sonarset.ingest.bag): bags built by an independent MCAP writer (mcap-ros2),
by rosbags for ROS 2 sqlite3 and ROS 1, and by export_bag; no ROS install."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")
mcap_writer = pytest.importorskip("mcap_ros2.writer")

from sonarset import open_store  # noqa: E402
from sonarset.cli.app import app  # noqa: E402
from sonarset.errors import InputValidationError  # noqa: E402
from sonarset.format.attrs import SensorGrid  # noqa: E402
from sonarset.ingest.bag import export_bag, import_bag  # noqa: E402
from sonarset.store.validate import validate_store  # noqa: E402

from tests.bag_drives import BASE_NS, Drive, msgdef, stamp, twist, write_bag  # noqa: E402


def test_an_independently_written_mcap_imports_with_left_at_positive_azimuth(tmp_path):
    drive = Drive()
    bag = drive.write(tmp_path / "drive.mcap")
    [run] = import_bag(bag, tmp_path / "s.zarr")
    store = open_store(tmp_path / "s.zarr")
    assert store.grid.matches(drive.grid, rtol=1e-5)
    # the messages list beams right to left; the store holds them left-positive, as the spec says
    np.testing.assert_allclose(run.read("images"), drive.images / 255.0, atol=1e-3)
    np.testing.assert_allclose(run.read("velocity"), drive.expected_velocity(), atol=1e-3)
    np.testing.assert_allclose(run.read("time"), np.arange(30) * 0.2, atol=1e-9)
    np.testing.assert_allclose(run.read("pose")[:, :2], drive.odom[10:][::2][:30, :2], atol=1e-9)
    assert abs(store.attrs.frame_rate_hz - 5.0) < 1e-6
    assert run.attrs.source["value_rule"].startswith("uint8 / 255")
    assert validate_store(tmp_path / "s.zarr") == []


def test_a_target_on_the_left_lands_at_positive_azimuth(tmp_path):
    drive = Drive()
    drive.images[:] = 0
    az = drive.grid.azimuth_centres()
    left = int(np.argmax(az))  # the beam furthest left (largest rotation about the up axis)
    drive.images[:, 5, left] = 255
    [run] = import_bag(drive.write(tmp_path / "d.mcap", beams_right_to_left=True), tmp_path / "s.zarr")
    image = run.read("images")[0]
    assert np.unravel_index(np.argmax(image), image.shape) == (5, left) and az[left] > 0


@pytest.mark.parametrize("dtype_code", [2, 8])
def test_pixel_types_map_by_the_recorded_rule(tmp_path, dtype_code):
    drive = Drive()
    [run] = import_bag(drive.write(tmp_path / "d.mcap", image_dtype=dtype_code), tmp_path / "s.zarr")
    np.testing.assert_allclose(run.read("images"), drive.images / 255.0, atol=1e-3)


@pytest.mark.parametrize("sidecar_interval", [0.2, 0.25])
def test_a_jittery_drive_with_a_sidecar_rig_makes_a_store_that_opens_checked(tmp_path, sidecar_interval):
    """The store's nominal rate and its rig's interval agree whatever the stamps' jitter: the
    sidecar's interval where the bag's median agrees with it, else the bag's (said)."""
    import json

    times = np.arange(40) * 0.2 + np.random.default_rng(1).uniform(-0.004, 0.004, 40)
    bag = Drive(times_s=times).write(tmp_path / "d.mcap")
    (tmp_path / "d.json").write_text(json.dumps({"rig": {"frame_interval_s": sidecar_interval}}))
    notes = []
    import_bag(bag, tmp_path / "s.zarr", note=notes.append)
    store = open_store(tmp_path / "s.zarr", check=True)
    assert math.isclose(store.rig.frame_interval_s * store.attrs.frame_rate_hz, 1.0, rel_tol=1e-9)
    if sidecar_interval == 0.2:
        assert store.rig.frame_interval_s == 0.2 and "sidecar's rig" not in "".join(notes)
    else:
        assert abs(store.rig.frame_interval_s - 0.2) < 0.005 and "the sidecar's rig says 0.25 s" in "".join(notes)


def test_the_older_acoustic_msgs_package_name_reads_too(tmp_path):
    """marine_acoustic_msgs was acoustic_msgs before 2023: bags of older drivers carry that name."""
    drive = Drive(n_frames=10)
    [run] = import_bag(drive.write(tmp_path / "d.mcap", sonar_package="acoustic_msgs"), tmp_path / "s.zarr")
    np.testing.assert_allclose(run.read("images"), drive.images / 255.0, atol=1e-3)
    assert run.attrs.source["images_type"] == "acoustic_msgs/msg/ProjectedSonarImage"


@pytest.mark.parametrize("first", [0.0, -1e-6])  # a rounding error below 0 m is 0 m
def test_a_range_bin_at_zero_metres_is_dropped_and_said(tmp_path, first):
    """Sonars that report their first sample at 0 m: that bin would reach behind the sensor."""
    def from_zero(k, msg):
        msg["ranges"] = [r - msg["ranges"][0] + first for r in msg["ranges"]]
        return msg

    drive, notes = Drive(n_frames=10), []
    [run] = import_bag(drive.write(tmp_path / "d.mcap", edit=from_zero), tmp_path / "s.zarr", note=notes.append)
    step = drive.grid.range_step
    assert open_store(tmp_path / "s.zarr").grid.matches(
        drive.grid.model_copy(update=dict(range_min_m=step / 2, range_max_m=drive.grid.range_max_m - drive.grid.range_min_m
                                          - step / 2, n_range=drive.grid.n_range - 1)), rtol=1e-5)
    np.testing.assert_allclose(run.read("images"), drive.images[:, 1:] / 255.0, atol=1e-3)
    assert any(f"the range bin at {first:g} m dropped" in n for n in notes), notes


def test_twist_without_header_takes_bag_time_and_a_few_dropped_pings_are_recorded_in_the_run(tmp_path):
    drive = Drive(n_frames=40)
    keep = np.ones(40, bool)
    keep[[15, 16]] = False  # two pings dropped
    keep[37] = False  # and one near the end, 2 frames before it: kept, no window reaches them
    drive.frame_ns, drive.images = drive.frame_ns[keep], drive.images[keep]
    notes = []
    [run] = import_bag(drive.write(tmp_path / "d.mcap", stamped=False), tmp_path / "s.zarr", name="drive",
                       note=notes.append)
    assert run.name == "drive" and run.n_frames == 37
    assert run.attrs.model_extra["gaps"] == [[15, 2], [35, 1]]
    [summary] = [n for n in notes if "lost ping" in n]  # one line, however many pings were lost
    assert "3 lost ping(s) at 2 gap(s)" in summary and "1 run(s); 2 gap(s) recorded" in summary, summary
    assert validate_store(tmp_path / "s.zarr") == []
    from sonarset.windows import FrameBank, WindowIndex

    bank = FrameBank.from_store(open_store(tmp_path / "s.zarr"))
    starts = WindowIndex.build(bank, 3, 1).starts.tolist()
    # windows 12..14 would hold frames on both sides of the first gap, 32..34 of the second
    assert starts == [i for i in range(34) if not 12 <= i <= 14 and not 32 <= i <= 33]
    np.testing.assert_allclose(bank.images, drive.images / 255.0, atol=1e-3)  # no frame dropped


def test_a_long_gap_splits_the_drive_and_short_ones_stay_recorded(tmp_path):
    from sonarset.ingest.bag.align import MAX_LOST

    drive = Drive(n_frames=60)
    keep = np.ones(60, bool)
    keep[20:21 + MAX_LOST] = False  # MAX_LOST + 1 pings in a row: the sensor stopped
    keep[40] = False  # one ping: recorded
    drive.frame_ns, drive.images = drive.frame_ns[keep], drive.images[keep]
    notes = []
    runs = import_bag(drive.write(tmp_path / "d.mcap"), tmp_path / "s.zarr", name="d", note=notes.append)
    assert [(r.name, r.n_frames) for r in runs] == [("d_000", 20), ("d_001", 38 - MAX_LOST)]
    assert runs[0].attrs.model_extra.get("gaps") is None
    assert runs[1].attrs.model_extra["gaps"] == [[19 - MAX_LOST, 1]]
    [summary] = [n for n in notes if "lost ping" in n]
    assert f"2 run(s), split at 1 gap(s) of over {MAX_LOST} pings; 1 gap(s) recorded" in summary, summary
    assert validate_store(tmp_path / "s.zarr") == []


def test_export_then_import_gives_back_the_run_and_eval_runs_on_it(tmp_path):
    from sonarset.sim import generate

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=30)
    generate(tmp_path / "sim.zarr", runs=0, test_runs=1, minutes=0.3, seed=4, grid=grid, workers=1)
    src = open_store(tmp_path / "sim.zarr")
    bag = export_bag(src, tmp_path / "run.mcap")
    [run] = import_bag(bag, tmp_path / "back.zarr")
    a = src.run("test_000")
    # what no message carries comes back through the sidecar written beside the bag
    back = open_store(tmp_path / "back.zarr", check=True)
    assert (tmp_path / "run.json").is_file() and run.name == "test_000" and back.rig == src.rig
    assert run.split == a.split == "test"
    assert back.processing.same_images(src.processing) and not back.processing.unknown
    images_a, images_b = a.read("images").astype(np.float64), run.read("images").astype(np.float64)
    cc = np.corrcoef(images_a.ravel(), images_b.ravel())[0, 1]
    assert cc >= 0.999
    np.testing.assert_allclose(run.read("velocity"), a.read("velocity"), atol=1e-3)
    np.testing.assert_allclose(run.read("time"), a.read("time"), atol=1e-6)
    d = run.read("pose") - a.read("pose")
    d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(d).max() < 1e-6
    res = CliRunner().invoke(app, ["eval", str(tmp_path / "back.zarr"), "--models", "naive,flow", "--samples", "10",
                                   "--horizons", "1,3", "--no-figures", "--out", str(tmp_path / "ev")])
    assert res.exit_code == 0, res.output

    # the same run written by mcap-ros2-support, a writer that is not the importer's library
    drive = Drive()
    drive.grid, drive.images = grid, a.read("images").astype(np.float64) * 255.0
    drive.frame_ns = BASE_NS + np.round((a.read("time") - a.read("time")[0]) * 1e9).astype(np.int64)
    step = int(np.median(np.diff(drive.frame_ns)))
    drive.command_ns = drive.frame_ns - step  # each command in force over the interval that ends at its frame
    drive.v, drive.w = a.read("velocity")[:, 0].astype(float), a.read("velocity")[:, 1].astype(float)
    drive.odom_ns, drive.odom = drive.frame_ns, a.read("pose").astype(float)
    [other] = import_bag(drive.write(tmp_path / "other.mcap", image_dtype=8), tmp_path / "other.zarr",
                         split="test")
    images_c = other.read("images").astype(np.float64)
    assert np.corrcoef(images_a.ravel(), images_c.ravel())[0, 1] >= 0.999
    np.testing.assert_allclose(other.read("velocity"), a.read("velocity"), atol=1e-3)
    res = CliRunner().invoke(app, ["eval", str(tmp_path / "other.zarr"), "--models", "naive,flow", "--samples",
                                   "10", "--horizons", "1,3", "--no-figures", "--out", str(tmp_path / "ev2")])
    assert res.exit_code == 0, res.output


def test_ros2_sqlite3_and_ros1_bags_import_too(tmp_path):
    """Bags from rosbags' own writers, in both ROS 2 storages and ROS 1."""
    drive = Drive(n_frames=12)
    for kind in ("sqlite3", "ros1"):
        path = write_bag(drive, tmp_path / (f"{kind}.bag" if kind == "ros1" else kind), kind)
        [run] = import_bag(path, tmp_path / f"{kind}.zarr")
        np.testing.assert_allclose(run.read("images"), drive.images / 255.0, atol=1e-3)
        np.testing.assert_allclose(run.read("velocity"), drive.expected_velocity(), atol=1e-3)


@pytest.mark.parametrize("name, says", [
    ("drive.bag.active", "a ROS 1 bag its recorder did not close (still recording, or killed): `rosbag reindex` it"),
    ("drive.rosbag", "a ROS 1 bag: name it *.bag"),
])
def test_a_ros1_bag_under_another_name_is_said_so(tmp_path, name, says):
    """rosbags tells ROS 1 bags by their suffix: another name was misread as a ROS 2 bag."""
    bag = write_bag(Drive(n_frames=4), tmp_path / "drive.bag", "ros1").rename(tmp_path / name)
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr")])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 1 and len(lines) == 1 and lines[0].startswith(f"error: {bag}: {says}"), res.output
    assert not (tmp_path / "s.zarr").exists()


def _drop_data(k, msg):
    msg["image"]["data"] = msg["image"]["data"][:-3]
    return msg


def _zero_stamp(k, msg):
    if k == 3:
        msg["header"]["stamp"] = {"sec": 0, "nanosec": 0}
    return msg


def _backwards(k, msg):
    if k == 3:
        msg["header"]["stamp"] = stamp(BASE_NS - 10**9)
    return msg


def _bad_dtype(k, msg):
    msg["image"]["dtype"] = 12
    return msg


def _beam_count(k, msg):
    msg["image"]["beam_count"] = 9
    return msg


def _ranges_below_zero(k, msg):
    msg["ranges"] = [r - 1.0 for r in msg["ranges"]]
    return msg


def _nan_pixel(k, msg):
    pixels = np.frombuffer(msg["image"]["data"], np.uint8) / np.float32(255)
    pixels[7] = np.nan if k == 4 else pixels[7]
    msg["image"]["data"], msg["image"]["dtype"] = pixels.astype(np.float32).tobytes(), 8
    return msg


def _pixel_type_changes(k, msg):
    if k == 5:
        msg["image"]["data"] = np.frombuffer(msg["image"]["data"], np.uint8).astype(np.uint16).tobytes()
        msg["image"]["dtype"] = 2
    return msg


def _grid_changes(k, msg):
    if k == 5:
        msg["ranges"] = [r * 1.1 for r in msg["ranges"]]
    return msg


MALFORMED = {
    "truncated file": (lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]), [], "cannot read"),
    # bytes zeroed inside the first chunk: every topic's reader would meet them; said once
    "a damaged chunk": (lambda p: p.write_bytes((b := p.read_bytes())[:3000] + bytes(100) + b[3100:]), [],
                        "the bag ends inside a message or is damaged (reading topic '/sonar/image')"),
    "not a bag": (lambda p: p.write_bytes(b"\x89MCAP0\r\n" + b"garbage" * 100), [], "cannot read"),
    "named topic missing": (None, ["--images", "/nope"], "no topic '/nope'"),
    "topic of the wrong type": (None, ["--images", "/cmd_vel"], "is geometry_msgs/msg/TwistStamped, not"),
    "image data cut short": (_drop_data, [], "image data has"),
    "zero stamps": (_zero_stamp, [], "zero or negative"),
    "stamps go backwards": (_backwards, [], "go backwards"),
    "unknown pixel type": (_bad_dtype, [], "unknown SonarImageData dtype 12"),
    "beam_count disagrees": (_beam_count, [], "beam directions for beam_count 9"),
    "grid changes mid-run": (_grid_changes, [], "differ from the first message"),
    "a NaN pixel": (_nan_pixel, [], "message 4: NaN or infinite pixel values"),
    "pixel type changes mid-run": (_pixel_type_changes, [], "message 5: pixels are uint16, the first message's uint8"),
    "ranges below zero": (_ranges_below_zero, [], "ranges -0.4375..1.9375 m (20 bins) put the first bin's near edge"),
    "commands a minute late": (None, ["--cmd-offset", "60"], "no command reaches any frame interval"),
    "command timeout of zero": (None, ["--cmd-timeout", "0"], "command timeout must be a finite time > 0"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_bags_get_one_line_and_leave_nothing(tmp_path, case):
    damage, args, says = MALFORMED[case]
    drive = Drive(n_frames=10)
    edit = damage if damage is not None and damage.__name__.startswith("_") else None
    bag = drive.write(tmp_path / "d.mcap", edit=edit)
    if damage is not None and edit is None:
        damage(bag)
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), *args])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 1 and len(lines) == 1 and lines[0].startswith("error:"), res.output
    assert says in lines[0], lines[0]
    assert "Traceback" not in res.output
    assert not (tmp_path / "s.zarr").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["d.mcap"]


def test_a_plain_image_topic_needs_the_sidecar_grid(tmp_path):
    with pytest.raises(InputValidationError, match="no sonar image topic"):
        import_bag(_only_commands(tmp_path / "c.mcap"), tmp_path / "s.zarr")


def _only_commands(path: Path) -> Path:
    with open(path, "wb") as f:
        w = mcap_writer.Writer(f)
        s = w.register_msgdef("geometry_msgs/msg/Twist", msgdef("geometry_msgs/msg/Twist"))
        w.write_message("/cmd_vel", s, twist(0.1, 0.0), log_time=BASE_NS, publish_time=BASE_NS)
        w.finish()
    return path


def test_eval_notes_a_model_trained_at_another_frame_rate():
    """A real sensor's rate (7.1 Hz) against the pretrained model's 5 Hz frames: said, not hidden."""
    import json

    from sonarset.models.echopt.cards import card_processing, training_notices
    from sonarset.models.echopt.checkpoint import PRETRAINED

    card = json.loads(PRETRAINED.with_suffix(".json").read_text())
    assert training_notices("echopt", card, card_processing(card), None, 0.2) == []
    [note] = training_notices("echopt", card, card_processing(card), None, 1 / 7.1)
    assert "trained on 0.2 s frames (5 Hz)" in note and "(7.1 Hz)" in note


def test_microphone_pings_in_a_bag_beamform_as_import_raw_does(tmp_path):
    """A simulated run's scene rendered to microphone signals, once as import-raw's files and once
    as MicrophoneArrayPing messages with TwistStamped commands: the same images either way."""
    import json
    import shutil

    from rosbags.rosbag2 import StoragePlugin, Writer

    from sonarset.ingest.bag.messages import writing_typestore
    from sonarset.ingest.raw import import_raw
    from sonarset.sim import generate
    from sonarset.sim.reference import write_raw_recording

    generate(tmp_path / "sim.zarr", runs=0, test_runs=1, minutes=0.02, seed=3, workers=1, snr_db=40.0)
    rec_dir = write_raw_recording(open_store(tmp_path / "sim.zarr").run("test_000"), tmp_path / "raw", seed=1)
    by_file = import_raw(rec_dir, tmp_path / "file.zarr")
    signals = np.load(rec_dir / "signals.npy")
    time_s, velocity = np.load(rec_dir / "time.npy"), np.load(rec_dir / "velocity.npy")
    sidecar = json.loads((rec_dir / "recording.json").read_text())
    ts = writing_typestore()
    T = ts.types
    bag = tmp_path / "pings"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        cp = w.add_connection("/ertis/pings", "sonarset_msgs/msg/MicrophoneArrayPing", typestore=ts)
        cc = w.add_connection("/cmd_vel", "geometry_msgs/msg/TwistStamped", typestore=ts)
        ns = BASE_NS + np.round((time_s - time_s[0]) * 1e9).astype(np.int64)
        step = int(np.median(np.diff(ns)))

        def header(t):
            return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(t // 10**9),
                                                                                   nanosec=int(t % 10**9)),
                                            frame_id="ertis")

        for k, t in enumerate(ns):
            vec = T["geometry_msgs/msg/Vector3"]
            cmd = T["geometry_msgs/msg/TwistStamped"](header=header(t - step), twist=T["geometry_msgs/msg/Twist"](
                linear=vec(x=float(velocity[k, 0]), y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=float(velocity[k, 1]))))
            w.write(cc, int(t - step), ts.serialize_cdr(cmd, cc.msgtype))
            ping = T["sonarset_msgs/msg/MicrophoneArrayPing"](
                header=header(t), sample_rate_hz=float(sidecar["sample_rate_hz"]), channel_count=signals.shape[1],
                sample_count=signals.shape[2], samples=signals[k].ravel())
            w.write(cp, int(t), ts.serialize_cdr(ping, cp.msgtype))
    meta = tmp_path / "pings.json"
    meta.write_text(json.dumps(sidecar))
    for extra in rec_dir.iterdir():  # files the sidecar names (a microphone CSV) sit beside it
        if extra.suffix == ".csv":
            shutil.copy(extra, tmp_path / extra.name)
    [by_bag] = import_bag(bag, tmp_path / "bag.zarr", meta_path=meta, name="test_000")
    assert by_bag.attrs.source["kind"] == "import-bag" and by_bag.attrs.source["beamformer"] == "dmas3-cf"
    np.testing.assert_array_equal(by_bag.read("images"), by_file.read("images"))
    np.testing.assert_allclose(by_bag.read("velocity"), by_file.read("velocity"), atol=1e-6)
    assert validate_store(tmp_path / "bag.zarr") == []


