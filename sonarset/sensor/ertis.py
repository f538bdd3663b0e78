"""The eRTIS sensor, the one home of its physics shared by the simulator and the raw importer: the
speed of sound, the emitted FM sweep, the envelope low-pass of its processing, and the microphone
layout (sources: docs/physics.md, "The sensor").

scipy is imported where it is used: ``sonarset.format`` reads ``C_SOUND`` from here, and the format
layer must stay quick to import.
"""

from __future__ import annotations

import csv
from importlib import resources
from pathlib import Path

import numpy as np

C_SOUND = 343.0  # m/s, dry air at 20 degC
F_LO, F_HI, SWEEP_S = 25e3, 50e3, 2.5e-3  # the emitted sweep: 25 -> 50 kHz in 2.5 ms
ENVELOPE_LP_HZ = 6e3  # the envelope low-pass of the eRTIS processing (public RTIS Dev defaults)
LAYOUT_CSV = "data/ertis32_microphones.csv"  # inside the sonarset package
#: The azimuth PSFs the simulator can give the sensor: the array's delay-and-sum beam pattern
#: (side lobes included), or its main lobe alone (an ablation); sim/sonar.py tabulates each.
AZIMUTH_PSFS = ("array", "mainlobe")


def sweep(fs: float, f_start: float = F_LO, f_end: float = F_HI, duration: float = SWEEP_S,
          window: str = "hann") -> np.ndarray:
    """A linear FM sweep sampled at ``fs`` Hz, Hann-windowed (``window='none'``: unwindowed); by
    default the eRTIS one, which the simulator emits."""
    from scipy import signal

    t = np.arange(int(round(duration * fs))) / fs
    s = signal.chirp(t, f_start, duration, f_end)
    return s * signal.windows.hann(len(t)) if window == "hann" else s


def envelope_lowpass(env: np.ndarray, fs: float, axis: int = -1) -> np.ndarray:
    """The processing's envelope low-pass (2nd-order Butterworth at ``ENVELOPE_LP_HZ``, zero phase)."""
    from scipy import signal

    b, a = signal.butter(2, ENVELOPE_LP_HZ, fs=fs)
    return signal.filtfilt(b, a, env, axis=axis)


def read_layout_csv(path: str | Path | None = None, text: str | None = None) -> np.ndarray:
    """Microphone positions (M, 3) in metres from a CSV with columns x, y, z ('#' comments allowed);
    default: the shipped eRTIS layout (``sonarset/data/ertis32_microphones.csv``). ValueError with a
    one-line reason."""
    if text is None:
        text = (resources.files("sonarset").joinpath(LAYOUT_CSV) if path is None else Path(path)).read_text()
    rows = [[c.strip() for c in r] for r in csv.reader(text.splitlines()) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise ValueError("no header row (expected columns x,y,z)")
    header = [h.lower() for h in rows[0]]
    missing = [k for k in ("x", "y", "z") if k not in header]
    if missing:
        raise ValueError(f"header {','.join(rows[0])} lacks column(s) {', '.join(missing)}")
    cols = [header.index(k) for k in ("x", "y", "z")]
    out = []
    for i, r in enumerate(rows[1:], start=2):
        try:
            out.append([float(r[c]) for c in cols])
        except (ValueError, IndexError):
            raise ValueError(f"row {i}: expected numbers in columns x,y,z, got {','.join(r)!r}") from None
    if not out:
        raise ValueError("no microphone rows")
    return np.array(out)


def microphone_y() -> np.ndarray:
    """Horizontal (y, positive left) positions of the 32 eRTIS microphones, metres."""
    return np.ascontiguousarray(read_layout_csv()[:, 1])
