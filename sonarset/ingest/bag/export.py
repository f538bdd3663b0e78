"""``export_bag``: runs of a store as one MCAP file that plays in ROS 2 tools, Foxglove and Rerun.

Per run, on the frame clock ``base_time_s + time``:
- ``/sonar/image`` ``marine_acoustic_msgs/ProjectedSonarImage``: the energyscape as float32,
  range-major, ``ranges`` the bin centres, ``beam_directions`` the beams in the sensor frame (Z
  forward, X up), frame ``sonar``;
- ``/cmd_vel`` ``geometry_msgs/TwistStamped``: ``velocity[k]`` published when it took effect,
  one frame interval before frame k, so that holding each command until the next gives back
  exactly ``velocity`` (what ``import_bag`` computes);
- ``/odom`` ``nav_msgs/Odometry`` and ``/tf`` (odom -> base_link) where the run has poses, and
  ``/tf_static`` base_link -> sonar (the rig's sensor offset, the sensor frame's axes).
Several runs go one after another on the clock, a second apart, each under its own topic prefix
when there is more than one (``/run_000/sonar/image``...).

Beside it, ``OUT.json``: the sidecar ``import_bag`` reads by default, with what a bag has no
message for (the store's processing and rig, the run's name and split), so that an import gives back a
store that trains and fine-tunes as the original did.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Callable

import numpy as np

from sonarset.errors import SonarSetError
from sonarset.ingest.metadata import sidecar_for
import sonarset.ingest.bag.messages as m
from sonarset.store.atomic import aside_dir, refuse_non_regular
from sonarset.store.store import SonarStore, open_store

BASE_TIME_S = 1.0e9  # 2001-09-09: a stamp no reader takes for "unset" (zero)
# base_link (x forward, y left, z up) -> sonar (x up, y right, z forward): a half turn about (x + z)
SONAR_IN_BASE = (0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5))  # (w, x, y, z)


def export_bag(store: str | os.PathLike | SonarStore, out: str | os.PathLike, *, runs: list[str] | None = None,
               base_time_s: float = BASE_TIME_S, progress: Callable[[str, int, int], None] | None = None) -> Path:
    """Write ``runs`` (default: every complete run) of ``store`` to the MCAP file ``out`` and its
    sidecar ``out.json``, written aside and renamed into place; returns the MCAP's path."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    src = store if isinstance(store, SonarStore) else open_store(store, check=True)
    names = runs or src.runs()
    missing = [n for n in names if n not in src.runs()]
    if missing:
        raise SonarSetError(f"{src.location}: no complete run {missing[0]!r} (runs: {', '.join(src.runs())})",
                            parameter="runs")
    out = Path(out)
    if out.suffix != ".mcap":
        raise SonarSetError(f"{out}: the output is an MCAP file: name it *.mcap", parameter="out")
    refuse_non_regular(out, "the MCAP file", "the output needs an .mcap file path")
    refuse_non_regular(sidecar_for(out), "the MCAP file's sidecar", "export writes its sidecar there")
    ts = m.writing_typestore()
    tmp = aside_dir(out)
    try:
        bag_dir = tmp / "bag"
        with Writer(bag_dir, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
            clock = int(round(base_time_s * 1e9))  # ns: float seconds since 1970 keep only ~0.1 us
            for name in names:
                prefix = f"/{name}" if len(names) > 1 else ""
                clock = _write_run(writer, ts, src, name, prefix, clock, static, progress) + 1_000_000_000
        [mcap] = bag_dir.glob("*.mcap")
        sidecar = tmp / "sidecar.json"
        sidecar.write_text(json.dumps(_sidecar(src, names), indent=2) + "\n")
        os.replace(sidecar, sidecar_for(out))
        os.replace(mcap, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _sidecar(store: SonarStore, names: list[str]) -> dict:
    """The recording metadata (format.sidecars.RecordingMeta) of the exported runs."""
    doc: dict = {"recording_version": "1.0"}
    if len(names) == 1:
        doc["name"] = names[0]
    splits = {store.run(n).split for n in names}
    if len(splits) == 1:  # a test run must not come back as a training run
        doc["split"] = splits.pop()
    if not store.processing.unknown:
        doc["processing"] = store.processing.model_dump(mode="json")
    if store.rig is not None:
        doc["rig"] = store.rig.model_dump(mode="json")
    doc["source"] = {"exported_from": str(store.location), "runs": names}
    return doc


def _write_run(writer, ts, store: SonarStore, name: str, prefix: str, clock: int, static, progress) -> int:
    run = store.run(name)
    data = run.load(image_dtype=np.float32)
    grid = store.grid
    T = len(data.time)
    t = clock + np.round((data.time - data.time[0]) * 1e9).astype(np.int64)
    Types = ts.types
    conn_image = writer.add_connection(f"{prefix}/sonar/image", m.SONAR_IMAGE, typestore=ts)
    conn_cmd = writer.add_connection(f"{prefix}/cmd_vel", m.TWIST_STAMPED, typestore=ts)
    conn_odom = conn_tf = None
    if data.pose is not None:
        conn_odom = writer.add_connection(f"{prefix}/odom", m.ODOMETRY, typestore=ts)
        conn_tf = writer.add_connection(f"{prefix}/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
    offset = store.rig.sensor_offset_m if store.rig is not None else 0.0
    _write(writer, ts, static, t[0], Types["tf2_msgs/msg/TFMessage"](transforms=[
        _transform(Types, t[0], "base_link", "sonar", (offset, 0.0, 0.0), SONAR_IN_BASE)]))
    directions = [Types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))
                  for x, y, z in m.beam_directions(grid.azimuth_centres())]
    ranges = grid.range_centres().astype(np.float32)
    ping = Types["marine_acoustic_msgs/msg/PingInfo"](frequency=0.0, sound_speed=343.0,
                                                       tx_beamwidths=np.zeros(0, np.float32),
                                                       rx_beamwidths=np.zeros(0, np.float32))
    step = np.diff(t, prepend=t[0] - (int(np.median(np.diff(t))) if T > 1 else 200_000_000))
    for k in range(T):
        # the command that moved the robot into frame k took effect one frame interval before it
        cmd_time = t[k] - step[k]
        twist = Types["geometry_msgs/msg/Twist"](linear=_vec(Types, data.velocity[k, 0], 0, 0),
                                                 angular=_vec(Types, 0, 0, data.velocity[k, 1]))
        _write(writer, ts, conn_cmd, cmd_time, Types[m.TWIST_STAMPED](header=_header(Types, cmd_time, "base_link"),
                                                                      twist=twist))
        image = Types["marine_acoustic_msgs/msg/SonarImageData"](
            is_bigendian=False, dtype=8, beam_count=grid.n_azimuth,
            data=np.ascontiguousarray(data.images[k], "<f4").view(np.uint8).ravel())
        _write(writer, ts, conn_image, t[k], Types[m.SONAR_IMAGE](
            header=_header(Types, t[k], "sonar"), ping_info=ping, beam_directions=directions, ranges=ranges,
            image=image))
        if conn_odom is not None:
            x, y, yaw = (float(v) for v in data.pose[k])
            q = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
            _write(writer, ts, conn_odom, t[k], _odometry(Types, t[k], x, y, q))
            _write(writer, ts, conn_tf, t[k], Types["tf2_msgs/msg/TFMessage"](
                transforms=[_transform(Types, t[k], "odom", "base_link", (x, y, 0.0), q)]))
        if progress and (k % 64 == 63 or k == T - 1):
            progress(name, k + 1, T)
    return int(t[-1])


def _write(writer, ts, conn, t_ns: int, msg) -> None:
    writer.write(conn, int(t_ns), ts.serialize_cdr(msg, conn.msgtype))


def _stamp(Types, t_ns: int):
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return Types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(Types, t: int, frame: str):
    return Types["std_msgs/msg/Header"](stamp=_stamp(Types, t), frame_id=frame)


def _vec(Types, x, y, z):
    return Types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))


def _quaternion(Types, q):
    w, x, y, z = q
    return Types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)


def _transform(Types, t: int, parent: str, child: str, xyz, q):
    return Types["geometry_msgs/msg/TransformStamped"](
        header=_header(Types, t, parent), child_frame_id=child,
        transform=Types["geometry_msgs/msg/Transform"](translation=_vec(Types, *xyz), rotation=_quaternion(Types, q)))


def _odometry(Types, t: int, x: float, y: float, q):
    pose = Types["geometry_msgs/msg/PoseWithCovariance"](
        pose=Types["geometry_msgs/msg/Pose"](position=Types["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                             orientation=_quaternion(Types, q)),
        covariance=np.zeros(36))
    twist = Types["geometry_msgs/msg/TwistWithCovariance"](
        twist=Types["geometry_msgs/msg/Twist"](linear=_vec(Types, 0, 0, 0), angular=_vec(Types, 0, 0, 0)),
        covariance=np.zeros(36))
    return Types[m.ODOMETRY](header=_header(Types, t, "odom"), child_frame_id="base_link", pose=pose, twist=twist)
