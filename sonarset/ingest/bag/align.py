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


def split_at_gaps(times: np.ndarray, tolerance: float = 0.05,
                  reference_s: float | None = None) -> tuple[list[Segment], list[str], float]:
    """Runs of frames without a lost ping, one summary note, and the frame interval (seconds).

    A real sensor loses pings (BatSLAM2's eRTIS drive: 95 of 1,186) and its clock jitters (a few
    per cent). An interval over ``GAP_FACTOR`` median intervals holds a lost ping: a window must not
    span it, so the run splits there; jitter alone never reaches it. The interval is the median of
    the intervals without a lost ping, what the store declares. A stretch too short for a window
    is dropped, and so is one whose own median interval strays from it by more than ``tolerance``
    (the format's frame-rate rule, spec/FORMAT.md section 7: a few jittery frames between two
    lost pings), so that what is written validates; ``reference_s``, where given, is the interval
    they must keep to instead (the frame interval an existing store declares). A drive can lose a
    hundred pings: the note counts them, it does not list them.
    """
    if len(times) < 2:
        return [Segment(0, len(times))], [], 0.2
    dt = np.diff(times)
    nominal = float(np.median(dt))
    gaps = dt > GAP_FACTOR * nominal
    interval = float(np.median(dt[~gaps])) if (~gaps).any() else nominal
    keep_to = interval if reference_s is None else reference_s
    cuts = np.flatnonzero(gaps) + 1
    bounds = [0, *cuts.tolist(), len(times)]
    segments, short, off_rate, dropped = [], 0, 0, 0
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < MIN_SEGMENT:
            short, dropped = short + 1, dropped + b - a
        elif abs(float(np.median(dt[a:b - 1])) - keep_to) > tolerance * keep_to:
            off_rate, dropped = off_rate + 1, dropped + b - a
        else:
            segments.append(Segment(a, b))
    if not cuts.size:
        return segments, [], interval
    lost = int(np.sum(np.maximum(np.round(dt[gaps] / interval) - 1, 1)))
    longest = float(dt[gaps].max())
    note = (f"{lost} lost ping(s) at {cuts.size} gap(s) (intervals over {GAP_FACTOR:g} x the median "
            f"{interval:.4g} s, the longest {longest:.3g} s): {len(segments)} run(s) split at the gaps, "
            "so that no window spans one")
    if dropped:
        why = [f"{short} shorter than a window's {MIN_SEGMENT} frames"] if short else []
        why += [f"{off_rate} whose jitter puts their median interval over {tolerance:.0%} off"] if off_rate else []
        note += f"; {dropped} frame(s) dropped in {short + off_rate} stretch(es) between gaps ({', '.join(why)})"
    return segments, [note], interval


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
