"""The clock offset between a bag's commands and its images, estimated from the data.

A controller's clock and a sensor's can disagree by seconds (BatSLAM2 fitted a 7.00 s sonar-lidar
offset by hand), and a bag imported with such an offset is silently misaligned: every command
pairs with frames seconds away from the motion it caused. The images say when the robot moved:

- the image motion at frame k, from frames k-1 and k: the shift (in bins, sub-bin) that best
  aligns their range profiles (forward motion brings echoes closer), the same along azimuth
  (turning sweeps them across the beams), and how much the frames differ at all;
- the commanded motion over each frame interval, the held command (``align.held_mean``) times the
  interval: signed and absolute forward and turning displacement, the commands shifted by a lag;
- over candidate lags (+-``MAX_LAG_S``, half a frame interval apart, 401 at most), how much of
  the image motion the commanded motion explains (R^2 of a least-squares fit, averaged over the
  three signals); the best lag is refined by a parabola through its neighbours.

The lag is the offset to add to the command stamps (``command_offset_s``). Its confidence is how
far the best fit stands above the fits at lags more than a second away (in their standard
deviations) and how much it explains: images without motion in them (noise, a robot standing
still) give no confident estimate, and nothing is said about them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np

from sonarset.ingest.bag.align import command_coverage, held_mean

MAX_LAG_S = 10.0
#: An estimate is confident when its fit explains this much of the image motion, and CHANCE_FACTOR
#: times what its 4 regressors explain of noise by chance (4 / frames; 40 frames of noise reach 0.2)...
MIN_R2 = 0.1
CHANCE_FACTOR = 8.0
#: ...and stands this many standard deviations above the fits at other lags (noise: up to ~6.5).
MIN_SIGMA = 8.0
#: A confident offset beyond this many frame intervals (and 0.25 s) is worth a warning.
WARN_FRAMES = 1.5
MIN_FRAMES = 30


@dataclass(frozen=True)
class OffsetEstimate:
    """``offset_s``: the shift to add to the command stamps that best aligns them with the images'
    motion; ``r2``: how much of that motion it explains; ``sigma``: how far above the other lags."""

    offset_s: float
    r2: float
    sigma: float
    confident: bool

    def describe(self) -> str:
        return f"{self.offset_s:+.2f} s (R^2 {self.r2:.2f}, {self.sigma:.0f} sigma over other lags)"

    def as_attr(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def image_motion(frames: Sequence[np.ndarray], max_shift: int | None = None) -> np.ndarray:
    """(n, 3) per frame: the range shift and azimuth shift (bins) that best align frame k-1 with
    frame k, and their mean absolute difference; row 0 is zero."""
    n = len(frames)
    out = np.zeros((n, 3))
    if n < 2:
        return out
    by_range = np.stack([np.mean(f, axis=1, dtype=np.float64) for f in frames])
    by_azimuth = np.stack([np.mean(f, axis=0, dtype=np.float64) for f in frames])
    out[1:, 0] = _best_shift(by_range, max_shift)
    out[1:, 1] = _best_shift(by_azimuth, max_shift)
    prev = np.asarray(frames[0], np.float32)
    for k in range(1, n):  # a frame at a time: a long drive is never float at once
        cur = np.asarray(frames[k], np.float32)
        out[k, 2] = float(np.abs(cur - prev).mean())
        prev = cur
    return out


def _best_shift(profiles: np.ndarray, max_shift: int | None) -> np.ndarray:
    """For each consecutive pair of profiles (rows), the shift s (sub-bin) at which
    profile[k][i + s] best matches profile[k-1][i] (normalised correlation)."""
    n_bins = profiles.shape[1]
    s_max = max(1, min(n_bins // 3, max_shift if max_shift is not None else max(3, n_bins // 8)))
    p = profiles - profiles.mean(axis=1, keepdims=True)
    prev, cur = p[:-1], p[1:]
    shifts = np.arange(-s_max, s_max + 1)
    corr = np.empty((len(prev), len(shifts)))
    for j, s in enumerate(shifts):
        lo, hi = max(0, -s), n_bins - max(0, s)  # prev[i] against cur[i + s]
        a, b = prev[:, lo:hi], cur[:, lo + s:hi + s]
        denom = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
        corr[:, j] = np.where(denom > 0, (a * b).sum(axis=1) / np.where(denom > 0, denom, 1), 0.0)
    j = corr.argmax(axis=1)
    inner = (j > 0) & (j < len(shifts) - 1)
    jj = np.clip(j, 1, len(shifts) - 2)
    rows = np.arange(len(j))
    y0, y1, y2 = corr[rows, jj - 1], corr[rows, jj], corr[rows, jj + 1]
    curve = y0 - 2 * y1 + y2
    frac = np.where(inner & (curve < 0), 0.5 * (y0 - y2) / np.where(curve < 0, curve, -1), 0.0)
    return shifts[j] + np.clip(frac, -0.5, 0.5)


def estimate_offset(frame_times: np.ndarray, frames: Sequence[np.ndarray], command_times: np.ndarray,
                    v: np.ndarray, omega: np.ndarray, timeout_s: float,
                    max_lag_s: float = MAX_LAG_S) -> OffsetEstimate | None:
    """The offset to add to the command stamps that best aligns the commanded motion with the
    images' (module docstring); None where there are too few frames or commands to say."""
    t = np.asarray(frame_times, np.float64)
    if len(t) < MIN_FRAMES or len(command_times) < 2:
        return None
    motion = image_motion(frames)
    return estimate_from_motion(t, motion, np.asarray(command_times, np.float64), np.asarray(v, np.float64),
                                np.asarray(omega, np.float64), timeout_s, max_lag_s)


def estimate_from_motion(t: np.ndarray, motion: np.ndarray, cmd_t: np.ndarray, v: np.ndarray, omega: np.ndarray,
                         timeout_s: float, max_lag_s: float = MAX_LAG_S) -> OffsetEstimate | None:
    """``estimate_offset`` from the image motion signals (``image_motion``) already taken."""
    dt = np.diff(t)
    interval = float(np.median(dt))
    if not interval > 0:
        return None
    edges = t  # frame k's interval (t[k-1], t[k]]: rows 1..n-1
    signals = motion[1:]
    keep = signals.std(axis=0) > 1e-12
    if not keep.any():
        return None
    signals = (signals[:, keep] - signals[:, keep].mean(axis=0)) / signals[:, keep].std(axis=0)
    lags = np.arange(-max_lag_s, max_lag_s + 1e-9, max(interval / 2, max_lag_s / 200))  # at most 401
    scores = np.full(len(lags), np.nan)
    for i, lag in enumerate(lags):
        scores[i] = _fit(signals, edges, dt, cmd_t + lag, v, omega, timeout_s)
    if np.isnan(scores).all():
        return None
    best = int(np.nanargmax(scores))
    offset = float(lags[best])
    if 0 < best < len(lags) - 1 and np.isfinite(scores[best - 1:best + 2]).all():
        y0, y1, y2 = scores[best - 1:best + 2]
        curve = y0 - 2 * y1 + y2
        if curve < 0:
            offset += float(np.clip(0.5 * (y0 - y2) / curve, -0.5, 0.5)) * (lags[1] - lags[0])
    far = scores[(np.abs(lags - lags[best]) > max(1.0, 3 * interval)) & np.isfinite(scores)]
    spread = float(far.std()) if far.size > 2 else 0.0
    sigma = float((scores[best] - far.mean()) / spread) if spread > 0 else 0.0
    r2 = float(scores[best])
    enough = max(MIN_R2, CHANCE_FACTOR * 4 / len(dt))
    return OffsetEstimate(float(offset), r2, sigma, bool(r2 >= enough and sigma >= MIN_SIGMA))


def _fit(signals: np.ndarray, edges: np.ndarray, dt: np.ndarray, cmd_t: np.ndarray, v: np.ndarray,
         omega: np.ndarray, timeout_s: float) -> float:
    """Mean R^2 of the image motion signals on the commanded motion over the frames the commands
    (at this lag) reach; NaN when they reach too few."""
    covered = command_coverage(cmd_t, edges, timeout_s)
    if covered.sum() < max(MIN_FRAMES, len(dt) // 2):
        return np.nan
    fv, fw = held_mean(cmd_t, v, edges, timeout_s) * dt, held_mean(cmd_t, omega, edges, timeout_s) * dt
    design = np.stack([np.ones_like(fv), fv, fw, np.abs(fv), np.abs(fw)], axis=1)[covered]
    y = signals[covered]
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    resid = y - design @ coef
    total = ((y - y.mean(axis=0)) ** 2).sum(axis=0)
    ok = total > 0
    return float(np.mean(1 - (resid[:, ok] ** 2).sum(axis=0) / total[ok])) if ok.any() else np.nan


def offset_warning(estimate: OffsetEstimate | None, interval_s: float, applied_s: float) -> str | None:
    """One line when a confident estimate is far from zero (beyond ``WARN_FRAMES`` frame intervals
    and 0.25 s), naming the offset that aligns the commands; else None."""
    if estimate is None or not estimate.confident or \
            abs(estimate.offset_s) <= max(0.25, WARN_FRAMES * interval_s):
        return None
    total = applied_s + estimate.offset_s
    return (f"the commands match the images' motion best {abs(estimate.offset_s):.2f} s "
            f"{'later' if estimate.offset_s > 0 else 'earlier'} than stamped (R^2 {estimate.r2:.2f}, "
            f"{estimate.sigma:.0f} sigma over other lags): "
            f"a clock offset between controller and sensor? (command_offset_s {total:.2f} aligns them)")


def command_clock(streams, offset_s: float, timeout_s: float) -> OffsetEstimate | None:
    """``estimate_offset`` for a bag's streams (``reader.BagStreams``: image frames, commands), the
    commands shifted by the ``offset_s`` already given: what remains."""
    cmd = streams.commands
    return estimate_offset(streams.frames.times, streams.frames.values["images"], cmd.times + offset_s,
                           cmd.values["v"], cmd.values["omega"], timeout_s)


def offset_hint(estimate: OffsetEstimate | None, applied_s: float) -> str:
    """What to add to a problem of commands that reach no frame when a confident estimate puts
    them off by more than 0.25 s; else ''."""
    if estimate is None or not estimate.confident or abs(estimate.offset_s) <= 0.25:
        return ""
    return (f"; the images' motion puts the commands {estimate.offset_s:+.2f} s off "
            f"(command_offset_s {applied_s + estimate.offset_s:.2f} aligns them)")
