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

BASE_NS = 1_700_000_000 * 10**9
TIME = "builtin_interfaces/Time"
DEFS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance",
    "marine_acoustic_msgs/PingInfo": "float32 frequency\nfloat32 sound_speed\nfloat32[] tx_beamwidths\n"
                                     "float32[] rx_beamwidths",
    "marine_acoustic_msgs/SonarImageData": "bool is_bigendian\nuint32 dtype\nuint32 beam_count\nuint8[] data",
}
TOP = {
    "marine_acoustic_msgs/msg/ProjectedSonarImage": (
        "std_msgs/Header header\nmarine_acoustic_msgs/PingInfo ping_info\ngeometry_msgs/Vector3[] beam_directions\n"
        "float32[] ranges\nmarine_acoustic_msgs/SonarImageData image",
        ["std_msgs/Header", "builtin_interfaces/Time", "marine_acoustic_msgs/PingInfo", "geometry_msgs/Vector3",
         "marine_acoustic_msgs/SonarImageData"]),
    "geometry_msgs/msg/TwistStamped": ("std_msgs/Header header\ngeometry_msgs/Twist twist",
                                       ["std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Twist",
                                        "geometry_msgs/Vector3"]),
    "geometry_msgs/msg/Twist": (DEFS["geometry_msgs/Twist"], ["geometry_msgs/Vector3"]),
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist",
        ["std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/PoseWithCovariance", "geometry_msgs/Pose",
         "geometry_msgs/Point", "geometry_msgs/Quaternion", "geometry_msgs/TwistWithCovariance",
         "geometry_msgs/Twist", "geometry_msgs/Vector3"]),
}


def msgdef(name: str) -> str:
    text, deps = TOP[name]
    return text + "".join(f"\n{'=' * 80}\nMSG: {d}\n{DEFS[d]}" for d in deps)


def stamp(t_ns: int) -> dict:
    return {"sec": t_ns // 10**9, "nanosec": t_ns % 10**9}


def twist(v: float, w: float) -> dict:
    return {"linear": {"x": v, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": w}}


class Drive:
    """A small drive: frames on a grid, commands at their own rate, odometry."""

    def __init__(self, n_frames=30, hz=5.0, grid=None, command_hz=20.0, seed=0, times_s=None):
        self.grid = grid or SensorGrid(range_min_m=0.5, range_max_m=3.0, n_range=20, azimuth_min_rad=-1.0,
                                       azimuth_max_rad=1.0, n_azimuth=10)
        rng = np.random.default_rng(seed)
        times_s = np.arange(n_frames) / hz if times_s is None else np.asarray(times_s)
        n_frames = len(times_s)
        self.frame_ns = BASE_NS + np.round(times_s * 1e9).astype(np.int64)
        self.images = rng.integers(0, 256, (n_frames, *self.grid.shape), dtype=np.uint8)
        t0, t1 = self.frame_ns[0] - 10**9, self.frame_ns[-1]
        self.command_ns = np.arange(t0, t1 + 1, int(1e9 / command_hz), dtype=np.int64)
        self.v = rng.uniform(0, 0.3, len(self.command_ns))
        self.w = rng.uniform(-0.5, 0.5, len(self.command_ns))
        self.odom_ns = np.arange(t0, t1 + 10**9, 10**8, dtype=np.int64)
        tt = (self.odom_ns - BASE_NS) * 1e-9
        self.odom = np.stack([0.1 * tt, 0.05 * tt, 0.3 * tt], axis=1)

    def write(self, path: Path, *, beams_right_to_left=True, stamped=True, odometry=True, image_dtype=0,
              edit=None) -> Path:
        """An MCAP file by mcap-ros2's writer: beams in the messages' own order (right to left, as
        Z forward X up makes them for increasing rotation about X... either way: the test says)."""
        az = self.grid.azimuth_centres()
        order = np.arange(len(az))[::-1] if beams_right_to_left else np.arange(len(az))
        with open(path, "wb") as f:
            w = mcap_writer.Writer(f)
            s_img = w.register_msgdef("marine_acoustic_msgs/msg/ProjectedSonarImage",
                                      msgdef("marine_acoustic_msgs/msg/ProjectedSonarImage"))
            kind = "geometry_msgs/msg/TwistStamped" if stamped else "geometry_msgs/msg/Twist"
            s_cmd = w.register_msgdef(kind, msgdef(kind))
            s_odom = w.register_msgdef("nav_msgs/msg/Odometry", msgdef("nav_msgs/msg/Odometry"))
            dtype = {0: np.uint8, 2: np.uint16, 8: np.float32}[image_dtype]
            scale = {0: 1, 2: 257, 8: 1 / 255}[image_dtype]
            for k, t in enumerate(self.frame_ns):
                pixels = (self.images[k][:, order].astype(np.float64) * scale).astype(dtype)
                msg = {"header": {"stamp": stamp(int(t)), "frame_id": "sonar"},
                       "ping_info": {"frequency": 40e3, "sound_speed": 343.0, "tx_beamwidths": [], "rx_beamwidths": []},
                       # Z forward, X up: a beam at azimuth a (left positive) points along (0, -sin a, cos a)
                       "beam_directions": [{"x": 0.0, "y": -math.sin(az[j]), "z": math.cos(az[j])} for j in order],
                       "ranges": self.grid.range_centres().tolist(),
                       "image": {"is_bigendian": False, "dtype": image_dtype, "beam_count": len(az),
                                 "data": pixels.tobytes()}}
                if edit is not None:
                    msg = edit(k, msg)
                if msg is not None:
                    w.write_message("/sonar/image", s_img, msg, log_time=int(t), publish_time=int(t))
            for t, v, om in zip(self.command_ns, self.v, self.w):
                body = {"header": {"stamp": stamp(int(t)), "frame_id": "base_link"}, "twist": twist(v, om)} \
                    if stamped else twist(v, om)
                w.write_message("/cmd_vel", s_cmd, body, log_time=int(t), publish_time=int(t))
            if odometry:
                for t, (x, y, yaw) in zip(self.odom_ns, self.odom):
                    q = {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}
                    w.write_message("/odom", s_odom, {
                        "header": {"stamp": stamp(int(t)), "frame_id": "odom"}, "child_frame_id": "base_link",
                        "pose": {"pose": {"position": {"x": x, "y": y, "z": 0.0}, "orientation": q},
                                 "covariance": [0.0] * 36},
                        "twist": {"twist": twist(0, 0), "covariance": [0.0] * 36}}, log_time=int(t), publish_time=int(t))
            w.finish()
        return path

    def expected_velocity(self, timeout_s=0.5) -> np.ndarray:
        """velocity[k]: the held command's mean over (t[k-1], t[k]], by brute-force sampling."""
        t = (self.frame_ns - BASE_NS) * 1e-9
        c = (self.command_ns - BASE_NS) * 1e-9
        edges = np.concatenate([[t[0] - (t[1] - t[0])], t])
        out = []
        for a, b in zip(edges[:-1], edges[1:]):
            s = np.linspace(a, b, 20001)[1:]
            j = np.searchsorted(c, s, side="right") - 1
            live = (j >= 0) & (s - c[np.maximum(j, 0)] <= timeout_s)
            out.append([np.where(live, self.v[j], 0).mean(), np.where(live, self.w[j], 0).mean()])
        return np.array(out)


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
    generate(tmp_path / "sim.zarr", runs=1, test_runs=0, minutes=0.3, seed=4, grid=grid, workers=1)
    src = open_store(tmp_path / "sim.zarr")
    bag = export_bag(src, tmp_path / "run.mcap")
    [run] = import_bag(bag, tmp_path / "back.zarr", split="test")
    a = src.run("run_000")
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



def test_ros2_sqlite3_and_ros1_bags_import_too(tmp_path):
    """Bags from rosbags' own writers, in both ROS 2 storages and ROS 1."""
    drive = Drive(n_frames=12)
    for kind in ("sqlite3", "ros1"):
        path = write_bag(drive, tmp_path / (f"{kind}.bag" if kind == "ros1" else kind), kind)
        [run] = import_bag(path, tmp_path / f"{kind}.zarr")
        np.testing.assert_allclose(run.read("images"), drive.images / 255.0, atol=1e-3)
        np.testing.assert_allclose(run.read("velocity"), drive.expected_velocity(), atol=1e-3)


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
    "command timeout of zero": (None, ["--cmd-timeout", "0"], "command timeout must be > 0"),
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


def jittery_times(n: int, hz: float = 7.1, jitter: float = 0.05, lost: float = 0.08, seed: int = 0) -> np.ndarray:
    """Frame times of a real sensor's drive (BatSLAM2's public eRTIS drive: 7.1 Hz, 95 of 1,186
    pings lost): every stamp off by ``jitter`` of a frame (normal), ``lost`` of the pings missing."""
    rng = np.random.default_rng(seed)
    total = int(n / (1 - lost)) + 20
    t = np.arange(total) / hz + rng.normal(0.0, jitter / hz, total)
    return np.sort(t[rng.random(total) > lost])[:n]


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


def test_a_long_drive_is_held_in_its_pixel_type_and_written_a_chunk_at_a_time(tmp_path):
    import tracemalloc

    from sonarset.ingest.bag.reader import read_streams

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=200, azimuth_min_rad=-1.5, azimuth_max_rad=1.5,
                      n_azimuth=90)
    drive = Drive(n_frames=400, grid=grid)
    bag = drive.write(tmp_path / "d.mcap")
    assert read_streams(bag).frames.values["images"][0].dtype == np.uint8
    # a short drive first: the lazy imports and first-call caches of an import are not the drive's
    # memory, and whether an earlier test in this process paid for them must not move the peak
    import_bag(Drive(n_frames=20, grid=grid).write(tmp_path / "warm.mcap"), tmp_path / "warm.zarr")
    tracemalloc.start()
    try:
        [run] = import_bag(bag, tmp_path / "s.zarr")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    as_float32 = 400 * 200 * 90 * 4  # 29 MB: the whole drive as float32, once
    assert peak < as_float32, f"{peak / 1e6:.1f} MB"
    np.testing.assert_allclose(run.read("images", 390, 400), drive.images[390:] / 255.0, atol=1e-6)


def test_implausible_commands_are_refused_in_one_line_as_import_does_unless_allowed(tmp_path):
    """Commands in cm/s (a Twist's 0.3 m/s logged as 30): ``import``'s plausibility rules, its refusal
    and its --allow-implausible."""
    drive = Drive(n_frames=10)
    drive.v = drive.v * 100
    bag = drive.write(tmp_path / "d.mcap")
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr")])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 1 and len(lines) == 1 and "Traceback" not in res.output, res.output
    assert lines[0].startswith(f"error: {bag}: topic '/cmd_vel': linear speed up to"), lines[0]
    assert "cm/s" in lines[0] and "(--allow-implausible imports it as is)" in lines[0], lines[0]
    assert not (tmp_path / "s.zarr").exists()
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), "--allow-implausible"])
    assert res.exit_code == 0, res.output
    [warning] = [ln for ln in res.output.splitlines() if ln.startswith("warning:")]
    assert "linear speed up to" in warning and str(bag) in warning
    assert open_store(tmp_path / "s.zarr").runs() == ["d"]


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
