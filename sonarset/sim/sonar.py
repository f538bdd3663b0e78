"""eRTIS-like 2D imaging sonar: visible reflectors -> log energyscape on the sensor grid.

The fast image-domain model: the echo of every visible reflector (reflectivity x specular lobe x
spreading x emitter directivity x air absorption) is spread over the grid by separable PSFs, the
range PSF (the low-passed envelope of the matched-filtered sweep) and the azimuth PSF (the array's
beam pattern, shift-invariant in u = sin theta). docs/physics.md has every number with its
source; each constant below names its own.

Echoes add incoherently in energy. The image is then made as the sensor's toolchain makes it
(``energyscape.py``, the ``processing`` settings): delay-and-sum, or DMAS3 with a coherence factor
(its pattern ``energyscape.dmas3_beam_table``; the factor from the ratio of beamformed energy to the
energy at one microphone, which is exact for one echo and for noise), then smoothing, removal of
1.5 x the azimuth mean, clipping and a log with a floor. The ``raw`` profile is delay-and-sum energy
with no post-processing: clip((10 log10(E / E_full) + 60) / 60, 0, 1), where E_full is the image
peak of a perfect wall at normal incidence at the minimum range 0.5 m.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy import signal, special

from sonarset.format.attrs import Processing, SensorGrid
from sonarset.sensor.energyscape import dmas3_beam_table, dmas3_noise_gain, postprocess, smooth
from sonarset.sensor.ertis import AZIMUTH_PSFS, C_SOUND, F_HI, F_LO, envelope_lowpass, microphone_y, sweep
from sonarset.sim.kernels import accumulate_psf_coherence, coherence_amplitude, reflector_echoes
from sonarset.sim.robot import sensor_pose
from sonarset.sim.spec import check_psf
from sonarset.sim.world import World

ABSORPTION_DB_PER_M = 1.3  # at 40 kHz (ISO 9613-1:1993, 20 degC, 50 % RH), over the two-way path 2r
EMITTER_RADIUS = 0.004  # m, a baffled circular piston (Kinsler et al., Fundamentals of Acoustics, 7.5)
SPECULAR_N = 6  # cos^n lobe of a wall (Kuc & Siegel 1987: n in 5-8 for smooth walls)
# matched filter and array: 10 log10 of the time-bandwidth product 62.5 (18 dB) and of 32 microphones (15 dB)
PROCESSING_GAIN_DB = 33.0
# Electronic noise floor of the sensor after processing, dB re full scale. The per-frame SNR sets
# the noise relative to the frame's strongest echo; without a floor, a robot facing open space
# would see its noise shrink with its echoes to a black image, which no real sensor shows.
NOISE_FLOOR_DB = -55.0
FS = 500e3  # sampling rate for tabulating the range PSF
WALL_STEP = 0.02  # m between wall samples; energies are weighted by it, so images do not depend on it


@functools.lru_cache(maxsize=4)
def range_psf_table(fs: float = FS) -> tuple[np.ndarray, np.ndarray]:
    """(range offsets [m], amplitude envelope, peak 1) of a point reflector after processing."""
    s = sweep(fs)
    mf = signal.correlate(s, s, mode="full")
    env = envelope_lowpass(np.abs(signal.hilbert(mf)), fs)
    env = np.maximum(env, 0) / env.max()
    lag = (np.arange(len(mf)) - (len(s) - 1)) / fs
    dr = lag * C_SOUND / 2
    keep = np.abs(dr) <= 0.12
    return dr[keep], env[keep]


@functools.lru_cache(maxsize=4)
def beam_table(n: int = 4001) -> tuple[np.ndarray, np.ndarray]:
    """(Δu in [-2, 2], amplitude beam pattern, peak 1): delay-and-sum, energy-averaged over the band."""
    y = microphone_y()
    du = np.linspace(-2, 2, n)
    freqs = np.linspace(F_LO, F_HI, 26)
    energy = np.zeros(n)
    for f in freqs:
        k = 2 * np.pi * f / C_SOUND
        energy += np.abs(np.exp(1j * k * np.outer(du, y)).sum(1) / len(y)) ** 2
    return du, np.sqrt(energy / len(freqs))


@functools.lru_cache(maxsize=4)
def mainlobe_table(n: int = 4001) -> tuple[np.ndarray, np.ndarray]:
    """A side-lobe-free beam: a Gaussian in u with the array pattern's -3 dB width.

    Not a physical array; it isolates the effect of side lobes (with it, acoustic flow beats the
    naive shift as in the paper; with the real array's side-lobe plateau it does not, BENCHMARKS.md).
    """
    du, bp = beam_table(n)
    e = bp ** 2
    half = np.flatnonzero(e >= 0.5 * e.max())
    sigma = (du[half[-1]] - du[half[0]]) / (2 * np.sqrt(2 * np.log(2)))
    return du, np.exp(-du ** 2 / (4 * sigma ** 2))


BEAMS = dict(zip(AZIMUTH_PSFS, (beam_table, mainlobe_table)))  # the tables, in AZIMUTH_PSFS's order


def emitter_directivity(theta: np.ndarray, f: float = 40e3) -> np.ndarray:
    x = 2 * np.pi * f / C_SOUND * EMITTER_RADIUS * np.sin(theta)
    out = np.ones_like(x)
    nz = np.abs(x) > 1e-9
    out[nz] = 2 * special.j1(x[nz]) / x[nz]
    return np.abs(out)


def absorption(r: np.ndarray) -> np.ndarray:
    return 10 ** (-ABSORPTION_DB_PER_M * 2 * r / 20)


@dataclass
class Echoes:
    """Visible reflectors in the sensor frame: range [m], azimuth [rad], amplitude at a microphone,
    and, for a batch of sensor poses, the index of the frame each echo belongs to; with
    ``source`` the reflector of each (wall j: j, circle j: walls + j) and ``along`` the wall
    sample's distance from its wall's start (m; 0 for circles)."""

    r: np.ndarray
    theta: np.ndarray
    amp: np.ndarray
    frame: np.ndarray | None = None
    source: np.ndarray | None = None
    along: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.frame is None:
            self.frame = np.zeros(len(self.r), np.int64)

    def __len__(self) -> int:
        return len(self.r)


def visible_echoes(world: World, sensor: np.ndarray, r_max: float, wall_step: float = WALL_STEP) -> Echoes:
    """Every reflector the sensor at pose (x, y, heading) hears, occlusion respected.

    ``sensor`` may also be a batch of poses (F, 3); the echoes then carry their frame index. One
    vectorised pass over a batch costs far less than a pass per frame.
    """
    sensors = np.atleast_2d(np.asarray(sensor, float))
    rows = reflector_echoes(sensors, world.seg_a.reshape(-1, 2), world.seg_b.reshape(-1, 2), world.seg_refl,
                            world.circ_c.reshape(-1, 2), world.circ_r, world.circ_refl, float(r_max),
                            float(wall_step), SPECULAR_N, float(np.sqrt(wall_step / WALL_STEP)))
    r, theta = rows[:, 1], rows[:, 2]
    amp = rows[:, 3] * emitter_directivity(theta) * absorption(r)
    return Echoes(r, theta, amp, rows[:, 0].astype(np.int64), rows[:, 4].astype(np.int64), rows[:, 5])


@dataclass
class SonarModel:
    """The fast image-domain model: separable PSFs evaluated at every grid point."""

    grid: SensorGrid
    snr_db: float = 5.0
    dynamic_range_db: float = Processing.model_fields["span_db"].default  # of the raw images (the format's)
    psf: str = "array"  # azimuth PSF: "array" (the eRTIS delay-and-sum pattern) or "mainlobe"
    processing: Processing = field(default_factory=Processing.ertis)

    def __post_init__(self) -> None:
        check_psf(self.psf, self.processing)
        # raw: format 1.0's images, made by the energy-domain encoder below (bit for bit the same)
        self._raw = self.processing.beamformer == "das" and not self.processing.post_processed
        dr, env = range_psf_table()
        du, bp = BEAMS[self.psf]()
        self._r_step = dr[1] - dr[0]
        # Each range bin holds the energy averaged over its width (decimation of the finely sampled
        # envelope with a box filter): a 2 cm PSF point-sampled on 2.25 cm bins would alias, making
        # echo levels depend on where a reflector falls within a bin.
        box = max(1, int(round(self.grid.range_step / self._r_step)))
        if 2 * box > len(env):
            # Bins wider than half the envelope table (0.12 m): the average spreads the main lobe
            # beyond the table, so widen it with zeros first ('same' mode keeps the table's length;
            # finer grids keep their images bit for bit).
            dr = dr[0] + self._r_step * np.arange(-box, len(env) + box)
            env = np.pad(env, box)
        self._r0, self._renv2 = dr[0], np.convolve(env ** 2, np.ones(box) / box, mode="same")
        self._u_step = du[1] - du[0]
        self._beam2 = bp ** 2
        if self.processing.beamformer == "dmas3-cf":
            du3, b3 = dmas3_beam_table(len(du))
            assert np.allclose(du3, du)
            self._beam3_2 = b3 ** 2
            # DMAS3's side lobes sit near -43 dB and the coherence factor takes them ~30 dB lower
            # (it is the delay-and-sum pattern squared for one echo): below the 60 dB display range,
            # so only the main lobe down to -40 dB is accumulated.
            below = np.abs(du)[b3 < 1e-2]
            self._u3_max = float(below.min())  # the main lobe's -40 dB half-width in u
            self._n_mics = len(microphone_y())
            self._dmas3_noise = np.float32(dmas3_noise_gain(self._n_mics))
        self.r_c = self.grid.range_centres()
        self.u_c = np.sin(self.grid.azimuth_centres())
        if self.processing.beamformer == "dmas3-cf" and not np.all(np.diff(self.u_c) > 0):
            self._u3_max = 2.0  # azimuths beyond +-90 deg: u is not monotonic, accumulate everywhere
        # noise correlation lengths in bins: the PSF widths at broadside (Gaussian sigma)
        sig = (max(0.0085 / self.grid.range_step, 0.3), max(np.radians(2.4) / self.grid.azimuth_step, 0.3))
        fr, fa = np.fft.fftfreq(self.grid.n_range), np.fft.fftfreq(self.grid.n_azimuth)
        self._noise_tf = np.exp(-2 * np.pi ** 2 * ((fr[:, None] * sig[0]) ** 2 + (fa[None, :] * sig[1]) ** 2)).astype(np.float32)
        self._noise_keep = np.flatnonzero(np.exp(-2 * np.pi ** 2 * (fa * sig[1]) ** 2) >= 0.1)
        # The range PSF is evaluated where it is above -60 dB of its peak: farther out, even a
        # full-scale echo adds less than the 60 dB display range resolves.
        support = np.abs(dr[self._renv2 > 1e-6 * self._renv2.max()]).max() + self.grid.range_step
        k = int(np.ceil(support / self.grid.range_step)) + 1
        self._offsets = np.arange(-k, k + 1)
        self.e_full, self.a_full = self._full_scale()

    def _full_scale(self) -> tuple[float, float]:
        """(peak delay-and-sum energy, peak processed amplitude) of a perfect wall at normal incidence
        at the grid's minimum range: the strongest echo the sensor can see, through the same
        beamformer and smoothing."""
        r0 = max(self.grid.range_min_m, 0.05) + self.grid.range_step / 2
        world = World("cal", np.array([[r0, -50.0]]), np.array([[r0, 50.0]]), np.ones(1),
                      np.zeros((0, 2)), np.zeros(0), np.zeros(0))
        ech = visible_echoes(world, np.zeros(3), r0 + 1.0)
        e_full = float(self.energy(ech).max())
        if self._raw:
            return e_full, float(np.sqrt(e_full))
        amp = smooth(self.amplitude(ech, 1)[0][0], self.grid, self.processing)
        return e_full, float(amp.max())

    def energy(self, echoes: Echoes, n_frames: int | None = None) -> np.ndarray:
        """Noise-free echo energy on the grid: (n_range, n_azimuth), or (n_frames, n_range, n_azimuth)
        for echoes of a batch of frames."""
        R, A = self.grid.shape
        F = 1 if n_frames is None else n_frames
        e = np.zeros((F, R, A), np.float32)  # single precision: the image is float16 in the end
        if len(echoes):
            # delay-and-sum alone: no DMAS3 columns (u3_max < 0), the per-microphone energy discarded
            accumulate_psf_coherence(e, e, np.zeros((F, R), np.float32), echoes.frame, echoes.r, np.sin(echoes.theta),
                                     echoes.amp ** 2, self.r_c, self.grid.range_step, self._offsets, self._renv2,
                                     self._r0, self._r_step, self.u_c, self._beam2, self._beam2, self._u_step, -1.0)
        return e[0] if n_frames is None else e

    def amplitude(self, echoes: Echoes, n_frames: int, rng: np.random.Generator | None = None,
                  snr_db=None) -> tuple[np.ndarray, np.ndarray]:
        """Beamformed envelope amplitude (n_frames, R, A) float32, before post-processing, and the
        frames' effective SNRs (n_frames,) as ``noise_sigma`` gives them.

        With ``rng``, sensor noise is added (``snr_db`` overrides the model's SNR per frame): drawn
        as ``noise_energy`` (the same numbers whatever the beamformer) and passed through the
        beamformer. DMAS3 sees the same noise field, ``dmas3_noise_gain`` weaker; the coherence
        factor is (beamformed energy) / (energy at one microphone), the noise's share of which is
        N sigma^2 (the array's gain is N).
        """
        R, A = self.grid.shape
        if self.processing.beamformer == "das":
            e = self.energy(echoes, n_frames)
        else:
            e = np.zeros((n_frames, R, A), np.float32)
            e3 = np.zeros((n_frames, R, A), np.float32)
            e_mic = np.zeros((n_frames, R), np.float32)
            if len(echoes):
                accumulate_psf_coherence(e, e3, e_mic, echoes.frame, echoes.r, np.sin(echoes.theta), echoes.amp ** 2,
                                         self.r_c, self.grid.range_step, self._offsets, self._renv2, self._r0,
                                         self._r_step, self.u_c, self._beam2, self._beam3_2, self._u_step,
                                         self._u3_max)
        eff = np.full(n_frames, np.inf)
        noise = None
        if rng is not None:
            sigma, eff = self.noise_sigma(e, self.snr_db if snr_db is None else snr_db)
            noise = self.noise_energy(sigma, rng, band_limited=True)
        if self.processing.beamformer == "das":
            if noise is not None:
                e += noise
            return np.sqrt(e, out=e), eff
        has_noise = noise is not None
        if not has_noise:
            noise, mic_noise = np.zeros((1, 1, 1), np.float32), np.zeros(n_frames, np.float32)
        else:
            mic_noise = (self._n_mics * sigma.astype(np.float32) ** 2)
        # amplitude = sqrt(DMAS3 energy) x CF, in place in e3 (sonarset/sim/kernels.py)
        coherence_amplitude(e, e3, e_mic, noise, has_noise, self._dmas3_noise, mic_noise)
        return e3, eff

    def pixels(self, amplitude: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Post-processed pixels in [0, 1] from ``amplitude`` (overwritten)."""
        return postprocess(amplitude, self.grid, self.processing, self.a_full, out)

    def noise_sigma(self, energy: np.ndarray, snr_db) -> tuple[np.ndarray, np.ndarray]:
        """(image-domain noise std, effective SNR at the microphones in dB) per frame of ``energy``
        (F, R, A): noise ``snr_db`` below each frame's strongest echo, never under the floor, so
        near the floor a frame's real SNR is below the nominal one.

        The PSFs peak at 1, so the image peak is the strongest echo's amplitude at a microphone
        (for a wall, the whole specular return); matched filter and beamformer then lower the
        noise by the processing gain.
        """
        peak = np.sqrt(energy.reshape(len(energy), -1).max(1))
        sigma = peak * 10 ** (-(np.asarray(snr_db, float) + PROCESSING_GAIN_DB) / 20)
        sigma = np.maximum(sigma, np.sqrt(self.e_full) * 10 ** (NOISE_FLOOR_DB / 20))
        return sigma, 20 * np.log10(np.maximum(peak, 1e-30) / sigma) - PROCESSING_GAIN_DB

    def noise_energy(self, sigma, rng: np.random.Generator, band_limited: bool = False) -> np.ndarray:
        """Noise energy per pixel: complex Gaussian noise of std ``sigma``, shaped like the PSF.

        ``sigma`` a number gives one frame (R, A); an array of F gives a batch (F, R, A), drawing
        the same random numbers as F single frames in turn.
        """
        sig = np.atleast_1d(np.asarray(sigma, np.float32))
        # Matched filter and beamformer correlate the noise over one PSF. The spectrum of white
        # complex Gaussian noise is itself white complex Gaussian noise, so the draw is taken as the
        # spectrum (pairs of normals viewed as complex64, no copy) and shaped in one inverse FFT
        # (single precision: a noise field needs no more).
        if band_limited:
            # Azimuth frequencies where the PSF passes under 10% of the amplitude (1% of the energy)
            # are not drawn: ~40% fewer random numbers, the largest cost of a frame.
            # Drawn in polar form (Box-Muller: a Rayleigh amplitude and a uniform phase make a complex
            # normal), from uniforms, at half the cost of numpy's normals.
            keep = self._noise_keep
            u = rng.random((len(sig), self.grid.n_range, len(keep), 2), dtype=np.float32)
            amp = np.log1p(-u[..., 0])
            amp *= -2
            np.sqrt(amp, out=amp)
            amp *= self._noise_tf[:, keep]
            phase = u[..., 1] * np.float32(2 * np.pi)
            spec = np.empty(amp.shape, np.complex64)
            spec.real = amp * np.cos(phase)
            spec.imag = amp * np.sin(phase)
            part = sfft.ifft(spec, axis=1, overwrite_x=True)
            full = np.zeros((len(sig), *self.grid.shape), np.complex64)
            full[:, :, keep] = part
            n = sfft.ifft(full, axis=2, overwrite_x=True)
        else:
            spec = rng.standard_normal((len(sig), *self.grid.shape, 2), dtype=np.float32).view(np.complex64)[..., 0]
            spec *= self._noise_tf
            n = sfft.ifft2(spec, axes=(-2, -1), overwrite_x=True)
        e = n.real ** 2 + n.imag ** 2
        e *= (sig ** 2 / e.mean(axis=(1, 2)))[:, None, None]
        return e if np.ndim(sigma) else e[0]

    def encode(self, energy: np.ndarray, noise: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """Pixels (10 log10(E / E_full) + DR) / DR clipped to [0, 1] of energy (plus noise): float32,
        or written into ``out`` (e.g. a float16 block)."""
        e = np.add(energy, 0 if noise is None else noise, dtype=np.float32)
        np.maximum(e, np.float32(1e-30), out=e)
        db = np.log10(e, out=e)
        # folded into one multiply-add: gain * log10(E) + 1 - gain * log10(E_full)
        gain = 10 / self.dynamic_range_db
        db *= np.float32(gain)
        db += np.float32(1 - gain * np.log10(self.e_full))
        return np.clip(db, 0, 1, out=db if out is None else out)

    def render(self, world: World, robot_pose: np.ndarray, rng: np.random.Generator | None,
               snr_db: float | None = None, return_snr: bool = False):
        """The energyscape seen from ``robot_pose``; no noise when ``rng`` is None.

        With ``return_snr`` also returns the frame's effective SNR at the microphones (dB).
        """
        img, eff = self.render_batch(world, np.asarray(robot_pose, float)[None], rng,
                                     None if snr_db is None else np.array([snr_db]))
        return (img[0], float(eff[0])) if return_snr else img[0]

    def render_batch(self, world: World, robot_poses: np.ndarray, rng: np.random.Generator | None,
                     snr_db: np.ndarray | None = None, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Energyscapes (F, R, A) float32 (or written into ``out``) and effective SNRs (F,) seen from
        robot poses (F, 3).

        ``snr_db`` (F,) overrides the model's SNR per frame (noise bursts). Rendering F frames in one
        call gives the same images as F calls of ``render`` with the same generator.
        """
        poses = np.asarray(robot_poses, float)
        ech = visible_echoes(world, sensor_pose(poses), self.grid.range_max_m + 0.1)
        if not self._raw:
            amp, eff = self.amplitude(ech, len(poses), rng, snr_db)
            return self.pixels(amp, out), eff
        e = self.energy(ech, len(poses))
        eff, noise = np.full(len(poses), np.inf), None
        if rng is not None:
            sigma, eff = self.noise_sigma(e, self.snr_db if snr_db is None else snr_db)
            noise = self.noise_energy(sigma, rng)
        return self.encode(e, noise, out), eff
