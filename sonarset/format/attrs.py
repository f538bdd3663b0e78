"""Pydantic models of every JSON document in the SonarSet format.

The JSON Schemas in ``spec/schema/`` are generated from these models (``sonarset schema``), and a
test fails when they are stale. Readers accept unknown keys (a minor version may add fields);
writers emit exactly these fields.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

#: Format version written by this library. Readers accept any 1.x (see spec/FORMAT.md §8).
#: 1.1 added the typed ``processing`` and ``rig`` store attributes.
FORMAT_VERSION = "1.1"
SUPPORTED_MAJOR = 1
#: Key under which all SonarSet attributes live (namespaced, as OME-Zarr's "ome").
NAMESPACE = "sonarset"

RUN_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
SPLIT_RE = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")
VERSION_RE = re.compile(r"^(\d+)\.(\d+)$")


def parse_version(value: Any) -> tuple[int, int]:
    """Return (major, minor) of a ``"MAJOR.MINOR"`` string; ValueError otherwise."""
    if not isinstance(value, str) or not VERSION_RE.match(value):
        raise ValueError(f"format_version must be a 'MAJOR.MINOR' string, got {value!r}")
    major, minor = VERSION_RE.match(value).groups()  # type: ignore[union-attr]
    return int(major), int(minor)


class SensorGrid(BaseModel):
    """The range x azimuth sampling grid of an energyscape.

    Bins are uniform; the bounds are bin *edges*, so the default grid (0.5-5 m in 200 bins,
    -90..+90 deg in 90 bins) has azimuth centres at +-89 deg, 2 deg apart (DESIGN.md §2).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    range_min_m: float = Field(ge=0.0, description="Lower edge of the first range bin, metres.")
    range_max_m: float = Field(gt=0.0, description="Upper edge of the last range bin, metres.")
    n_range: int = Field(ge=1, le=100_000, description="Number of range bins.")
    azimuth_min_rad: float = Field(
        ge=-math.pi - 1e-9, description="Left edge of the first azimuth bin, radians."
    )
    azimuth_max_rad: float = Field(
        le=math.pi + 1e-9, description="Right edge of the last azimuth bin, radians."
    )
    n_azimuth: int = Field(ge=1, le=100_000, description="Number of azimuth bins.")

    @model_validator(mode="after")
    def _ordered(self) -> "SensorGrid":
        if not self.range_max_m > self.range_min_m:
            raise ValueError("range_max_m must be greater than range_min_m")
        if not self.azimuth_max_rad > self.azimuth_min_rad:
            raise ValueError("azimuth_max_rad must be greater than azimuth_min_rad")
        return self

    @classmethod
    def default(cls) -> "SensorGrid":
        """The eRTIS-like default: 0.5-5.0 m in 200 bins, -90..+90 deg in 90 bins."""
        return cls(
            range_min_m=0.5, range_max_m=5.0, n_range=200,
            azimuth_min_rad=-math.pi / 2, azimuth_max_rad=math.pi / 2, n_azimuth=90,
        )

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_range, self.n_azimuth)

    @property
    def range_step(self) -> float:
        return (self.range_max_m - self.range_min_m) / self.n_range

    @property
    def azimuth_step(self) -> float:
        return (self.azimuth_max_rad - self.azimuth_min_rad) / self.n_azimuth

    def range_centres(self) -> np.ndarray:
        return self.range_min_m + (np.arange(self.n_range) + 0.5) * self.range_step

    def azimuth_centres(self) -> np.ndarray:
        return self.azimuth_min_rad + (np.arange(self.n_azimuth) + 0.5) * self.azimuth_step

    @classmethod
    def from_centres(cls, range_centres: np.ndarray, azimuth_centres: np.ndarray) -> "SensorGrid":
        """Infer the grid from coordinate arrays; ValueError if they are not uniform."""
        r = _uniform_edges(np.asarray(range_centres, dtype=np.float64), "range")
        a = _uniform_edges(np.asarray(azimuth_centres, dtype=np.float64), "azimuth")
        return cls(
            range_min_m=r[0], range_max_m=r[1], n_range=len(range_centres),
            azimuth_min_rad=a[0], azimuth_max_rad=a[1], n_azimuth=len(azimuth_centres),
        )

    def matches(self, other: "SensorGrid", rtol: float = 1e-6) -> bool:
        if self.shape != other.shape:
            return False
        scale = max(self.range_max_m, 1.0)
        return all(
            abs(a - b) <= rtol * scale
            for a, b in [
                (self.range_min_m, other.range_min_m), (self.range_max_m, other.range_max_m),
                (self.azimuth_min_rad, other.azimuth_min_rad),
                (self.azimuth_max_rad, other.azimuth_max_rad),
            ]
        )

    def describe(self) -> str:
        return (
            f"{self.n_range}x{self.n_azimuth} (range {self.range_min_m:g}-{self.range_max_m:g} m, "
            f"azimuth {math.degrees(self.azimuth_min_rad):g}..{math.degrees(self.azimuth_max_rad):g} deg)"
        )


def _uniform_edges(centres: np.ndarray, name: str) -> tuple[float, float]:
    if centres.ndim != 1 or len(centres) < 2:
        raise ValueError(f"{name} coordinates need at least 2 values in a 1-D array")
    if not np.all(np.isfinite(centres)):
        raise ValueError(f"{name} coordinates contain NaN or infinite values")
    step = np.diff(centres)
    if not np.all(step > 0):
        raise ValueError(f"{name} coordinates must be strictly increasing")
    mean = float(step.mean())
    if np.max(np.abs(step - mean)) > 1e-4 * mean:
        raise ValueError(f"{name} coordinates are not uniformly spaced")
    return float(centres[0] - mean / 2), float(centres[-1] + mean / 2)


class ImageEncoding(BaseModel):
    """How pixel values map to echo energy (DESIGN.md §2)."""

    model_config = ConfigDict(extra="allow")

    scale: Literal["log"] = Field(
        "log", description="Pixels are log-compressed energy: 1 = full scale, 0 = dynamic_range_db below."
    )
    dynamic_range_db: float = Field(60.0, gt=0, le=300)


class Processing(BaseModel):
    """How the images were made from the microphone signals: beamformer and energyscape post-processing.

    The stages follow the Cosys-Lab Acoustic-Imaging-Toolbox (``generate2DEnergyscape``): matched
    filter -> beamformer -> envelope -> Gaussian smoothing -> subtract ``azimuth_mean_factor`` x the
    mean over azimuth at each range -> clip at zero -> log mapping. Amplitudes are normalised to the
    strongest echo the sensor can see (a perfect wall at normal incidence at the grid's minimum
    range, through the same beamformer and smoothing), then
    ``pixel = clip((20 log10(a + offset) - floor_db) / span_db, 0, 1)`` with
    ``offset = 10^(floor_db / 20)`` when ``floor_offset`` (the toolbox's mapping, so that zero maps
    to 0) and ``offset = 0`` otherwise. Profiles: ``ertis`` (the simulator's default) and ``raw``
    (delay-and-sum energy, no post-processing: format 1.0's images).
    """

    # Unknown keys are kept (a later 1.y may add a stage) and take part in comparisons.
    model_config = ConfigDict(extra="allow", frozen=True)

    profile: str = Field("custom", pattern=r"^[a-z][a-z0-9_-]{0,31}$",
                         description="Name of the settings: 'ertis', 'raw', or 'custom'/'unknown'.")
    beamformer: Literal["das", "dmas3-cf"] = Field(
        "das", description="das: delay-and-sum; dmas3-cf: third-order delay-multiply-and-sum times the "
                           "coherence factor |sum of analytic signals|^2 / (N sum of |analytic|^2).")
    smoothing_range_m: float = Field(0.0, ge=0, le=10, description="Gaussian smoothing sigma along range, metres (0: none).")
    smoothing_azimuth_deg: float = Field(0.0, ge=0, le=90, description="Gaussian smoothing sigma along azimuth, degrees (0: none).")
    azimuth_mean_factor: float = Field(0.0, ge=0, le=100,
                                       description="Subtract this factor x the mean over azimuth at each range (0: none).")
    clip_at_zero: bool = Field(False, description="Clip negative amplitudes (after the subtraction) to zero.")
    floor_db: float = Field(-60.0, lt=0, ge=-300, description="Log floor, dB re full scale: maps to pixel 0.")
    span_db: float = Field(60.0, gt=0, le=300, description="dB from the floor to pixel 1.")
    floor_offset: bool = Field(False, description="Add the floor's amplitude before the log (toolbox mapping).")

    @classmethod
    def ertis(cls) -> "Processing":
        """The eRTIS toolchain's energyscapes, calibrated on the default grid (BENCHMARKS.md)."""
        return cls(profile="ertis", beamformer="dmas3-cf", smoothing_range_m=0.0675, smoothing_azimuth_deg=2.0,
                   azimuth_mean_factor=1.5, clip_at_zero=True, floor_db=-60.0, span_db=60.0, floor_offset=True)

    @classmethod
    def raw(cls) -> "Processing":
        """Delay-and-sum energy on a 60 dB log scale, no post-processing (format 1.0's images)."""
        return cls(profile="raw")

    @classmethod
    def named(cls, name: str) -> "Processing":
        profiles = {"ertis": cls.ertis, "raw": cls.raw}
        if name not in profiles:
            raise ValueError(f"unknown processing profile {name!r}; choose from {', '.join(profiles)}")
        return profiles[name]()

    @property
    def post_processed(self) -> bool:
        return bool(self.smoothing_range_m or self.smoothing_azimuth_deg or self.azimuth_mean_factor
                    or self.clip_at_zero or self.floor_offset)

    def same_images(self, other: "Processing") -> bool:
        """True when both settings make the same images (the profile name aside)."""
        return self.model_dump(exclude={"profile"}) == other.model_dump(exclude={"profile"})

    def describe(self) -> str:
        if not self.post_processed:
            return f"{self.profile} ({self.beamformer}, no post-processing)"
        return (f"{self.profile} ({self.beamformer}, smoothing {self.smoothing_range_m:g} m x "
                f"{self.smoothing_azimuth_deg:g} deg, {self.azimuth_mean_factor:g} x azimuth mean removed, "
                f"{self.floor_db:g} dB floor over {self.span_db:g} dB)")


class RobotRig(BaseModel):
    """The robot geometry that predictors need to turn commands into image motion."""

    # Unknown keys are kept (a later 1.y may add a stage) and take part in comparisons.
    model_config = ConfigDict(extra="allow", frozen=True)

    frame_interval_s: float = Field(0.2, gt=0, le=3600, description="Nominal time between frames, seconds.")
    sensor_offset_m: float = Field(
        0.15, ge=-10, le=10, description="Sensor position ahead of the wheel axle on the robot's x axis, metres.")
    wheel_base_m: float = Field(0.3, gt=0, le=10, description="Distance between the wheels, metres.")
    v_max_m_s: float = Field(0.3, gt=0, description="Largest linear speed command, m/s (symmetric).")
    omega_max_rad_s: float = Field(1.0, gt=0, description="Largest angular speed command, rad/s (symmetric).")

    def describe(self) -> str:
        return (f"{self.frame_interval_s:g} s frames, sensor {self.sensor_offset_m:g} m ahead of the axle, "
                f"wheel base {self.wheel_base_m:g} m, |v| <= {self.v_max_m_s:g} m/s, "
                f"|omega| <= {self.omega_max_rad_s:g} rad/s")

    def provenance(self) -> dict[str, float]:
        """The rig as a simulated run's provenance (``RunAttrs.source``) records it. Format 1.0
        stores have no ``rig`` attribute: :meth:`from_provenance` reads their rig back from there."""
        return {"dt": self.frame_interval_s, "sensor_offset_m": self.sensor_offset_m, "wheel_base_m": self.wheel_base_m}

    @classmethod
    def from_provenance(cls, source: dict) -> RobotRig | None:
        """The rig a simulated run's provenance records (:meth:`provenance`); None where it records
        none or an invalid one. The speed limits are the defaults, which the simulator has always used."""
        try:
            return cls(frame_interval_s=float(source["dt"]), sensor_offset_m=float(source["sensor_offset_m"]),
                       wheel_base_m=float(source["wheel_base_m"]))
        except (KeyError, TypeError, ValueError):  # pydantic's ValidationError is a ValueError
            return None


class _Attrs(BaseModel):
    # Unknown keys are kept, not rejected: a 1.x reader must read a later 1.y store.
    model_config = ConfigDict(extra="allow")


class StoreAttrs(_Attrs):
    """``attributes.sonarset`` of the root group."""

    format_version: str = Field(FORMAT_VERSION, description="'MAJOR.MINOR' of the SonarSet spec.")
    kind: Literal["store"] = "store"
    grid: SensorGrid = Field(description="The sensor grid shared by every run in the store.")
    frame_rate_hz: float = Field(5.0, gt=0, description="Nominal frame rate; times are authoritative.")
    image_encoding: ImageEncoding = Field(default_factory=ImageEncoding)
    processing: Processing = Field(
        default_factory=Processing.raw,
        description="How the images were made (1.1). Absent in 1.0 stores, whose images are 'raw'.")
    rig: RobotRig | None = Field(
        None, description="Robot geometry (1.1); absent: unknown (1.0 stores made by the simulator: the default rig).")
    created_by: str = Field("", description="Software that created the store, with version.")
    description: str = ""

    @field_validator("format_version")
    @classmethod
    def _version(cls, v: str) -> str:
        parse_version(v)
        return v


class RunAttrs(_Attrs):
    """``attributes.sonarset`` of a run group."""

    kind: Literal["run"] = "run"
    complete: bool = Field(
        description="Set true by the writer as its last step; readers ignore runs where it is false."
    )
    n_frames: int = Field(ge=0, description="Number of frames T; every time-indexed array has length T.")
    split: str = Field("train", description="Data split this run belongs to: train, val, test, ...")
    source: dict[str, Any] = Field(
        default_factory=dict, description="Provenance: simulator seed and world, or imported file."
    )

    @field_validator("split")
    @classmethod
    def _split(cls, v: str) -> str:
        if not SPLIT_RE.match(v):
            raise ValueError("split must be lower-case letters, digits, '_' or '-' (e.g. 'train')")
        return v


class RecordingUnits(BaseModel):
    """Units of an external recording; the importer converts everything to SI."""

    model_config = ConfigDict(extra="forbid")

    range: Literal["m", "cm", "mm"] = Field("m", description="Unit of range values and pose x, y.")
    azimuth: Literal["rad", "deg"] = Field("rad", description="Unit of azimuth values and pose heading.")
    linear_velocity: Literal["m/s", "cm/s", "mm/s"] = "m/s"
    angular_velocity: Literal["rad/s", "deg/s"] = "rad/s"
    time: Literal["s", "ms", "us", "ns"] = "s"


class RecordingGrid(BaseModel):
    """A sensor grid given in the recording's own units (bin edges, as SensorGrid)."""

    model_config = ConfigDict(extra="forbid")

    range_min: float
    range_max: float
    n_range: int = Field(ge=1)
    azimuth_min: float
    azimuth_max: float
    n_azimuth: int = Field(ge=1)


class RecordingMeta(BaseModel):
    """The JSON sidecar of an external recording imported with ``sonarset import``.

    Arrays come from the ``.npz`` (or ``.npy`` files): ``images`` (T, R, A), ``velocity`` (T, 2)
    as (v, omega), ``time`` (T,), optionally ``range`` (R,), ``azimuth`` (A,) bin centres, ``pose``
    (T, 3) as (x, y, heading), ``snr_db`` (T,), ``slip`` (T, 2) as (left, right) wheel factors.
    """

    model_config = ConfigDict(extra="forbid")

    recording_version: Literal["1.0"] = "1.0"
    name: str | None = Field(None, description="Run name in the store; default: the file's stem.")
    split: str = "train"
    grid: RecordingGrid | None = Field(
        None, description="Required unless `range` and `azimuth` arrays are supplied."
    )
    units: RecordingUnits = Field(default_factory=RecordingUnits)
    image_encoding: Literal["energyscape", "db", "linear"] = Field(
        "energyscape",
        description=(
            "energyscape: already in [0, 1] over dynamic_range_db; db: decibels re full scale "
            "(<= 0); linear: non-negative energy, normalised to the recording's maximum."
        ),
    )
    dynamic_range_db: float = Field(60.0, gt=0, le=300)
    velocity_alignment: Literal["previous", "next"] = Field(
        "previous",
        description=(
            "previous: velocity[k] moved the robot from frame k-1 to k (the SonarSet convention); "
            "next: velocity[k] is executed after frame k (shifted on import, dropping frame 0)."
        ),
    )
    processing: Processing | None = Field(
        None, description="How the images were made, as stored after the importer's conversion "
                          "(default: profile 'unknown').")
    rig: RobotRig | None = Field(None, description="Robot geometry (default: unknown).")
    source: dict[str, Any] = Field(default_factory=dict, description="Free-form provenance.")

    @field_validator("name")
    @classmethod
    def _name(cls, v: str | None) -> str | None:
        if v is not None and not RUN_NAME_RE.match(v):
            raise ValueError("name must be 1-128 of letters, digits, '_', '.', '-' and start alphanumeric")
        return v

    @field_validator("split")
    @classmethod
    def _split(cls, v: str) -> str:
        return RunAttrs._split(v)

    @field_validator("processing", "rig")
    @classmethod
    def _closed(cls, v: BaseModel | None) -> BaseModel | None:
        # Stores keep unknown keys of a later minor version; a hand-written sidecar has no such excuse.
        if v is not None and v.model_extra:
            raise ValueError(f"unknown key(s) {', '.join(sorted(v.model_extra))}")
        return v


class RawSweep(BaseModel):
    """The emitted sweep: a linear FM chirp by its parameters, or its samples at the recording's rate."""

    model_config = ConfigDict(extra="forbid")

    f_start_hz: float | None = Field(None, gt=0, description="Chirp start frequency, Hz (eRTIS: 25000).")
    f_end_hz: float | None = Field(None, gt=0, description="Chirp end frequency, Hz (eRTIS: 50000).")
    duration_s: float | None = Field(None, gt=0, le=0.1, description="Chirp duration, s (eRTIS: 0.0025).")
    window: Literal["hann", "none"] = Field("hann", description="Amplitude window of the chirp.")
    samples: list[float] | None = Field(
        None, min_length=8, description="The sweep's samples at sample_rate_hz (instead of the parameters).")

    @model_validator(mode="after")
    def _one_form(self) -> "RawSweep":
        params = [self.f_start_hz, self.f_end_hz, self.duration_s]
        if self.samples is not None and any(p is not None for p in params):
            raise ValueError("give either samples or f_start_hz/f_end_hz/duration_s, not both")
        if self.samples is None and any(p is None for p in params):
            raise ValueError("give f_start_hz, f_end_hz and duration_s (or samples)")
        return self


class RawRecordingMeta(BaseModel):
    """The JSON sidecar of a raw microphone recording imported with ``sonarset import-raw``.

    Arrays come from the ``.npz`` (or ``.npy`` files): ``signals`` (T, M, n) per measurement and
    microphone, ``velocity`` (T, 2) as (v, omega), ``time`` (T,), optionally ``pose`` (T, 3) and
    ``sweep`` (n_sweep,) (the emitted sweep's samples, when the sidecar gives none).
    An import format, not a store format: the importer beamforms the signals into energyscapes.
    """

    model_config = ConfigDict(extra="forbid")

    raw_version: Literal["1.0"] = "1.0"
    name: str | None = Field(None, description="Run name in the store; default: the file's stem.")
    split: str = "train"
    sample_rate_hz: float = Field(gt=0, le=100e6, description="Sampling rate of the microphone signals, Hz.")
    speed_of_sound_m_s: float = Field(ge=300, le=400, description="Speed of sound in air during the recording, m/s.")
    sweep: RawSweep | None = Field(
        None, description="The emitted sweep; required unless the input holds a `sweep` array.")
    microphones: str | list[list[float]] = Field(
        description="Microphone layout: 'ertis32' (the shipped eRTIS layout), a CSV path relative to the "
                    "sidecar with columns x,y,z in metres, or a list of [x, y, z] (or [x, y]) positions in "
                    "metres; one per channel, in channel order. Sensor frame: x forward, y left, the "
                    "emitter at the origin.")
    start_time_s: float = Field(0.0, ge=-1, le=1, description="Time of the first sample after the start of the emission, s.")
    amplitude_scale: float = Field(
        1.0, gt=0, description="Recording units per simulator amplitude unit: an echo the simulator gives amplitude "
                               "a at a microphone reads amplitude_scale x a x the sweep. Sets the energyscapes' 0 dB.")
    grid: RecordingGrid | None = Field(
        None, description="Sensor grid of a new store, in units.range / units.azimuth (default: the 200 x 90 "
                          "eRTIS-like grid); an existing store keeps its own and must agree.")
    units: RecordingUnits = Field(default_factory=RecordingUnits)
    velocity_alignment: Literal["previous", "next"] = Field(
        "previous", description="As in the image recording sidecar: next drops measurement 0.")
    rig: RobotRig | None = Field(None, description="Robot geometry (default: unknown).")
    source: dict[str, Any] = Field(default_factory=dict, description="Free-form provenance.")

    _name = field_validator("name")(RecordingMeta._name.__func__)
    _split = field_validator("split")(RecordingMeta._split.__func__)
    _closed = field_validator("rig")(RecordingMeta._closed.__func__)


SCHEMAS: dict[str, type[BaseModel]] = {
    "store": StoreAttrs,
    "run": RunAttrs,
    "recording": RecordingMeta,
    "raw-recording": RawRecordingMeta,
}


def json_schema(kind: str) -> dict[str, Any]:
    """The JSON Schema of one document kind: 'store', 'run' or 'recording'."""
    if kind not in SCHEMAS:
        raise ValueError(f"unknown schema kind {kind!r}; choose from {', '.join(SCHEMAS)}")
    schema = SCHEMAS[kind].model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = f"https://sonarset.dev/schema/{FORMAT_VERSION}/{kind}.schema.json"
    return schema


def json_schema_text(kind: str) -> str:
    return json.dumps(json_schema(kind), indent=2, sort_keys=True) + "\n"


def pydantic_problems(exc: Exception, prefix: str = "") -> list[str]:
    """One line per pydantic error: 'grid.n_range: Input should be greater than or equal to 1'."""
    errors = getattr(exc, "errors", None)
    if not callable(errors):
        return [f"{prefix}{exc}"]
    lines = []
    for err in errors():
        loc = ".".join(str(p) for p in err.get("loc", ()))
        where = f"{prefix}{loc}" if loc else prefix.rstrip(".")
        lines.append(f"{where}: {err.get('msg', 'invalid')}" if where else err.get("msg", "invalid"))
    return lines
