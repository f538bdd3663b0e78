"""Beamforming microphone signals into envelope amplitude on a sensor grid.

What the eRTIS toolchain does to one measurement (Cosys-Lab Acoustic-Imaging-Toolbox,
``calculateDMASCF``): matched filter with the emitted sweep -> steer the channels towards every
azimuth of the grid (far field, in the horizontal plane) -> delay-and-sum, or DMAS3 times the
coherence factor -> envelope -> envelope low-pass -> sample at the grid's ranges (two-way time
2r/c). The energyscape post-processing that follows is an image operation
(``energyscape.postprocess``).

The envelope (``exact.DETECTORS``): delay-and-sum's output is the analytic signal itself, band-limited to
the sweep's band, so its modulus is the exact envelope. DMAS3 x CF's output is not band-limited:
the cube roots make odd harmonics that fold at the output rate (at 225 kHz the fifth of 45 kHz lands
on 0 Hz) and the coherence factor modulates it, so it has baseband content, and the modulus of its
analytic signal spreads that into 1/t tails (the Hilbert kernel): a streak along every target's
azimuth over all ranges that survives the post-processing. So DMAS3-CF is detected as the toolbox
does it: rectify, low-pass, then decimate (``rectify``; the bin average is the decimation), which
keeps every echo at its range and gives a lone echo the fast model's range PSF (the low-passed
envelope). The square law (``square``) keeps echoes at their ranges too, but widens the range PSF
(the low-pass acts on the energy): a lone echo's bin reads 7% above the fast model's. BENCHMARKS.md,
"The envelope of DMAS3-CF", has the measurements.

Two implementations of the same stage:

- the exact path (``sensor.exact``, with the pieces both paths share): steering in the frequency
  domain, the signal-level reference's and the simple reference for recorded signals.
- the fast path (``SignalBeamformer``, here): each channel's matched-filtered analytic signal is
  made once, upsampled by ``U`` (as ``U`` fractionally delayed copies at the output rate), and the steered
  channels are gathered from it at the nearest upsampled sample (delay error <= 1 / (2 U fs),
  0.16 us at 3.2 MHz: under 3 degrees of phase at 50 kHz; DMAS3-CF peaks within 1% of the exact
  path, 3% at 1.6 MHz). The cube roots of DMAS3 commute with a delay, so they
  are taken once per channel, not once per azimuth; one compiled loop then sums, for every azimuth
  and output sample, the analytic channels (delay-and-sum and the coherence factor's numerator),
  their powers (its denominator) and the first three powers of the cube roots (DMAS3 by Newton's
  identity, ``energyscape.dmas3``). The output runs at the recording's rate divided by
  floor(fs / ``FS_PROCESS``), at or just above the reference's 200 kHz, so that the odd harmonics
  of DMAS3 fold much as they do there.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import fft as sfft

from sonarset.format.attrs import SensorGrid
from sonarset.sensor.ertis import C_SOUND, envelope_lowpass
from sonarset.sensor.exact import (
    MARGIN_S, band_bins, band_envelope, bin_average, check_detector, detect, range_edges, range_samples, steering,
    steering_projection, sweep_band, sweep_norm,
)

FS_PROCESS = 200e3  # Hz: the reference's rate; the fast path's output runs at fs_in / floor(fs_in / this)
UPSAMPLED_HZ = 3.2e6  # the fast path's steering grid: delays rounded to 1 / (2 x this)


@njit(cache=True, nogil=True, fastmath=True)
def _gather(zr, zi, cr, pw, shift, n_out, dmas):
    """Beamformed output (A, n_out) from per-channel polyphase tables (M, P, Q) float32 of the
    upsampled analytic signal: real part ``zr``, imaginary part ``zi``, cube root of the real part
    ``cr``, power ``pw``. Output sample j of azimuth a reads channel m at upsampled sample
    j * P + shift[a, m], that is phase shift % P, position shift // P + j: a contiguous run.

    dmas False: the delay-and-sum envelope |sum z| / M. True: DMAS3 (normalised as
    ``energyscape.dmas3``) times the coherence factor |sum z|^2 / (M sum |z|^2).
    """
    A, M = shift.shape
    P = zr.shape[1]
    out = np.zeros((A, n_out))
    # float32 sums: 32 terms lose ~1e-6, far below what DMAS3's cancellation needs
    sr = np.empty(n_out, np.float32)
    si = np.empty(n_out, np.float32)
    s1 = np.empty(n_out, np.float32)
    s2 = np.empty(n_out, np.float32)
    s3 = np.empty(n_out, np.float32)
    sp = np.empty(n_out, np.float32)
    comb = M * (M - 1) * (M - 2) / 6.0
    for a in range(A):
        sr[:] = 0.0
        si[:] = 0.0
        s1[:] = 0.0
        s2[:] = 0.0
        s3[:] = 0.0
        sp[:] = 0.0
        for m in range(M):
            r = shift[a, m] % P
            q = shift[a, m] // P
            xr = zr[m, r, q:q + n_out]
            xi = zi[m, r, q:q + n_out]
            if dmas:
                xc = cr[m, r, q:q + n_out]
                xp = pw[m, r, q:q + n_out]
                for j in range(n_out):
                    c = xc[j]
                    c2 = c * c
                    sr[j] += xr[j]
                    si[j] += xi[j]
                    s1[j] += c
                    s2[j] += c2
                    s3[j] += c2 * c
                    sp[j] += xp[j]
            else:
                for j in range(n_out):
                    sr[j] += xr[j]
                    si[j] += xi[j]
        for j in range(n_out):
            e2 = np.float64(sr[j]) ** 2 + np.float64(si[j]) ** 2
            if dmas:
                t1, t2, t3 = np.float64(s1[j]), np.float64(s2[j]), np.float64(s3[j])
                e3 = (t1 * t1 * t1 - 3.0 * t1 * t2 + 2.0 * t3) / 6.0 / comb
                out[a, j] = e3 * e2 / (M * np.float64(sp[j]) + 1e-300)
            else:
                out[a, j] = np.sqrt(e2) / M
    return out


@dataclass
class SignalBeamformer:
    """The fast path for one recording geometry: signals (M, n_samples) at ``fs`` -> envelope
    amplitude (R, A) float32 on ``grid``, where a lone echo that reaches every microphone as
    a x ``sweep`` peaks at a.

    ``positions`` (M, 3) are metres in the sensor frame (x forward, y left) with the emitter at the
    origin; ``start_s`` is the time of the first sample after the start of the emission.
    """

    grid: SensorGrid
    positions: np.ndarray
    sweep: np.ndarray
    fs: float
    n_samples: int
    beamformer: str = "dmas3-cf"
    c: float = C_SOUND
    start_s: float = 0.0
    band_hz: tuple[float, float] | None = None
    detector: str | None = None  # None: the beamformer's (``exact.DEFAULT_DETECTOR``)

    def __post_init__(self) -> None:
        self.detector = check_detector(self.beamformer, self.detector)
        fs = float(self.fs)
        self.decim = max(1, int(fs // FS_PROCESS))  # the output never slower than the reference's rate
        self.up = max(1, int(math.ceil(UPSAMPLED_HZ / fs - 1e-9)))
        self.fs_out = fs / self.decim
        self.stride = self.decim * self.up  # upsampled samples per output sample
        fs_up = fs * self.up
        az = self.grid.azimuth_centres()
        self.proj = steering_projection(np.asarray(self.positions, float), az)
        delay_up = np.rint(self.proj / self.c * fs_up).astype(np.int64)  # (A, M) upsampled samples
        # Range bin edges in output samples: each bin holds the envelope's energy averaged over its
        # width, as the fast model's range PSF is (a 2 cm PSF point-sampled on coarser bins would
        # miss echoes between bin centres).
        t_edge = range_edges(self.grid, self.fs_out, None, self.c, self.start_s)
        margin = int(MARGIN_S * self.fs_out)
        self.j0 = max(0, int(t_edge.min()) - margin)
        j1 = int(t_edge.max()) + margin + 1
        self.n_out = j1 - self.j0
        self.edges = t_edge - self.j0
        # Upsampled window: output sample j of azimuth a reads (j0 + j) * stride - delay. It starts
        # on a whole output sample, so that its polyphase rows are the signal advanced by r / fs_up.
        P = self.stride
        self.w0 = (self.j0 * P - int(delay_up.max())) // P * P
        w1 = (j1 - 1) * P - int(delay_up.min()) + 1
        self.shift = np.ascontiguousarray(self.j0 * P - delay_up - self.w0)  # >= 0
        self.n_q = -(-(w1 - self.w0) // P)
        ns = len(self.sweep)
        # Only the samples that reach the window matter; the FFT is long enough that the matched
        # filter's negative lags never wrap onto it.
        self.n_use = int(min(self.n_samples, math.ceil(w1 / self.up) + ns + 1))
        self.n_fft = sfft.next_fast_len(self.n_use + ns, real=True)
        band = self.band_hz or sweep_band(self.sweep, fs)
        self.band, f = band_bins(self.n_fft, fs, band)
        if len(self.band) == 0:
            raise ValueError(f"no frequency bins in the band {band[0]:g}-{band[1]:g} Hz at {fs:g} Hz")
        # Input samples of the window's output positions; outside the record the signal is zero.
        k = (self.w0 // P + np.arange(self.n_q)) * self.decim
        self._valid = np.flatnonzero((k >= 0) & (k < self.n_fft))
        self._k = k[self._valid]
        # Matched filter, analytic doubling, and for polyphase row r an advance by r / fs_up.
        mf = 2 * np.conj(sfft.rfft(self.sweep, self.n_fft)[self.band])
        advance = np.exp(2j * np.pi * f[None, :] * np.arange(P)[:, None] / fs_up)
        self._mf = (mf[None, :] * advance).astype(np.complex64)  # (P, F)
        self._local = threading.local()
        self.norm = 1.0
        self.norm = self._calibrate()

    def _calibrate(self) -> float:
        """The envelope peak of a lone unit echo, steered at its own direction, through this very
        chain (the grid's azimuths need not include the echo's: 90 bins have no broadside)."""
        t_echo = 2 * self.grid.range_centres()[self.grid.n_range // 2] / self.c - self.start_s
        k0 = int(round(t_echo * self.fs))
        sig = np.zeros((len(self.positions), self.n_samples), np.float32)
        n = max(0, min(len(self.sweep), self.n_samples - k0))
        sig[:, k0:k0 + n] = self.sweep[:n]  # broadside: every channel at once
        look = np.full((1, len(self.positions)), self.j0 * self.stride - self.w0, np.int64)
        return float(self._envelope(sig, look).max())

    def analytic(self, sig: np.ndarray, dmas: bool = True) -> tuple[np.ndarray, ...]:
        """Per-channel polyphase tables (M, stride, Q) float32 of the matched-filtered analytic
        signal upsampled by ``up``: real part, imaginary part, cube root of the real part, power.

        Row r holds the signal at the output rate advanced by r upsampled samples: one short
        inverse FFT per row (a fractional delay in the frequency domain) instead of one long one
        per channel and a transposition."""
        M, P = sig.shape[0], self.stride
        band = slice(int(self.band[0]), int(self.band[-1]) + 1)  # contiguous: slices, not fancy indexing
        X = sfft.rfft(np.asarray(sig[:, :self.n_use], np.float32), self.n_fft, axis=1)[:, band]
        zr = np.zeros((M, P, self.n_q), np.float32)
        zi = np.zeros((M, P, self.n_q), np.float32)
        if not len(self._k):
            return zr, zi, zr.copy(), zi.copy()  # the window lies outside the record
        src = slice(int(self._k[0]), int(self._k[-1]) + 1, self.decim)
        dst = slice(int(self._valid[0]), int(self._valid[-1]) + 1)
        step = 8  # channels per inverse FFT: the complex intermediate stays a few MB
        full = getattr(self._local, "full", None)
        if full is None or full.shape[0] < min(step, M):
            # one buffer per thread: outside the band it stays zero (the inverse FFT does not
            # overwrite its input), so it is cleared once, not for every measurement
            full = self._local.full = np.zeros((min(step, M), P, self.n_fft), np.complex64)
        for m0 in range(0, M, step):
            m1 = min(M, m0 + step)
            buf = full[:m1 - m0]
            np.multiply(X[m0:m1, None, :], self._mf[None], out=buf[:, :, band])
            z = sfft.ifft(buf, axis=2)
            zr[m0:m1, :, dst] = z.real[:, :, src]
            zi[m0:m1, :, dst] = z.imag[:, :, src]
        if not dmas:  # delay-and-sum reads only the analytic signal
            return zr, zi, zr[:0], zr[:0]
        pw = zr * zr
        pw += zi * zi
        return zr, zi, np.cbrt(zr), pw

    def _envelope(self, sig: np.ndarray, shift: np.ndarray) -> np.ndarray:
        dmas = self.beamformer != "das"
        out = _gather(*self.analytic(sig, dmas), shift, self.n_out, dmas)
        if not dmas:  # already the analytic signal's modulus
            return envelope_lowpass(out, self.fs_out, axis=-1)
        return detect(out, self.fs_out, self.detector)

    def envelope(self, sig: np.ndarray) -> np.ndarray:
        """Low-passed envelope (A, n_out) on the output window."""
        return self._envelope(sig, self.shift) / self.norm

    def amplitude(self, sig: np.ndarray) -> np.ndarray:
        """Envelope amplitude (R, A) float32 of one measurement's signals (M, n_samples)."""
        return bin_average(self.envelope(sig), self.edges)

    def exact_amplitude(self, sig: np.ndarray) -> np.ndarray:
        """The same from the exact path (frequency-domain steering at the recording's rate): slow,
        the simple reference."""
        fs = float(self.fs)
        n_fft = sfft.next_fast_len(2 * self.n_samples)
        band, f = band_bins(n_fft, fs, self.band_hz or sweep_band(self.sweep, fs))
        X = sfft.rfft(np.asarray(sig, float), n_fft, axis=1)[None, :, band]
        Y = X * np.conj(sfft.rfft(self.sweep, n_fft)[band])
        t_idx = range_samples(self.grid, fs, n_fft, self.c, self.start_s)
        env = band_envelope(Y, steering(f, self.proj, self.c), band, n_fft, fs, t_idx, self.beamformer,
                            self.detector)
        edges = range_edges(self.grid, fs, n_fft, self.c, self.start_s)
        return bin_average(env[0] / sweep_norm(self.sweep, fs, self.detector), edges)
