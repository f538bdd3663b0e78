"""The eRTIS sensor the simulator models: the speed of sound, the emitted FM sweep's band and
length, and the microphone layout (sources in ``sonar.py``'s docstring)."""

from __future__ import annotations

import csv
from importlib import resources

import numpy as np

C_SOUND = 343.0
F_LO, F_HI, SWEEP_S = 25e3, 50e3, 2.5e-3


def microphone_y() -> np.ndarray:
    """Horizontal (y, positive left) positions of the 32 eRTIS microphones, metres."""
    text = resources.files("sonarset").joinpath("data/ertis32_microphones.csv").read_text()
    rows = [r for r in csv.reader(text.splitlines()) if r and not r[0].startswith("#")]
    header = rows[0]
    return np.array([float(r[header.index("y")]) for r in rows[1:]])
