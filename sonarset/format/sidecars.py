"""Pydantic models of the JSON sidecars that describe an external recording to the importers:
``RecordingMeta`` (``sonarset import``) and ``RawRecordingMeta`` (``sonarset import-raw``), spec/FORMAT.md §9.

An import format, not a store format: the importer converts what they describe into a store's runs.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from sonarset.format.attrs import PROCESSING_PROFILES, ImageEncoding, Processing, RobotRig, RunAttrs, run_name_problems


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
    dynamic_range_db: float = Field(ImageEncoding.model_fields["dynamic_range_db"].default, gt=0, le=300)
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
        for problem in ([] if v is None else run_name_problems(v)):
            raise ValueError(problem.message)
        return v

    @field_validator("split")
    @classmethod
    def _split(cls, v: str) -> str:
        return RunAttrs._split(v)

    @field_validator("processing", mode="before")
    @classmethod
    def _named_profile(cls, v: Any) -> Any:
        # A named profile's omitted settings are the profile's, as import-raw's --processing ertis
        # --beamformer das is ertis with another beamformer: {"profile": "ertis"} filled with the
        # format's per-key defaults (delay-and-sum, no post-processing) would not be ertis's images.
        if not (isinstance(v, dict) and v.get("profile") in PROCESSING_PROFILES):
            return v
        named = Processing.named(v["profile"]).model_dump()
        return {**named, **v}

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
