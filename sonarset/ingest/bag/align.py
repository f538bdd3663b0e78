"""Commands and poses onto the sonar's frames, and the gaps where pings were dropped.

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
MAX_LOST = 5  # pings lost in a row that a run keeps, as a recorded gap; a longer gap splits it
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
    """Frames ``start:stop`` of a recording, one run, and the gaps it keeps: ``(k, lost)``, ``lost``
    pings missing between its frames k-1 and k (the run attribute ``gaps``, spec/FORMAT.md section 4)."""

    start: int
    stop: int
    gaps: tuple[tuple[int, int], ...] = ()


def split_at_gaps(times: np.ndarray, tolerance: float = 0.05,
                  reference_s: float | None = None) -> tuple[list[Segment], list[str], float]:
    """Runs of frames, the gaps each keeps, one summary note, and the frame interval (seconds).

    A real sensor loses pings (BatSLAM2's eRTIS drive: 95 of 1,186) and its clock jitters (a few
    per cent). An interval over ``GAP_FACTOR`` median intervals holds lost pings (jitter alone never
    reaches it): round(interval / median) - 1 of them. A gap of up to ``MAX_LOST`` pings stays
    inside its run, recorded (``Segment.gaps``): windows never span one (``sonarset.windows``), so
    a drive that loses one ping in twelve stays one run. A longer gap (the sensor stopped) splits
    the run. The interval is the median of the intervals without a lost ping, what the store
    declares. A run too short for a window is dropped; so is one whose median interval (gaps
    included, as ``validate`` measures it) strays from it by more than ``tolerance`` (the format's
    frame-rate rule, spec/FORMAT.md section 7): such a run is first split at each of its gaps and
    its pieces kept where they keep to the rate. ``reference_s``, where given, is the interval
    they must keep to instead (the frame interval an existing store declares). A drive can lose a
    hundred pings: the note counts them, it does not list them.
    """
    if len(times) < MIN_SEGMENT:  # no run: not even a rate to measure
        return [], [f"{len(times)} frame(s) left, a run needs at least {MIN_SEGMENT}"], 0.0
    dt = np.diff(times)
    nominal = float(np.median(dt))
    gap = dt > GAP_FACTOR * nominal
    interval = float(np.median(dt[~gap])) if (~gap).any() else nominal
    keep_to = interval if reference_s is None else reference_s
    lost = np.zeros(len(dt), np.int64)
    lost[gap] = np.maximum(np.round(dt[gap] / interval) - 1, 1)
    long = np.flatnonzero(lost > MAX_LOST) + 1
    segments: list[Segment] = []
    drops = {"short": 0, "off": 0, "frames": 0}
    for a, b in zip([0, *long.tolist()], [*long.tolist(), len(times)]):
        _keep(a, b, dt, lost, keep_to, tolerance, segments, drops, whole=True)
    if not gap.any():
        if not segments and drops["off"] and reference_s is not None:  # a steady drive at another rate
            return [], [f"the frames are {interval:.4g} s apart, the store declares {reference_s:.4g} s frames"], interval
        return segments, [], interval
    kept = sum(len(s.gaps) for s in segments)
    note = (f"{int(lost.sum())} lost ping(s) at {int(gap.sum())} gap(s) (intervals over {GAP_FACTOR:g} x the median "
            f"{interval:.4g} s, the longest {float(dt[gap].max()):.3g} s): {len(segments)} run(s)")
    note += f", split at {long.size} gap(s) of over {MAX_LOST} pings" if long.size else ""
    note += f"; {kept} gap(s) recorded in their runs, which no window spans" if kept else ""
    if drops["frames"]:
        why = [f"{drops['short']} shorter than a window's {MIN_SEGMENT} frames"] if drops["short"] else []
        if drops["off"]:
            why.append(f"{drops['off']} whose jitter puts their median interval over {tolerance:.0%} off")
        note += (f"; {drops['frames']} frame(s) dropped in {drops['short'] + drops['off']} stretch(es) between gaps "
                 f"({', '.join(why)})")
    return segments, [note], interval


def _keep(a: int, b: int, dt: np.ndarray, lost: np.ndarray, keep_to: float, tolerance: float,
          segments: list[Segment], drops: dict, whole: bool) -> None:
    """Frames a:b as a run with its gaps, or, where its rate strays, its stretches between gaps."""
    if b - a < MIN_SEGMENT:
        drops["short"], drops["frames"] = drops["short"] + 1, drops["frames"] + b - a
    elif abs(float(np.median(dt[a:b - 1])) - keep_to) <= tolerance * keep_to:
        inside = np.flatnonzero(lost[a:b - 1]) + 1  # frame k of the run follows lost pings
        segments.append(Segment(a, b, tuple((int(k), int(lost[a + k - 1])) for k in inside)))
    elif whole and lost[a:b - 1].any():
        cuts = (np.flatnonzero(lost[a:b - 1]) + a + 1).tolist()
        for c, d in zip([a, *cuts], [*cuts, b]):
            _keep(c, d, dt, lost, keep_to, tolerance, segments, drops, whole=False)
    else:
        drops["off"], drops["frames"] = drops["off"] + 1, drops["frames"] + b - a


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
