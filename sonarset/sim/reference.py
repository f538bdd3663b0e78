"""Slow signal-level reference of the sonar, used to validate the fast image-domain model.

For each visible reflector it synthesises the 25->50 kHz sweep at each of the 32 microphones with
the true two-way delay (emitter at the array centre; far-field arrival across the array), then
does what eRTIS processing does: matched filter, beamforming towards every azimuth of the grid,
envelope, envelope low-pass, and sampling at the grid's range bins. Two beamformers, as in the
Cosys-Lab toolbox's ``calculateDMASCF``: delay-and-sum (in the frequency domain, as an analytic
signal), and DMAS3 with a coherence factor (in the time domain, on the steered channel signals).
Nothing here shares code with the fast model's PSF tables except the sweep definition and the
microphone positions; the post-processing of the envelope image (``energyscape.postprocess``) is
an image operation that both use.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft
from scipy import signal

from ..schema import SensorGrid
from .energyscape import BEAMFORMERS, dmas3
from .sonar import C_SOUND, Echoes, envelope_lowpass, microphone_y, sweep

FS_REF = 200e3  # Hz: above Nyquist for the 50 kHz top of the sweep


def reference_energy(echoes: Echoes, grid: SensorGrid, *, realizations: int = 8, coherent: bool = False,
                     seed: int = 0, fs: float = FS_REF) -> np.ndarray:
    """Delay-and-sum echo energy on the grid (n_range, n_azimuth): ``reference_amplitude`` squared."""
    return reference_amplitude(echoes, grid, "das", realizations=realizations, coherent=coherent,
                               seed=seed, fs=fs) ** 2


def reference_amplitude(echoes: Echoes, grid: SensorGrid, beamformer: str = "das", *, realizations: int = 8,
                        coherent: bool = False, seed: int = 0, fs: float = FS_REF) -> np.ndarray:
    """Beamformed envelope amplitude on the grid (n_range, n_azimuth), from simulated microphone
    signals: RMS over the noise-free realizations, on the fast model's scale (a lone echo of
    amplitude a at a microphone peaks at a).

    The fast model adds echoes incoherently (diffuse scattering; wall samples 2 cm apart are more
    than half a wavelength apart, so their coherent sum would be an artefact of the sampling). By
    default the reference does the same in expectation: each echo gets an independent random phase
    and the energy is averaged over ``realizations``. ``coherent=True`` keeps all phases at zero.
    """
    y = microphone_y()
    s = sweep(fs)
    n_sig = int(np.ceil((2 * grid.range_max_m / C_SOUND + 0.004) * fs)) + len(s)
    n_fft = sfft.next_fast_len(2 * n_sig)
    f_all = sfft.rfftfreq(n_fft, 1 / fs)
    band = np.flatnonzero((f_all > 15e3) & (f_all < 60e3))  # the sweep has no energy elsewhere
    f = f_all[band]
    S = sfft.rfft(s, n_fft)[band]
    # Each echo reaches mic m after r (out) + r - y_m sin(theta) (back, far field across the array).
    tau = (2 * echoes.r[:, None] - y[None, :] * np.sin(echoes.theta)[:, None]) / C_SOUND  # (N, M)
    u = np.sin(grid.azimuth_centres())
    # Delay-and-sum steering: undo each microphone's lead y_m sin(theta) / c, for every look direction.
    steer = np.exp(-2j * np.pi * f[:, None, None] * (y[None, None, :] * u[None, :, None]) / C_SOUND)  # (F, A, M)
    norm = envelope_lowpass(np.abs(signal.hilbert(signal.correlate(s, s))), fs).max()
    t_idx = np.clip(np.rint(2 * grid.range_centres() / C_SOUND * fs).astype(int), 0, n_fft - 1)
    rng = np.random.default_rng(seed)
    n_real = 1 if coherent else max(1, realizations)
    phase = np.zeros((1, len(echoes))) if coherent else rng.uniform(0, 2 * np.pi, (n_real, len(echoes)))
    weights = echoes.amp[None, :] * np.exp(1j * phase)  # (K, N): one row per realization
    X = np.empty((n_real, len(y), len(f)), complex)
    for m in range(len(y)):  # per microphone, to bound memory: (N, F) phase terms at a time
        X[:, m] = weights @ np.exp(-2j * np.pi * tau[:, m, None] * f[None, :])
    Y = X * (np.abs(S) ** 2)[None, None, :]  # sweep spectrum times its matched filter
    if beamformer not in BEAMFORMERS:
        raise ValueError(f"beamformer must be one of {', '.join(BEAMFORMERS)}, got {beamformer!r}")
    if beamformer == "das":
        Z = np.einsum("fam,kmf->kaf", steer, Y) / len(y)
        # Analytic signal: positive frequencies doubled, inverse FFT, magnitude = envelope.
        full = np.zeros((n_real, len(u), n_fft), complex)
        full[:, :, band] = 2 * Z
        env = envelope_lowpass(np.abs(sfft.ifft(full, axis=2)), fs, axis=2)
    else:
        env = np.empty((n_real, len(u), n_fft))
        # Only the samples of the grid's ranges (with a margin for the filters' edges) are processed.
        t0 = max(0, int(t_idx.min()) - int(0.002 * fs))
        t1 = min(n_fft, int(t_idx.max()) + int(0.002 * fs))
        env[:] = 0
        for a in range(len(u)):
            # The channels steered towards azimuth a, as analytic signals (K, M, T).
            full = np.zeros((n_real, len(y), n_fft), complex)
            full[:, :, band] = 2 * Y * steer[:, a, :].T[None]
            z = sfft.ifft(full, axis=2)[:, :, t0:t1]
            out = dmas3(z.real, axis=1)
            out *= np.abs(z.sum(1)) ** 2 / (len(y) * (np.abs(z) ** 2).sum(1) + 1e-300)  # coherence factor
            env[:, a, t0:t1] = envelope_lowpass(np.abs(signal.hilbert(out, axis=-1)), fs, axis=-1)
    amp = np.maximum(env[:, :, t_idx], 0) / norm  # (K, A, R)
    return np.sqrt((amp ** 2).mean(0).T)
