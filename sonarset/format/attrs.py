"""Pydantic models of the store's own JSON documents: the root's and each run's attributes, with
the sensor grid, the image processing and the robot rig they hold, and the rules on names and
versions. Each default lives here, on its model, once.

The JSON Schemas in ``spec/schema/`` are generated from these models (``sonarset.format.schemas``),
and a test fails when they are stale. Readers accept unknown keys (a minor version may add fields);
writers emit exactly these fields.
"""

from __future__ import annotations

import math
import re
from typing import Any, Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from sonarset.format.problems import Problem

#: Format version written by this library. Readers accept any 1.x (see spec/FORMAT.md §8).
#: 1.1 added the typed ``processing`` and ``rig`` store attributes; 1.2 a crc32c checksum on every chunk.
FORMAT_VERSION = "1.2"
SUPPORTED_MAJOR = 1
#: The first version whose arrays must end their codec chain with a crc32c checksum (FORMAT.md §2).
CHECKSUMS_SINCE = (1, 2)
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


def version_problems(value: Any) -> list[Problem]:
    """A store's ``format_version`` against what this library reads (any 1.x, spec/FORMAT.md §8)."""
    from sonarset.version import __version__

    try:
        major, _ = parse_version(value)
    except ValueError as exc:
        return [Problem("", f"attributes.{NAMESPACE}.{exc}")]
    if major != SUPPORTED_MAJOR:
        return [Problem("", f"format version {value} is not supported (this sonarset {__version__} reads "
                            f"{SUPPORTED_MAJOR}.x); upgrade sonarset")]
    return []


def requires_checksums(version: str) -> bool:
    """Whether a store of ``version`` must checksum every chunk (format 1.2 on); False for an
    unparseable version, which ``version_problems`` reports."""
    try:
        return parse_version(version) >= CHECKSUMS_SINCE
    except ValueError:
        return False


def run_name_problems(name: str) -> list[Problem]:
    """A run name against the spec's pattern (spec/FORMAT.md §2)."""
    if isinstance(name, str) and RUN_NAME_RE.match(name):
        return []
    return [Problem("", f"invalid run name {name!r}: a run name is 1-128 letters, digits, '_', '.' or '-', "
                        "starting with a letter or digit")]


def split_problems(split: str) -> list[Problem]:
    """A split name against the spec's pattern (spec/FORMAT.md §4)."""
    if isinstance(split, str) and SPLIT_RE.match(split):
        return []
    return [Problem("", "split must be lower-case letters, digits, '_' or '-' (e.g. 'train')")]


class SensorGrid(BaseModel):
    """The range x azimuth sampling grid of an energyscape.

    Bins are uniform; the bounds are bin *edges*, so the default grid (0.5-5 m in 200 bins,
    -90..+90 deg in 90 bins) has azimuth centres at +-89 deg, 2 deg apart (spec/FORMAT.md §3, grid).
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


#: The named processing settings: each is the ``Processing`` classmethod of that name.
PROCESSING_PROFILES = ("ertis", "raw")
#: The profile of images whose processing was not recorded (an import without a processing block).
UNKNOWN_PROFILE = "unknown"
#: The beamformers an energyscape can be made with (the simulator and import-raw implement each).
Beamformer = Literal["das", "dmas3-cf"]
BEAMFORMERS: tuple[str, ...] = get_args(Beamformer)


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
    beamformer: Beamformer = Field(
        "das", description="das: delay-and-sum; dmas3-cf: third-order delay-multiply-and-sum times the "
                           "coherence factor |sum of analytic signals|^2 / (N sum of |analytic|^2).")
    smoothing_range_m: float = Field(0.0, ge=0, le=10, description="Gaussian smoothing sigma along range, metres (0: none).")
    smoothing_azimuth_deg: float = Field(0.0, ge=0, le=90,
                                         description="Gaussian smoothing sigma along azimuth, degrees (0: none).")
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
                   azimuth_mean_factor=1.5, clip_at_zero=True, floor_offset=True)

    @classmethod
    def raw(cls) -> "Processing":
        """Delay-and-sum energy on the default log scale, no post-processing (format 1.0's images)."""
        return cls(profile="raw")

    @classmethod
    def named(cls, name: str) -> "Processing":
        if name not in PROCESSING_PROFILES:
            raise ValueError(f"unknown processing profile {name!r}; choose from {', '.join(PROCESSING_PROFILES)}")
        return getattr(cls, name)()

    @property
    def post_processed(self) -> bool:
        return bool(self.smoothing_range_m or self.smoothing_azimuth_deg or self.azimuth_mean_factor
                    or self.clip_at_zero or self.floor_offset)

    @property
    def unknown(self) -> bool:
        """Images whose making was not recorded (an import without a processing block): their fields
        are defaults, not a description, so they are a kind of images of their own."""
        return self.profile == UNKNOWN_PROFILE

    def same_images(self, other: "Processing") -> bool:
        """True when both settings make the same images (the profile name aside). Images of unknown
        making are the same only as other images of unknown making (more recordings of one's own),
        never as a recorded processing: a model of 'raw' images is not silently fine-tuned on them."""
        if self.unknown or other.unknown:
            return self.unknown and other.unknown
        return self.model_dump(exclude={"profile"}) == other.model_dump(exclude={"profile"})

    def describe(self) -> str:
        if self.unknown:
            return f"{self.profile} (not recorded how they were made)"
        if not self.post_processed:
            return f"{self.profile} ({self.beamformer}, no post-processing)"
        return (f"{self.profile} ({self.beamformer}, smoothing {self.smoothing_range_m:g} m x "
                f"{self.smoothing_azimuth_deg:g} deg, {self.azimuth_mean_factor:g} x azimuth mean removed, "
                f"{self.floor_db:g} dB floor over {self.span_db:g} dB)")


class ImageEncoding(BaseModel):
    """How pixel values map to echo energy (spec/FORMAT.md §1, Energyscapes)."""

    model_config = ConfigDict(extra="allow")

    scale: Literal["log"] = Field(
        "log", description="Pixels are log-compressed energy: 1 = full scale, 0 = dynamic_range_db below."
    )
    dynamic_range_db: float = Field(Processing.model_fields["span_db"].default, gt=0, le=300)


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
        for problem in split_problems(v):
            raise ValueError(problem.message)
        return v
