"""The ROS messages a bag import reads and an export writes, and their conventions.

Definitions come from the bag itself (rosbags registers what a bag's writer embedded), so a bag
from another driver version works; the definitions shipped in ``sonarset/data/ros`` (documented in
spec/ros/README.md) are registered only for types a bag does not define, and for writing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SONAR_IMAGE = "marine_acoustic_msgs/msg/ProjectedSonarImage"
#: The same message under the package's name before 2023 (apl-ocean-engineering's acoustic_msgs).
OLD_SONAR_IMAGE = "acoustic_msgs/msg/ProjectedSonarImage"
PLAIN_IMAGE = "sensor_msgs/msg/Image"
MICROPHONES = "sonarset_msgs/msg/MicrophoneArrayPing"
TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
ODOMETRY = "nav_msgs/msg/Odometry"

IMAGE_TYPES = (SONAR_IMAGE, OLD_SONAR_IMAGE, PLAIN_IMAGE)
COMMAND_TYPES = (TWIST_STAMPED, TWIST)
ODOMETRY_TYPES = (ODOMETRY,)
RAW_TYPES = (MICROPHONES,)

# SonarImageData.dtype codes
SONAR_DTYPES = {0: "u1", 1: "i1", 2: "u2", 3: "i2", 4: "u4", 5: "i4", 6: "u8", 7: "i8", 8: "f4", 9: "f8"}
SONAR_DTYPE_CODES = {np.dtype(v).newbyteorder("=").str[1:]: k for k, v in SONAR_DTYPES.items()}
# sensor_msgs/Image encodings a single-channel sonar image comes in
PLAIN_ENCODINGS = {"mono8": "u1", "8UC1": "u1", "mono16": "u2", "16UC1": "u2", "32FC1": "f4", "64FC1": "f8"}

DEFINITIONS = Path(__file__).resolve().parents[2] / "data" / "ros"


def shipped_types() -> dict:
    """The message types of ``sonarset/data/ros`` as rosbags type definitions."""
    from rosbags.typesys import get_types_from_msg

    types: dict = {}
    for path in sorted(DEFINITIONS.glob("*/msg/*.msg")):
        package = path.parent.parent.name
        for pkg in (package, "acoustic_msgs") if package == "marine_acoustic_msgs" else (package,):
            types.update(get_types_from_msg(path.read_text(), f"{pkg}/msg/{path.stem}"))
    return types


def writing_typestore():
    """ROS 2 Jazzy's standard messages plus the shipped ones: what ``export_bag`` serialises with."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(shipped_types())
    return store


def stamp_ns(stamp) -> int:
    """A builtin_interfaces/Time (ROS 2) or ROS 1 time as integer nanoseconds since the epoch."""
    return int(stamp.sec) * 1_000_000_000 + int(getattr(stamp, "nanosec", getattr(stamp, "nsec", 0)))


def yaw_of(q) -> float:
    """Heading (rotation about z) of a geometry_msgs/Quaternion, radians."""
    return float(np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z)))


def beam_azimuths(directions: np.ndarray) -> np.ndarray:
    """Azimuth (ours: positive to the left of forward) of ProjectedSonarImage beam directions
    (N, 3) as (x, y, z) in the sensor frame: Z forward and X up make Y point right, so a beam to
    the left has negative y."""
    return np.arctan2(-directions[:, 1], directions[:, 2])


def beam_directions(azimuth: np.ndarray) -> np.ndarray:
    """Unit beam directions (N, 3) of azimuths, the inverse of ``beam_azimuths`` (no elevation)."""
    return np.stack([np.zeros_like(azimuth), -np.sin(azimuth), np.cos(azimuth)], axis=1)
