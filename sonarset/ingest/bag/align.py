"""Commands and poses onto the sonar's frames, and runs split where pings were dropped.

The spec's alignment: ``velocity[k]`` is the command that moved the robot from frame k-1 to
frame k. A robot's controller holds each command until the next arrives (zero-order hold) and
stops when none has come for its timeout (``diff_drive_controller``'s ``cmd_vel_timeout``, 0.5 s
by default). So ``velocity[k]`` is the time-weighted mean of the held command over (t[k-1], t[k]];
for the first frame, over the one frame interval before it. Commands arrive at any rate (20 Hz is
common); ``command_offset_s`` is added to every command stamp, for a known clock offset between
the controller and the sensor. Frames before the first command are dropped (a robot not yet
commanded); a frame interval no command reaches is an error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GAP_FACTOR = 1.5  # a frame interval this many median intervals long holds a dropped ping
MIN_SEGMENT = 4  # frames: 3 of context and one to predict, the shortest window
COMMAND_TIMEOUT_S = 0.5


def held_mean(times: np.ndarray, values: np.ndarray, edges: np.ndarray, timeout_s: float) -> np.ndarray:
    """Mean over each interval (edges[k], edges[k+1]] of the zero-order hold of ``values`` set at
    ``times`` (sorted), each value falling to zero ``timeout_s`` after it was set.

    The held signal is piecewise constant, so its integral is piecewise linear between the
    moments a command starts and stops: exact at every edge by interpolation, in O(n) memory.
    """
    ends = np.minimum(np.append(times[1:], times[-1] + timeout_s), times + timeout_s)
    points = np.stack([times, ends], axis=1).ravel()
    pieces = np.stack([np.zeros_like(values, dtype=np.float64), values * (ends - times)], axis=1).ravel()
    integral = np.concatenate([[0.0], np.cumsum(pieces)])[1:]  # at each point, the area so far
    area = np.interp(edges, points, integral, left=0.0, right=integral[-1])
    return np.diff(area) / np.diff(edges)


def command_coverage(times: np.ndarray, edges: np.ndarray, timeout_s: float) -> np.ndarray:
    """For each interval (edges[k], edges[k+1]], whether a command was in force in some of it."""
    return held_mean(times, np.ones_like(times), edges, timeout_s) > 0


@dataclass(frozen=True)
class Segment:
    """Frames ``start:stop`` of a recording, one run."""

    start: int
    stop: int


def split_at_gaps(times: np.ndarray) -> tuple[list[Segment], list[str]]:
    """Runs of frames without a dropped ping, and a note for each split or dropped piece."""
    if len(times) < 2:
        return [Segment(0, len(times))], []
    dt = np.diff(times)
    nominal = float(np.median(dt))
    cuts = np.flatnonzero(dt > GAP_FACTOR * nominal) + 1
    bounds = [0, *cuts.tolist(), len(times)]
    notes = []
    for c in cuts:
        missed = int(round(dt[c - 1] / nominal)) - 1
        notes.append(f"split at frame {c} (t = {times[c] - times[0]:.2f} s): {dt[c - 1]:.3f} s since the last "
                     f"frame, {dt[c - 1] / nominal:.1f} frame intervals ({max(missed, 1)} ping(s) dropped?)")
    segments = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a >= MIN_SEGMENT:
            segments.append(Segment(a, b))
        else:
            notes.append(f"frames {a}..{b - 1} dropped: {b - a} frame(s) between gaps, fewer than a window's "
                         f"{MIN_SEGMENT}")
    return segments, notes


def frame_edges(times: np.ndarray) -> np.ndarray:
    """Interval edges (t[-1], t[0], t[1], ...): the first frame's interval is one median step."""
    step = float(np.median(np.diff(times))) if len(times) > 1 else 0.2
    return np.concatenate([[times[0] - step], times])


def poses_at(times: np.ndarray, odom_times: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Odometry (x, y, yaw) interpolated linearly at frame times (yaw unwrapped, then wrapped)."""
    yaw = np.unwrap(poses[:, 2])
    out = np.stack([np.interp(times, odom_times, poses[:, 0]), np.interp(times, odom_times, poses[:, 1]),
                    np.interp(times, odom_times, yaw)], axis=1)
    out[:, 2] = (out[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return out
