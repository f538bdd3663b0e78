"""The arrays of a run group (spec/FORMAT.md §2) and the rules on them: their metadata, their
values, and the checks every writer applies before it writes. Each rule returns Problems located
at the array's key (``images``), which the caller places in its run (``Problem.at``)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from sonarset.format.attrs import SensorGrid, requires_checksums
from sonarset.format.problems import Problem


@dataclass(frozen=True)
class ArraySpec:
    dims: tuple[str, ...]
    dtypes: tuple[str, ...]
    required: bool
    write_dtype: str  # what the reference writer stores (images: float16 unless asked otherwise)
    last: int | None = None  # fixed size of the last axis, if any
    units: str | None = None
    description: str = ""

    def layout(self) -> str:
        """The shape this array must have, in words (``T`` frames; a grid's bins are the store's)."""
        if self.dims[0] != "time":
            return "a 1-D array of bin centres"
        if self.last is None and len(self.dims) > 1:
            return f"{len(self.dims)}-D ({', '.join(self.dims)})"
        return f"shape (T, {self.last})" if self.last is not None else "shape (T,)"


#: Every array a run group may hold. Time-indexed arrays all have length n_frames.
ARRAYS: dict[str, ArraySpec] = {
    "images": ArraySpec(("time", "range", "azimuth"), ("float16", "float32"), True, "float16",
                        units="1", description="energyscape, log energy in [0, 1]"),
    "velocity": ArraySpec(("time", "velocity_component"), ("float32", "float64"), True, "float32", last=2,
                          units="m/s, rad/s", description="command (v, omega) that moved the robot from frame k-1 to k"),
    "time": ArraySpec(("time",), ("float64",), True, "float64", units="s", description="frame time stamps"),
    "range": ArraySpec(("range",), ("float64", "float32"), True, "float64", units="m", description="range bin centres"),
    "azimuth": ArraySpec(("azimuth",), ("float64", "float32"), True, "float64", units="rad",
                         description="azimuth bin centres, positive to the left"),
    "pose": ArraySpec(("time", "pose_component"), ("float64", "float32"), False, "float64", last=3,
                      units="m, m, rad", description="ground-truth robot pose (x, y, heading) in the world frame"),
    "snr_db": ArraySpec(("time",), ("float32", "float64"), False, "float32", units="dB",
                        description="per-frame SNR at the microphones"),
    "slip": ArraySpec(("time", "wheel"), ("float32", "float64"), False, "float32", last=2, units="1",
                      description="wheel speed factors (left, right); 1 = no slip"),
}
OPTIONAL_ARRAYS = [k for k, s in ARRAYS.items() if not s.required]
#: The arrays indexed by frame (their first axis is ``time``), and those no run can lack.
FRAME_ARRAYS = tuple(k for k, s in ARRAYS.items() if s.dims[0] == "time")
REQUIRED_FRAME_ARRAYS = tuple(k for k in FRAME_ARRAYS if ARRAYS[k].required)


def expected_shape(key: str, n_frames: int, grid_shape: tuple[int, int]) -> tuple[int, ...]:
    """The shape array ``key`` must have in a run of ``n_frames`` frames on a grid (R, A)."""
    spec = ARRAYS[key]
    sizes = {"time": n_frames, "range": grid_shape[0], "azimuth": grid_shape[1]}
    return tuple(sizes.get(d, spec.last) for d in spec.dims)


def coordinate_problems(key: str, values: np.ndarray, grid: SensorGrid) -> list[Problem]:
    """A run's coordinate array (``range`` or ``azimuth``) against the grid's bin centres, to 1e-6
    of their scale (spec/FORMAT.md §2, Values)."""
    centres = grid.range_centres() if key == "range" else grid.azimuth_centres()
    tol = 1e-6 * max(1.0, float(np.max(np.abs(centres))))
    if values.shape == centres.shape and np.allclose(values, centres, rtol=0, atol=tol):
        return []
    unit = ARRAYS[key].units
    return [Problem(key, f"coordinates do not match the store grid (got {values[0]:.6g}..{values[-1]:.6g} {unit}, "
                         f"grid {centres[0]:.6g}..{centres[-1]:.6g} {unit})")]


_ONE_BITS = {np.dtype(np.float16): (np.uint16, 0x3C00, 0x8000), np.dtype(np.float32): (np.uint32, 0x3F800000, 0x80000000)}


def in_unit_interval(images: np.ndarray) -> bool:
    """All values finite and in [0, 1], in one integer pass over the bit patterns.

    Non-negative IEEE floats order like their bit patterns; negatives set the sign bit and NaN/inf
    lie above 1.0, so ``bits <= bits(1.0)`` (or -0.0) is exactly the test. Float16 min/max in
    NumPy are several times slower than this.
    """
    spec = _ONE_BITS.get(images.dtype)
    if spec is None:
        return bool(np.all(np.isfinite(images)) and images.min() >= 0 and images.max() <= 1)
    utype, one, negzero = spec
    bits = np.ascontiguousarray(images).view(utype).reshape(-1)  # a flat max is ~1.5x faster than a 3-D one
    if bits.max() <= one:
        return True
    return not bool(np.any((bits > one) & (bits != negzero)))


#: How far the median spacing of a run's time stamps may stray from the declared frame interval
#: (relative). Clock jitter and the odd dropped frame stay well inside it; the mistakes it exists
#: for (a 10 Hz recording declared 5 Hz, milliseconds declared as seconds) are factors of 2 to 1000.
FRAME_INTERVAL_TOLERANCE = 0.05


def median_interval(time: np.ndarray) -> float | None:
    """The median spacing of time stamps, seconds; None for fewer than two."""
    t = np.asarray(time, dtype=np.float64)
    return float(np.median(np.diff(t))) if t.size > 1 else None


def recorded_gap_frames(raw: object) -> np.ndarray:
    """The frames that follow a gap of a run's ``gaps`` record (``[[frame, lost], ...]``, spec/FORMAT.md
    §4), leniently: a malformed record gives none here (reading the run's windows refuses it)."""
    try:
        pairs = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
    except (TypeError, ValueError):
        return np.zeros(0, np.int64)
    ok = np.isfinite(pairs).all(1) & (pairs[:, 0] >= 1)
    return np.unique(pairs[ok, 0].astype(np.int64))


def frame_interval_problems(time: np.ndarray, frame_rate_hz: float, gap_frames: np.ndarray | None = None) -> list[Problem]:
    """The time stamps' median spacing against the declared ``frame_rate_hz`` (spec/FORMAT.md §7);
    the spacings across recorded gaps (``gap_frames``: the frames that follow one) are left out."""
    t = np.asarray(time, dtype=np.float64)
    if gap_frames is not None and len(gap_frames) and t.size > 1:
        keep = np.ones(t.size - 1, bool)
        keep[np.asarray(gap_frames)[(gap_frames >= 1) & (gap_frames < t.size)] - 1] = False
        steps = np.diff(t)[keep]
        dt = float(np.median(steps)) if steps.size else None
    else:
        dt = median_interval(t)
    if dt is None or not math.isfinite(dt) or frame_rate_hz <= 0:
        return []
    nominal = 1.0 / frame_rate_hz
    if abs(dt - nominal) <= FRAME_INTERVAL_TOLERANCE * nominal:
        return []
    ratio = dt / nominal
    hint = ""
    if 500 <= ratio <= 2000:
        hint = "; milliseconds declared as seconds?"
    elif 5e-4 <= ratio <= 2e-3:
        hint = "; seconds declared as milliseconds?"
    else:
        hint = f"; is the recording at {1 / dt:.3g} Hz?" if dt > 0 else ""
    return [Problem("time", f"time stamps are {dt:.6g} s apart (median), but the store declares frame_rate_hz "
                            f"{frame_rate_hz:g} ({nominal:g} s frames, tolerance {FRAME_INTERVAL_TOLERANCE:.0%}){hint}")]


def array_meta_problems(key: str, dtype: str, dims: tuple[str, ...] | None, shape: tuple[int, ...],
                        n_frames: int, grid_shape: tuple[int, int]) -> list[Problem]:
    """Array ``key``'s metadata in a run of ``n_frames`` frames on a grid (R, A) against the spec
    (FORMAT.md §2): dtype, dimension names, shape."""
    spec = ARRAYS[key]
    expected = expected_shape(key, n_frames, grid_shape)
    out = []
    if dtype not in spec.dtypes:
        out.append(Problem(key, f"dtype {dtype} not allowed (expected {' or '.join(spec.dtypes)})"))
    if tuple(dims or ()) != spec.dims:
        out.append(Problem(key, f"dimension_names {list(dims) if dims else None} must be {list(spec.dims)}"))
    if tuple(shape) != tuple(expected):
        out.append(Problem(key, f"shape {tuple(shape)} does not match {tuple(expected)} "
                                f"(n_frames={n_frames}, grid {grid_shape[0]}x{grid_shape[1]})"))
    return out


#: The Zarr v3 codec that checksums each chunk (FORMAT.md §2, Checksums).
CHECKSUM_CODEC = "crc32c"


@dataclass(frozen=True)
class MissingChecksum(Problem):
    """An array of a format 1.2 store whose chunks carry no checksum. Its data still reads (zarr
    needs no checksum to decode), so readers do not refuse it; ``validate`` reports it."""

    refused_by_readers: ClassVar[bool] = False


def checksummed(codecs: Sequence[Mapping[str, Any]]) -> bool:
    """Whether a codec chain (``zarr.json``'s ``codecs``, as dicts) ends with the crc32c codec, or,
    for a sharded array, the chain of its inner chunks does."""
    if not codecs:
        return False
    last = codecs[-1]
    if last.get("name") == CHECKSUM_CODEC:
        return True
    if last.get("name") == "sharding_indexed":
        return checksummed((last.get("configuration") or {}).get("codecs") or ())
    return False


def checksum_problems(key: str, codecs: Sequence[Mapping[str, Any]], format_version: str) -> list[Problem]:
    """From format 1.2 every array's chunks end with a crc32c checksum (FORMAT.md §2, Checksums)."""
    if not requires_checksums(format_version) or checksummed(codecs):
        return []
    return [MissingChecksum(key, f"chunks carry no {CHECKSUM_CODEC} checksum: format {format_version} requires "
                                 f"the {CHECKSUM_CODEC} codec last in every array's codecs")]


def value_problems(key: str, block: np.ndarray, first_frame: int = 0) -> list[Problem]:
    """The first value of ``block`` (array ``key``, frames from ``first_frame``) that the spec
    forbids: images must be finite and in [0, 1], every other array finite (FORMAT.md §2, Values)."""
    if block.size == 0:
        return []
    if key == "images":
        if in_unit_interval(block):
            return []
    elif np.isfinite(block).all():
        return []
    return nonfinite_problems(key, block, first_frame) or unit_interval_problems(key, block, first_frame)


def nonfinite_problems(key: str, block: np.ndarray, first_frame: int = 0, unit: str = "frame") -> list[Problem]:
    """The first frame of ``block`` (frames from ``first_frame``) holding NaN or an infinity."""
    if block.size == 0:
        return []
    frames = block.reshape(block.shape[0], -1) if block.ndim > 1 else block[:, None]
    finite = np.isfinite(frames)
    if finite.all():
        return []
    k = first_frame + int(np.flatnonzero(~finite.all(axis=1))[0])
    return [Problem(key, f"NaN or infinite values (first at {unit} {k})", frame=k)]


def unit_interval_problems(key: str, block: np.ndarray, first_frame: int = 0) -> list[Problem]:
    """The first frame of ``block`` (frames from ``first_frame``) whose finite values lie outside [0, 1]."""
    if block.size == 0 or in_unit_interval(block):
        return []
    frames = block.reshape(block.shape[0], -1) if block.ndim > 1 else block[:, None]
    finite = np.isfinite(frames)
    outside = finite & ((frames < 0) | (frames > 1))
    if not outside.any():
        return []  # only NaN or infinities, which nonfinite_problems reports
    k = first_frame + int(np.flatnonzero(outside.any(axis=1))[0])
    values = frames[finite]
    return [Problem(key, f"values outside [0, 1] ({float(values.min()):g}..{float(values.max()):g}; first at frame {k})",
                    frame=k)]


def dtype_problems(key: str, arr) -> list[Problem]:
    """``arr`` (an array, or an array's header) must hold real numbers (integers or floats)."""
    dtype = getattr(arr, "dtype", None)
    if isinstance(dtype, np.dtype) and dtype.kind in "fiu":
        return []
    return [Problem(key, f"dtype {dtype if dtype is not None else type(arr).__name__} is not a real number type")]


def layout_problems(key: str, shape: tuple[int, ...]) -> list[Problem]:
    """An array ``key`` of ``shape`` must have the spec's number of axes and last axis."""
    spec = ARRAYS[key]
    if len(shape) == len(spec.dims) and (spec.last is None or shape[-1] == spec.last):
        return []
    return [Problem(key, f"expected {spec.layout()}, got shape {tuple(shape)}")]


def frame_count_problems(key: str, n: int, n_frames: int) -> list[Problem]:
    """A per-frame array of ``n`` frames where the images have ``n_frames``."""
    return [] if n == n_frames else [Problem(key, f"{n} frames but images has {n_frames}")]


def time_order_problems(time: np.ndarray, previous: float = -np.inf, first: int = 0,
                        unit: str = "frame") -> list[Problem]:
    """A time stamp that does not come after the one before it (``previous`` before the first,
    whose index is ``first``: a block of a longer array)."""
    t = np.asarray(time, dtype=np.float64)
    if t.size == 0:
        return []
    bad = np.flatnonzero(np.diff(t, prepend=previous) <= 0)
    if not bad.size:
        return []
    return [Problem("time", f"not strictly increasing (first at {unit} {first + int(bad[0])})", frame=first + int(bad[0]))]


def run_array_problems(grid: SensorGrid, arrays: Mapping[str, np.ndarray]) -> list[Problem]:
    """Every problem with a run's arrays; empty when they can be written.

    The one check of arrays before they are written: the run writer applies it to every block,
    the importer to what it converted, and the readers and the validator apply its pieces chunk
    by chunk (dtype, layout, frame count, finite values, images in [0, 1], time order).
    """
    problems = [Problem(key, "missing") for key in REQUIRED_FRAME_ARRAYS if key not in arrays]
    if problems:
        return problems
    images = arrays["images"]
    T = images.shape[0] if images.ndim else -1
    images_ok = False  # finite and in [0, 1]: the common case, checked in one fast pass
    for key, arr in arrays.items():
        if key not in FRAME_ARRAYS:
            continue
        found = dtype_problems(key, arr) or layout_problems(key, arr.shape) or frame_count_problems(key, arr.shape[0], T)
        if not found and key == "images" and arr.size:
            images_ok = in_unit_interval(arr)
        if not found and not (key == "images" and images_ok):
            found = nonfinite_problems(key, arr)
        problems += found
    if images.ndim == 3:
        problems += _image_problems(grid, images, images_ok)
    t = arrays["time"]
    if not dtype_problems("time", t) and t.ndim == 1 and np.all(np.isfinite(t)):
        problems += time_order_problems(t)
    return problems


def _image_problems(grid: SensorGrid, images: np.ndarray, in_unit: bool) -> list[Problem]:
    """What the spec asks of images beyond their layout: the grid's frame shape, at least one
    frame, a float dtype and values in [0, 1] (``in_unit``: known to be)."""
    out = []
    if images.shape[1:] != grid.shape:
        out.append(f"frame shape {images.shape[1:]} does not match the grid {grid.shape}")
    if images.shape[0] < 1:
        out.append("a run needs at least one frame")
    if images.dtype not in (np.float16, np.float32, np.float64):
        out.append(f"dtype {images.dtype} must be float16 or float32")
    elif images.size and not in_unit and np.all(np.isfinite(images)):
        out.append(f"values must lie in [0, 1] (energyscape), found {float(images.min()):g}..{float(images.max()):g}")
    return [Problem("images", line) for line in out]
