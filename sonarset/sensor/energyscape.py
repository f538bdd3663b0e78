"""The energyscape stage of the eRTIS toolchain: beamformer models and image post-processing.

The Cosys-Lab Acoustic-Imaging-Toolbox (``calculateDMASCF``, ``generate2DEnergyscape``) makes a
robot's energyscape as: matched filter -> beamformer -> envelope -> Gaussian smoothing -> subtract
a factor x the mean over azimuth at each range -> clip at zero -> log with a floor. The
post-processing (everything after the envelope) is an image operation; it is shared here by the
fast image-domain model (``sonar.SonarModel``) and the signal-level reference
(``reference.reference_amplitude``), whose beamformers are independent.

DMAS3 (third-order delay-multiply-and-sum, Matrone et al. 2015, as in the toolbox): the signed
cube root of every delayed channel, then the sum over all channel triples of their products (the
third elementary symmetric polynomial), normalised here by C(N, 3) so that N aligned channels of
amplitude a give a. The coherence factor (Mallart & Fink 1994) is
CF = |sum of analytic channel signals|^2 / (N sum of their |.|^2), multiplied onto the output.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import ndimage, special

from sonarset.format.attrs import Processing, SensorGrid
from sonarset.sensor.ertis import C_SOUND, F_HI, F_LO, microphone_y


def dmas3(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Normalised DMAS3 of real channel signals along ``axis``: e3(sign(x) |x|^(1/3)) / C(N, 3).

    The third elementary symmetric polynomial comes from the power sums by Newton's identity,
    e3 = (S1^3 - 3 S1 S2 + 2 S3) / 6, which costs O(N) instead of O(N^3) triples.
    """
    c = np.cbrt(x)
    s1, s2, s3 = c.sum(axis), (c * c).sum(axis), (c * c * c).sum(axis)
    n = x.shape[axis]
    return (s1 ** 3 - 3 * s1 * s2 + 2 * s3) / 6 / math.comb(n, 3)


@functools.lru_cache(maxsize=4)
def dmas3_beam_table(n: int = 4001, n_phase: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """(Δu in [-2, 2], amplitude pattern of DMAS3, peak 1) of the eRTIS array, energy-averaged over
    the 25-50 kHz band as ``sonar.beam_table`` is for delay-and-sum.

    At each frequency a plane wave from Δu away from the look direction leaves channel m with phase
    k y_m Δu; DMAS3 is not linear, so its output power is averaged over the carrier's phase (it
    includes the odd harmonics the cube roots make, which the envelope keeps). Tabulated coarsely
    in Δu and interpolated: the pattern is smooth on the 0.005 step used.
    """
    y = microphone_y()
    du_coarse = np.linspace(-2, 2, 801)
    phase = 2 * np.pi * np.arange(n_phase) / n_phase
    power = np.zeros(len(du_coarse))
    freqs = np.linspace(F_LO, F_HI, 26)
    for f in freqs:
        k = 2 * np.pi * f / C_SOUND
        # (Δu, phase, mic): the delayed channels of a unit plane wave
        ch = np.cos(phase[None, :, None] + k * du_coarse[:, None, None] * y[None, None, :])
        power += 2 * (dmas3(ch) ** 2).mean(1)  # x2: a unit cosine has mean power 1/2
    du = np.linspace(-2, 2, n)
    return du, np.sqrt(np.interp(du, du_coarse, power / len(freqs)))


@functools.lru_cache(maxsize=4)
def dmas3_noise_gain(n_channels: int) -> float:
    """Output noise power of DMAS3 over that of delay-and-sum, both normalised to unit coherent gain,
    for independent Gaussian channel noise.

    e3 of N independent zero-mean terms has E[e3^2] = C(N,3) E[c^2]^3, with c the signed cube root
    of a Gaussian of variance s^2: E[|x|^(2/3)] = s^(2/3) 2^(1/3) Γ(5/6) / sqrt(π). Normalised by
    C(N,3)^2, and compared with delay-and-sum's s^2 / N: 32 channels give -24.8 dB.
    """
    m23 = 2 ** (1 / 3) * special.gamma(5 / 6) / math.sqrt(math.pi)
    return float(m23 ** 3 / math.comb(n_channels, 3) * n_channels)


def smoothing_sigma_bins(grid: SensorGrid, processing: Processing) -> tuple[float, float]:
    """The Gaussian smoothing's sigma in (range, azimuth) bins of ``grid``."""
    return (processing.smoothing_range_m / grid.range_step,
            math.radians(processing.smoothing_azimuth_deg) / grid.azimuth_step)


def smooth(amplitude: np.ndarray, grid: SensorGrid, processing: Processing) -> np.ndarray:
    """Gaussian smoothing of beamformed amplitude (..., R, A), in place when it is float32.

    As MATLAB's ``imgaussfilt``, which the toolbox calls: the kernel is truncated at 2 sigma
    (filter size 2 ceil(2 sigma) + 1) and the edges are replicated.
    """
    sr, sa = smoothing_sigma_bins(grid, processing)
    out = amplitude
    for axis, s in ((-2, sr), (-1, sa)):
        if s > 0:
            out = ndimage.gaussian_filter1d(out, s, axis=axis, mode="nearest", truncate=2.0, output=out)
    return out


def postprocess(amplitude: np.ndarray, grid: SensorGrid, processing: Processing, full_scale: float,
                out: np.ndarray | None = None) -> np.ndarray:
    """Pixels in [0, 1] from beamformed envelope amplitude (..., R, A).

    ``full_scale`` is the amplitude that maps to 0 dB (the sensor's strongest echo, after the same
    beamformer and smoothing). ``amplitude`` (float32) is overwritten.
    """
    a = np.asarray(amplitude, np.float32)
    a = smooth(a, grid, processing)
    if processing.azimuth_mean_factor:
        a -= np.float32(processing.azimuth_mean_factor) * a.mean(axis=-1, keepdims=True)
    if processing.clip_at_zero:
        np.maximum(a, 0, out=a)
    a *= np.float32(1 / full_scale)
    if processing.floor_offset:
        a += np.float32(10 ** (processing.floor_db / 20))
    np.maximum(a, np.float32(1e-30), out=a)
    db = np.log10(a, out=a)
    # pixel = (20 log10(a) - floor) / span, folded into one multiply-add
    db *= np.float32(20 / processing.span_db)
    db -= np.float32(processing.floor_db / processing.span_db)
    return np.clip(db, 0, 1, out=db if out is None else out)
