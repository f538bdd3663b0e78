"""A recording's values in its declared units (``schema.RecordingUnits``), converted to SI."""

from __future__ import annotations

import numpy as np

from sonarset.format.plausibility import UNIT_SCALES
from sonarset.format.attrs import SensorGrid
from sonarset.format.sidecars import RecordingGrid, RecordingUnits


def range_scale(units: RecordingUnits) -> float:
    return UNIT_SCALES["range"][units.range]


def angle_scale(units: RecordingUnits) -> float:
    return UNIT_SCALES["azimuth"][units.azimuth]


def velocity_to_si(velocity: np.ndarray, units: RecordingUnits) -> np.ndarray:
    """(v, omega) rows in m/s and rad/s."""
    return velocity * np.array([UNIT_SCALES["linear_velocity"][units.linear_velocity],
                                UNIT_SCALES["angular_velocity"][units.angular_velocity]])


def time_to_si(time: np.ndarray, units: RecordingUnits) -> np.ndarray:
    return time * UNIT_SCALES["time"][units.time]


def pose_to_si(pose: np.ndarray, units: RecordingUnits) -> np.ndarray:
    """(x, y, heading) rows in metres and radians."""
    return pose * np.array([range_scale(units), range_scale(units), angle_scale(units)])


def grid_to_si(grid: RecordingGrid, units: RecordingUnits) -> SensorGrid:
    """The sensor grid a recording declares; raises pydantic's ValidationError for a bad one."""
    rs, az = range_scale(units), angle_scale(units)
    return SensorGrid(range_min_m=grid.range_min * rs, range_max_m=grid.range_max * rs, n_range=grid.n_range,
                      azimuth_min_rad=grid.azimuth_min * az, azimuth_max_rad=grid.azimuth_max * az,
                      n_azimuth=grid.n_azimuth)
