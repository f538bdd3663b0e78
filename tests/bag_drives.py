"""Bags for the bag tests (tests/test_bag*.py): a simulated drive's frames and commands, written by
an independent MCAP writer (mcap-ros2) or by rosbags for ROS 2 sqlite3 and ROS 1, and the
timestamps of a jittery drive with lost pings."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")
mcap_writer = pytest.importorskip("mcap_ros2.writer")

from sonarset.format.attrs import SensorGrid  # noqa: E402



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
              edit=None, sonar_package="marine_acoustic_msgs") -> Path:
        """An MCAP file by mcap-ros2's writer: beams in the messages' own order (right to left, as
        Z forward X up makes them for increasing rotation about X... either way: the test says)."""
        az = self.grid.azimuth_centres()
        order = np.arange(len(az))[::-1] if beams_right_to_left else np.arange(len(az))
        with open(path, "wb") as f:
            w = mcap_writer.Writer(f)
            s_img = w.register_msgdef(f"{sonar_package}/msg/ProjectedSonarImage",
                                      msgdef("marine_acoustic_msgs/msg/ProjectedSonarImage").replace(
                                          "marine_acoustic_msgs/", f"{sonar_package}/"))
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



def jittery_times(n: int, hz: float = 7.1, jitter: float = 0.05, lost: float = 0.08, seed: int = 0) -> np.ndarray:
    """Frame times of a real sensor's drive (BatSLAM2's public eRTIS drive: 7.1 Hz, 95 of 1,186
    pings lost): every stamp off by ``jitter`` of a frame (normal), ``lost`` of the pings missing."""
    rng = np.random.default_rng(seed)
    total = int(n / (1 - lost)) + 20
    t = np.arange(total) / hz + rng.normal(0.0, jitter / hz, total)
    return np.sort(t[rng.random(total) > lost])[:n]


