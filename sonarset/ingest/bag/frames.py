"""Sonar frames from ``ProjectedSonarImage`` and ``sensor_msgs/Image`` messages, on one grid.

A ProjectedSonarImage carries its geometry: range-bin centres and one unit direction per beam
in the sensor frame (Z forward, X up, so Y right); its pixels are range-major (index =
range_bin * beam_count + beam) in any of ten dtypes, either byte order. Beams are put in the
store's order (azimuth increasing, left positive); beams or ranges that are not uniformly spaced
are resampled onto the uniform grid with the same extent and count (linear, ``scipy``), with a
note. A ``sensor_msgs/Image`` (mono8, mono16, 32FC1...) has rows = range bins and columns =
beams in azimuth order, and takes its grid from the sidecar.
"""

from __future__ import annotations

import numpy as np

from sonarset.errors import one_line
from sonarset.format.attrs import SensorGrid
import sonarset.ingest.bag.messages as m

UNIFORM_RTOL = 1e-4  # the store's own tolerance (format.attrs._uniform_edges)


class FrameDecoder:
    """Decodes one topic's frames; the first message fixes the geometry every later one must share."""

    def __init__(self, topic: str, grid: SensorGrid | None):
        self.topic, self.grid = topic, grid
        self.msgtype: str | None = None
        self.dtype: str | None = None
        self.notes: list[str] = []
        self._ranges = self._azimuths = None
        self._order = None  # beam permutation into increasing azimuth
        self._skip = 0  # leading range bins dropped: centred so near the sensor that they reach behind it
        self._message_azimuths = None  # the first message's beam azimuths, in its order
        self._resample = None  # (range, azimuth) resamplers, when the beams or bins are not uniform

    def decode(self, index: int, msg, problems: list[str]) -> np.ndarray | None:
        where = f"topic {self.topic!r}, message {index}"
        try:
            if hasattr(msg, "beam_directions"):
                self.msgtype = getattr(msg, "__msgtype__", m.SONAR_IMAGE)
                return self._sonar_image(where, msg, problems)
            self.msgtype = m.PLAIN_IMAGE
            return self._plain_image(where, msg, problems)
        except (ValueError, TypeError) as exc:
            problems.append(f"{where}: {one_line(exc)}")
            return None

    def _sonar_image(self, where: str, msg, problems: list[str]) -> np.ndarray | None:
        data = msg.image
        if data.dtype not in m.SONAR_DTYPES:
            problems.append(f"{where}: unknown SonarImageData dtype {data.dtype} (0-9 are defined)")
            return None
        dtype = np.dtype(m.SONAR_DTYPES[data.dtype]).newbyteorder(">" if data.is_bigendian else "<")
        ranges = np.asarray(msg.ranges, np.float64)
        beams = int(data.beam_count)
        directions = np.array([(d.x, d.y, d.z) for d in msg.beam_directions], np.float64).reshape(-1, 3)
        if len(directions) != beams:
            problems.append(f"{where}: {len(directions)} beam directions for beam_count {beams}")
            return None
        azimuths = m.beam_azimuths(directions)  # in the message's beam order, which may change
        if self._ranges is None:
            if not self._set_geometry(where, ranges, azimuths, problems):
                return None
            self._message_azimuths = azimuths
        elif len(ranges) != len(self._ranges) or not np.allclose(ranges, self._ranges, rtol=1e-6, atol=1e-9) \
                or beams != len(self._order) or not np.allclose(azimuths, self._message_azimuths, rtol=0, atol=1e-6):
            problems.append(f"{where}: the ranges or beams (their number, directions or order) differ from the "
                            "first message's; a run has one sensor grid")
            return None
        if not self._same_pixels(where, dtype, problems):
            return None
        raw = np.asarray(data.data, np.uint8)
        need = len(ranges) * beams * dtype.itemsize
        if raw.size != need:
            problems.append(f"{where}: image data has {raw.size} bytes, {len(ranges)} ranges x {beams} beams "
                            f"of {dtype.name} need {need}")
            return None
        image = raw.view(dtype).reshape(len(ranges), beams)
        return self._to_grid(image.astype(dtype.newbyteorder("="), copy=False))

    def _plain_image(self, where: str, msg, problems: list[str]) -> np.ndarray | None:
        if self.grid is None:
            problems.append(f"{where}: a sensor_msgs/Image carries no range or azimuth: give the grid in the "
                            "sidecar (its 'grid')")
            return None
        kind = m.PLAIN_ENCODINGS.get(msg.encoding)
        if kind is None:
            problems.append(f"{where}: image encoding {msg.encoding!r} is not a single-channel one "
                            f"({', '.join(m.PLAIN_ENCODINGS)})")
            return None
        dtype = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
        rows, cols, step = int(msg.height), int(msg.width), int(msg.step)
        if (rows, cols) != self.grid.shape:
            problems.append(f"{where}: image is {rows} x {cols} (range x azimuth), the grid is "
                            f"{self.grid.shape[0]} x {self.grid.shape[1]}")
            return None
        raw = np.asarray(msg.data, np.uint8)
        if step < cols * dtype.itemsize or raw.size != rows * step:
            problems.append(f"{where}: image data has {raw.size} bytes, {rows} rows of step {step} need "
                            f"{rows * step} (and a step of at least {cols * dtype.itemsize})")
            return None
        if not self._same_pixels(where, dtype, problems):
            return None
        image = raw.reshape(rows, step)[:, :cols * dtype.itemsize].copy().view(dtype)
        return image.astype(dtype.newbyteorder("="), copy=False)

    def _same_pixels(self, where: str, dtype: np.dtype, problems: list[str]) -> bool:
        """Whether ``dtype``'s values are the first message's kind (either byte order: each message
        says its own); the first message's sets it. One run has one pixel type, which the store's
        value rule (uint8 / 255, uint16 / 65535, ...) is made from."""
        native = dtype.newbyteorder("=")
        if self.dtype is None:
            self.dtype = native.str
        elif native != np.dtype(self.dtype):
            problems.append(f"{where}: pixels are {native.name}, the first message's {np.dtype(self.dtype).name}; "
                            "a run has one pixel type")
            return False
        return True

    def _set_geometry(self, where: str, ranges: np.ndarray, azimuths: np.ndarray, problems: list[str]) -> bool:
        if len(ranges) < 2 or len(azimuths) < 2:
            problems.append(f"{where}: a sonar image needs at least 2 ranges and 2 beams")
            return False
        if not (np.isfinite(ranges).all() and np.isfinite(azimuths).all()):
            problems.append(f"{where}: ranges or beam directions are not finite")
            return False
        order = np.argsort(azimuths, kind="stable")
        if np.any(np.diff(azimuths[order]) <= 0):
            problems.append(f"{where}: two beams point the same way")
            return False
        if np.any(np.diff(ranges) <= 0):
            problems.append(f"{where}: range bins must increase")
            return False
        if np.all(np.diff(order) < 0):
            self.notes.append("beams run right to left in the messages; stored left-positive, as the spec says")
        az = azimuths[order]
        self._ranges, self._azimuths, self._order = ranges, az, order
        # Many sonars report their first sample at 0 m (the transmit itself): a bin centred there
        # reaches behind the sensor, which no grid can hold. Such bins are dropped, and said so.
        # (a first centre a rounding error below 0 m is the same case; one further below is refused)
        self._skip = 0
        while len(ranges) - self._skip >= 2 and ranges[self._skip] >= -1e-3 * _half_step(ranges) \
                and ranges[self._skip] < _half_step(ranges[self._skip:]):
            self._skip += 1
        if self._skip:
            if len(ranges) - self._skip < 2:
                problems.append(f"{where}: a sonar image needs at least 2 ranges beyond the sensor")
                return False
            kept = ranges[self._skip]
            self.notes.append(f"the range bin{'s' if self._skip > 1 else ''} at {ranges[0]:g}"
                              f"{f'..{ranges[self._skip - 1]:g}' if self._skip > 1 else ''} m dropped (a bin there "
                              f"reaches behind the sensor); frames start at the bin at {kept:g} m")
            ranges = ranges[self._skip:]
        uniform_r, uniform_a = _uniform(ranges), _uniform(az)
        grid = _grid_of(where, ranges, az, uniform_r and uniform_a, problems)
        if grid is None:
            return False
        if not (uniform_r and uniform_a):
            self._resample = (None if uniform_r else (ranges, grid.range_centres()),
                              None if uniform_a else (az, grid.azimuth_centres()))
            which = " and ".join(w for w, u in (("range bins", uniform_r), ("beams", uniform_a)) if not u)
            self.notes.append(f"{which} are not uniformly spaced: resampled linearly onto {grid.describe()}")
        if self.grid is not None and not self.grid.matches(grid, rtol=1e-4):
            problems.append(f"{where}: the messages' grid {grid.describe()} differs from the given "
                            f"{self.grid.describe()}")
            return False
        self.grid = grid
        return True

    def _to_grid(self, image: np.ndarray) -> np.ndarray:
        """The image on the store's grid, in its own pixel type (a long drive of uint8 frames is held
        as uint8 until it is written, a chunk at a time); float32 where it had to be resampled."""
        image = image[self._skip:, self._order]
        if self._resample is None:
            return np.ascontiguousarray(image)
        from scipy.interpolate import interp1d

        image = image.astype(np.float32)
        along_r, along_a = self._resample
        if along_a is not None:
            image = interp1d(along_a[0], image, axis=1, bounds_error=False,
                             fill_value=(image[:, 0], image[:, -1]))(along_a[1])
        if along_r is not None:
            image = interp1d(along_r[0], image, axis=0, bounds_error=False,
                             fill_value=(image[0], image[-1]))(along_r[1])
        return np.ascontiguousarray(image, np.float32)


def _grid_of(where: str, ranges: np.ndarray, az: np.ndarray, uniform: bool, problems: list[str]) -> SensorGrid | None:
    """The grid whose bin centres are ``ranges`` and ``az`` (edges half a bin beyond the outer
    centres), or None and a problem naming the ranges or beams that make none."""
    from pydantic import ValidationError

    r_half = _half_step(ranges)
    a_half = (az[-1] - az[0]) / (len(az) - 1) / 2
    edges = (float(ranges[0] - r_half), float(ranges[-1] + r_half), float(az[0] - a_half), float(az[-1] + a_half))
    span = f"ranges {ranges[0]:g}..{ranges[-1]:g} m ({len(ranges)} bins)"
    if edges[0] < 0:
        problems.append(f"{where}: {span} put the first bin's near edge at {edges[0]:g} m, below zero; a sonar's "
                        "ranges are distances from it")
        return None
    if edges[2] < -np.pi - 1e-9 or edges[3] > np.pi + 1e-9:
        problems.append(f"{where}: beams at {np.degrees(az[0]):g}..{np.degrees(az[-1]):g} deg ({len(az)}) put the "
                        "outer bins' edges beyond -180..180 deg")
        return None
    try:
        if uniform:
            return SensorGrid.from_centres(ranges, az)
        return SensorGrid(range_min_m=edges[0], range_max_m=edges[1], n_range=len(ranges), n_azimuth=len(az),
                          azimuth_min_rad=edges[2], azimuth_max_rad=edges[3])
    except (ValidationError, ValueError) as exc:
        errors = exc.errors() if isinstance(exc, ValidationError) else [{"msg": str(exc)}]
        why = "; ".join(str(e.get("msg", "invalid")).removeprefix("Value error, ") for e in errors)
        problems.append(f"{where}: {span} and {len(az)} beams make no sensor grid: {why}")
        return None


def _half_step(centres: np.ndarray) -> float:
    return float(centres[-1] - centres[0]) / (len(centres) - 1) / 2


def _uniform(centres: np.ndarray) -> bool:
    step = np.diff(centres)
    return bool(np.max(np.abs(step - step.mean())) <= UNIFORM_RTOL * step.mean())
