"""The exact path of the beamforming stage (``beamform``'s docstring has the chain), and the pieces
the fast path shares with it: steering, the envelope detectors, range sampling and bin averaging.

Steering is done in the frequency domain (exact fractional delays), with one inverse FFT per azimuth
(delay-and-sum) or per azimuth and microphone (DMAS3). The signal-level reference
(``sim.reference.reference_amplitude``) runs it on simulated spectra; on recorded signals it is the
simple reference that ``bench/bench_import_raw.py`` compares the fast path against.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft
from scipy import signal

from sonarset.format.attrs import SensorGrid
from sonarset.format.attrs import BEAMFORMERS
from sonarset.sensor.energyscape import dmas3
from sonarset.sensor.ertis import C_SOUND, envelope_lowpass

BAND_MARGIN_HZ = 10e3  # around the sweep's band: the 25->50 kHz sweep keeps 15..60 kHz, as the reference
MARGIN_S = 0.002  # processed beyond the grid's first and last range, for the filters' edges


def steering_projection(positions: np.ndarray, azimuths: np.ndarray) -> np.ndarray:
    """(A, M) path-length lead, metres, of each microphone for a far-field echo from each azimuth in
    the horizontal plane: x cos(theta) + y sin(theta). Delaying channel m by it over c aligns them."""
    x, y = positions[:, 0], positions[:, 1]
    u = np.sin(azimuths)
    if not np.any(x):
        return y[None, :] * u[:, None]  # a planar array facing x (eRTIS): the reference's y sin(theta)
    return x[None, :] * np.cos(azimuths)[:, None] + y[None, :] * u[:, None]


def band_bins(n_fft: int, fs: float, band_hz: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(indices, frequencies) of the rfft bins strictly inside ``band_hz``."""
    f_all = sfft.rfftfreq(n_fft, 1 / fs)
    band = np.flatnonzero((f_all > band_hz[0]) & (f_all < band_hz[1]))
    return band, f_all[band]


def steering(f: np.ndarray, proj: np.ndarray, c: float = C_SOUND) -> np.ndarray:
    """(F, A, M) phase factors that delay channel m by proj[a, m] / c."""
    return np.exp(-2j * np.pi * f[:, None, None] * proj[None] / c)


#: Envelope detectors of a real beamformed signal; each beamformer's default first in ``DEFAULT_DETECTOR``.
DETECTORS = ("analytic", "square", "rectify")
DEFAULT_DETECTOR = {"das": "analytic", "dmas3-cf": "rectify"}


def check_detector(beamformer: str, detector: str | None) -> str:
    """The detector ``beamformer`` uses (its default for None); ValueError with a one-line reason."""
    if beamformer not in BEAMFORMERS:
        raise ValueError(f"beamformer must be one of {', '.join(BEAMFORMERS)}, got {beamformer!r}")
    detector = detector or DEFAULT_DETECTOR[beamformer]
    if detector not in DETECTORS:
        raise ValueError(f"detector must be one of {', '.join(DETECTORS)}, got {detector!r}")
    if beamformer == "das" and detector != "analytic":
        raise ValueError("delay-and-sum sums the analytic channels: its modulus is the envelope (detector 'analytic')")
    return detector


def detect(x: np.ndarray, fs: float, detector: str) -> np.ndarray:
    """Low-passed envelope of real signals ``x`` along the last axis: ``analytic`` |hilbert(x)|,
    ``square`` sqrt(2 lowpass(x^2)) (the square law), ``rectify`` pi/2 lowpass(|x|) (the toolbox's
    order). A carrier of amplitude a gives a with each."""
    if detector == "analytic":
        return envelope_lowpass(np.abs(signal.hilbert(x, axis=-1)), fs, axis=-1)
    if detector == "square":
        return np.sqrt(np.maximum(2 * envelope_lowpass(np.square(x), fs, axis=-1), 0))
    if detector == "rectify":
        return np.pi / 2 * envelope_lowpass(np.abs(x), fs, axis=-1)
    raise ValueError(f"detector must be one of {', '.join(DETECTORS)}, got {detector!r}")


def sweep_norm(s: np.ndarray, fs: float, detector: str = "analytic") -> float:
    """Peak of the low-passed matched-filter envelope of a lone echo ``s`` through ``detector``: a
    lone echo of amplitude a at a microphone then peaks at a after dividing by it."""
    return float(detect(signal.correlate(s, s), fs, detector).max())


def range_samples(grid: SensorGrid, fs: float, n: int, c: float = C_SOUND, start_s: float = 0.0) -> np.ndarray:
    """Sample index of each range bin centre (two-way time 2r/c after the emission, the first sample
    at ``start_s``), clipped to 0..n-1."""
    return np.clip(np.rint((2 * grid.range_centres() / c - start_s) * fs).astype(int), 0, n - 1)


def range_edges(grid: SensorGrid, fs: float, n: int | None = None, c: float = C_SOUND,
                start_s: float = 0.0) -> np.ndarray:
    """Sample index of each range bin edge (R + 1,), at least one sample apart, within 0..n-1."""
    r = grid.range_min_m + np.arange(grid.n_range + 1) * grid.range_step
    t = np.rint((2 * r / c - start_s) * fs).astype(np.int64)
    if n is not None:
        t = np.clip(t, 0, n - 1)
    t[1:] = np.maximum.accumulate(np.maximum(t[1:], t[:-1] + 1))
    return t


def bin_average(env: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Amplitude (R, A) float32 of envelopes (A, n): the RMS over each range bin's samples
    ``edges[i]:edges[i+1]``, negative lobes of the low-pass clipped first. Each bin holds the
    energy averaged over its width, as the fast model's range PSF does (a 2 cm PSF point-sampled
    on coarser bins would miss the echoes between bin centres)."""
    env = np.maximum(env, 0)
    csum = np.zeros((env.shape[0], env.shape[1] + 1))
    np.cumsum(env * env, axis=1, out=csum[:, 1:])
    e = (csum[:, edges[1:]] - csum[:, edges[:-1]]) / np.diff(edges)
    return np.ascontiguousarray(np.sqrt(np.maximum(e, 0)).T, dtype=np.float32)


def das_envelope(Y: np.ndarray, steer: np.ndarray, band: np.ndarray, n_fft: int, fs: float) -> np.ndarray:
    """Delay-and-sum envelope (K, A, n_fft) of matched-filtered channel spectra Y (K, M, F), in the
    frequency domain: the analytic signal is the doubled positive band, inverse-transformed."""
    Z = np.einsum("fam,kmf->kaf", steer, Y) / Y.shape[1]
    full = np.zeros((Y.shape[0], steer.shape[1], n_fft), complex)
    full[:, :, band] = 2 * Z
    return envelope_lowpass(np.abs(sfft.ifft(full, axis=2)), fs, axis=2)


def dmas3_cf(z: np.ndarray, axis: int = 1) -> np.ndarray:
    """DMAS3 of the real parts of steered analytic channels ``z`` times their coherence factor."""
    out = dmas3(z.real, axis=axis)
    n = z.shape[axis]
    out *= np.abs(z.sum(axis)) ** 2 / (n * (np.abs(z) ** 2).sum(axis) + 1e-300)
    return out


def dmas3_cf_envelope(Y: np.ndarray, steer: np.ndarray, band: np.ndarray, n_fft: int, fs: float,
                      t_idx: np.ndarray, detector: str = DEFAULT_DETECTOR["dmas3-cf"]) -> np.ndarray:
    """DMAS3-CF envelope (K, A, n_fft), zero outside the grid's ranges plus a margin: the channels
    steered in the frequency domain, one azimuth at a time (K, M, T)."""
    K, M = Y.shape[:2]
    env = np.zeros((K, steer.shape[1], n_fft))
    t0 = max(0, int(t_idx.min()) - int(MARGIN_S * fs))
    t1 = min(n_fft, int(t_idx.max()) + int(MARGIN_S * fs))
    for a in range(steer.shape[1]):
        full = np.zeros((K, M, n_fft), complex)
        full[:, :, band] = 2 * Y * steer[:, a, :].T[None]
        z = sfft.ifft(full, axis=2)[:, :, t0:t1]
        out = dmas3_cf(z, axis=1)
        env[:, a, t0:t1] = detect(out, fs, detector)
    return env


def band_envelope(Y: np.ndarray, steer: np.ndarray, band: np.ndarray, n_fft: int, fs: float,
                  t_idx: np.ndarray, beamformer: str, detector: str | None = None) -> np.ndarray:
    """The exact path: envelope (K, A, n_fft) of ``beamformer`` from matched-filtered spectra."""
    detector = check_detector(beamformer, detector)
    if beamformer == "das":
        return das_envelope(Y, steer, band, n_fft, fs)
    return dmas3_cf_envelope(Y, steer, band, n_fft, fs, t_idx, detector)


def sweep_band(sweep: np.ndarray, fs: float) -> tuple[float, float]:
    """The band the processing keeps: where the sweep's spectrum is within 40 dB of its peak,
    widened by ``BAND_MARGIN_HZ`` (the reference's 15-60 kHz for the 25->50 kHz sweep)."""
    n = sfft.next_fast_len(max(8 * len(sweep), 4096))
    mag = np.abs(sfft.rfft(sweep, n))
    f = sfft.rfftfreq(n, 1 / fs)
    keep = f[mag >= 1e-2 * mag.max()]
    return max(0.0, float(keep.min()) - BAND_MARGIN_HZ), min(fs / 2, float(keep.max()) + BAND_MARGIN_HZ)
