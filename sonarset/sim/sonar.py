"""eRTIS-like 2D imaging sonar: visible reflectors -> log energyscape on the sensor grid.

Physics (DESIGN.md §3), with sources:
- Sound speed 343 m/s (dry air, 20 °C).
- Air absorption 1.3 dB/m at 40 kHz (ISO 9613-1:1993, 20 °C, 50 % RH), applied over the two-way
  path 2r.
- Emitter: baffled circular piston, D(θ) = 2 J1(ka sinθ) / (ka sinθ) (Kinsler et al., Fundamentals
  of Acoustics, §7.5), radius 4 mm at 40 kHz.
- Specular lobe cos^n of the incidence angle, n = 6 (Kuc & Siegel 1987 use n in 5-8 for smooth walls).
- Spreading: wall ~ 1/(2r) (image source), pole of radius a ~ sqrt(a)/(2 r^1.5), point ~ a/(2r^2)
  (cylinder and sphere backscatter, Bowman et al., Electromagnetic and Acoustic Scattering by Simple
  Shapes).
- Range PSF: envelope of the matched-filtered, Hann-windowed 25->50 kHz FM sweep of 2.5 ms, low-passed
  at 6 kHz: FWHM 2.06 cm (eRTIS processing, Kerstens et al. 2019; public RTIS Dev defaults). Each
  range bin averages the energy over its width, so coarse grids do not alias the PSF.
- Azimuth PSF: delay-and-sum beam pattern of the 32-microphone eRTIS array (sonarset/data/
  ertis32_microphones.csv), energy-averaged over the sweep band: -3 dB width 5.6° broadside, growing
  as 1/cos θ because a linear array's pattern is shift-invariant in u = sin θ.
- Noise: SNR is peak echo amplitude over noise std at one microphone; matched filter and array add
  ~33 dB processing gain (10 log10 of time-bandwidth 62.5 plus 32 microphones: 18 + 15 dB).

Echoes add incoherently in energy. Pixels: clip((10 log10(E / E_full) + 60) / 60, 0, 1), where E_full
is the image peak of a perfect wall at normal incidence at the minimum range 0.5 m.
"""

from __future__ import annotations

import csv
import functools
from dataclasses import dataclass
from importlib import resources

import numpy as np
from scipy import fft as sfft
from scipy import signal, sparse, special

from ..schema import SensorGrid
from .robot import sensor_pose
from .world import World

C_SOUND = 343.0
ABSORPTION_DB_PER_M = 1.3
F_LO, F_HI, SWEEP_S = 25e3, 50e3, 2.5e-3
ENVELOPE_LP_HZ = 6e3
EMITTER_RADIUS = 0.004
SPECULAR_N = 6
PROCESSING_GAIN_DB = 33.0
# Electronic noise floor of the sensor after processing, dB re full scale. The per-frame SNR sets
# the noise relative to the frame's strongest echo; without a floor, a robot facing open space
# would see its noise shrink with its echoes to a black image, which no real sensor shows.
NOISE_FLOOR_DB = -55.0
DYNAMIC_RANGE_DB = 60.0
FS = 500e3  # sampling rate for tabulating the range PSF
WALL_STEP = 0.02  # m between wall samples; energies are weighted by it, so images do not depend on it


def microphone_y() -> np.ndarray:
    """Horizontal (y, positive left) positions of the 32 eRTIS microphones, metres."""
    text = resources.files("sonarset").joinpath("data/ertis32_microphones.csv").read_text()
    rows = [r for r in csv.reader(text.splitlines()) if r and not r[0].startswith("#")]
    header = rows[0]
    return np.array([float(r[header.index("y")]) for r in rows[1:]])


def sweep(fs: float = FS) -> np.ndarray:
    t = np.arange(int(round(SWEEP_S * fs))) / fs
    return signal.chirp(t, F_LO, SWEEP_S, F_HI) * signal.windows.hann(len(t))


def envelope_lowpass(env: np.ndarray, fs: float, axis: int = -1) -> np.ndarray:
    b, a = signal.butter(2, ENVELOPE_LP_HZ, fs=fs)
    return signal.filtfilt(b, a, env, axis=axis)


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


BEAMS = {"array": beam_table, "mainlobe": mainlobe_table}


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
    """Visible reflectors in the sensor frame: range [m], azimuth [rad], amplitude at a microphone."""

    r: np.ndarray
    theta: np.ndarray
    amp: np.ndarray

    def __len__(self) -> int:
        return len(self.r)


def _ray_blocked(s: np.ndarray, p: np.ndarray, world: World, skip_seg: np.ndarray | None,
                 skip_circ: np.ndarray | None) -> np.ndarray:
    """For rays sensor s -> points p (N, 2): is something closer than p in the way?

    Only walls and circles that come closer to the sensor than the farthest point can block; the
    others are left out of the (N x S) intersection test, which changes no result.
    """
    n = len(p)
    blocked = np.zeros(n, bool)
    if n == 0:
        return blocked
    d = p - s  # (N, 2)
    reach = float(np.sqrt((d ** 2).sum(1).max()))
    if len(world.seg_a):
        ab = world.seg_b - world.seg_a
        t0 = np.clip(((s - world.seg_a) * ab).sum(1) / np.maximum((ab ** 2).sum(1), 1e-12), 0, 1)
        near = np.flatnonzero(np.linalg.norm(world.seg_a + t0[:, None] * ab - s, axis=1) <= reach)
    else:
        near = np.zeros(0, np.int64)
    if len(near):
        e = world.seg_b[near] - world.seg_a[near]  # (S', 2)
        w = world.seg_a[near] - s  # (S', 2)
        den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (N, S)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / den  # along the ray
            u = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / den  # along the wall
        hit = (np.abs(den) > 1e-12) & (t > 1e-6) & (t < 1 - 1e-4) & (u >= 0) & (u <= 1)
        if skip_seg is not None:
            hit &= skip_seg[:, None] != near[None, :]  # a wall sample is not blocked by its own wall
        blocked |= hit.any(1)
    cnear = np.flatnonzero(np.linalg.norm(world.circ_c - s, axis=1) - world.circ_r <= reach) if len(world.circ_c) else []
    if len(cnear):
        L = np.linalg.norm(d, axis=1)  # (N,)
        dirn = d / np.maximum(L, 1e-12)[:, None]
        oc = world.circ_c[cnear] - s  # (C', 2)
        r = world.circ_r[cnear]
        proj = dirn @ oc.T  # (N, C')
        perp2 = (oc ** 2).sum(1)[None] - proj ** 2
        half = np.sqrt(np.maximum(r[None] ** 2 - perp2, 0))
        entry = proj - half
        hit = (perp2 < r[None] ** 2) & (entry > 1e-6) & (entry < L[:, None] - 1e-4)
        if skip_circ is not None:
            hit &= skip_circ[:, None] != cnear[None, :]  # nor a pole by itself
        blocked |= hit.any(1)
    return blocked


def visible_echoes(world: World, sensor: np.ndarray, r_max: float, wall_step: float = WALL_STEP) -> Echoes:
    """Every reflector the sensor at pose (x, y, heading) hears, occlusion respected."""
    s, heading = sensor[:2], sensor[2]
    pts, amps, segs, circs = [], [], [], []
    # Walls: dense samples within r_max, each an element of length wall_step (all walls at once).
    if len(world.seg_a):
        a, b = world.seg_a, world.seg_b
        e = b - a
        L = np.linalg.norm(e, axis=1)
        unit = e / L[:, None]
        rel = s - a
        foot = (rel * unit).sum(1)
        dperp = np.abs(rel[:, 0] * unit[:, 1] - rel[:, 1] * unit[:, 0])
        near = dperp < r_max
        h = np.sqrt(np.maximum(r_max ** 2 - dperp ** 2, 0))
        lo = np.where(near, np.maximum(0.0, foot - h), 0.0)
        hi = np.where(near, np.minimum(L, foot + h), 0.0)
        count = np.maximum(np.floor((hi - lo) / wall_step + 0.5).astype(np.int64), 0) * near
        if count.sum():
            seg_id = np.repeat(np.arange(len(L)), count)
            k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
            ts = lo[seg_id] + (k + 0.5) * wall_step
            q = a[seg_id] + ts[:, None] * unit[seg_id]
            normal = np.stack([-unit[seg_id, 1], unit[seg_id, 0]], axis=1)
            to_s = s - q
            dist = np.linalg.norm(to_s, axis=1)
            cos_inc = np.abs((to_s * normal).sum(1)) / np.maximum(dist, 1e-9)
            amp = world.seg_refl[seg_id] * cos_inc ** SPECULAR_N / (2 * np.maximum(dist, 1e-3)) * np.sqrt(wall_step / WALL_STEP)
            pts.append(q), amps.append(amp), segs.append(seg_id), circs.append(np.full(len(q), -1))
    # Circles: the specular point faces the sensor.
    if len(world.circ_c):
        oc = world.circ_c - s
        dc = np.linalg.norm(oc, axis=1)
        ok = (dc - world.circ_r < r_max) & (dc > world.circ_r)
        if ok.any():
            q = world.circ_c[ok] - world.circ_r[ok, None] * oc[ok] / dc[ok, None]
            r = dc[ok] - world.circ_r[ok]
            amp = world.circ_refl[ok] * np.sqrt(world.circ_r[ok]) / (2 * np.maximum(r, 1e-3) ** 1.5)
            pts.append(q), amps.append(amp), segs.append(np.full(len(q), -1)), circs.append(np.flatnonzero(ok))
    if not pts:
        return Echoes(np.zeros(0), np.zeros(0), np.zeros(0))
    q, amp = np.concatenate(pts), np.concatenate(amps)
    seg, circ = np.concatenate(segs), np.concatenate(circs)
    rel = q - s
    r = np.linalg.norm(rel, axis=1)
    theta = np.arctan2(rel[:, 1], rel[:, 0]) - heading
    theta = (theta + np.pi) % (2 * np.pi) - np.pi
    front = (np.abs(theta) < np.pi / 2) & (r < r_max) & (r > 1e-3) & (amp > 0)
    q, amp, r, theta, seg, circ = q[front], amp[front], r[front], theta[front], seg[front], circ[front]
    vis = ~_ray_blocked(s, q, world, seg, circ)
    r, theta, amp = r[vis], theta[vis], amp[vis]
    amp = amp * emitter_directivity(theta) * absorption(r)
    return Echoes(r, theta, amp)


@dataclass
class SonarModel:
    """The fast image-domain model: separable PSFs evaluated at every grid point."""

    grid: SensorGrid
    snr_db: float = 5.0
    dynamic_range_db: float = DYNAMIC_RANGE_DB
    psf: str = "array"  # azimuth PSF: "array" (the eRTIS delay-and-sum pattern) or "mainlobe"

    def __post_init__(self) -> None:
        if self.psf not in BEAMS:
            raise ValueError(f"psf must be one of {', '.join(BEAMS)}, got {self.psf!r}")
        dr, env = range_psf_table()
        du, bp = BEAMS[self.psf]()
        self._r_step = dr[1] - dr[0]
        # Each range bin holds the energy averaged over its width (decimation of the finely sampled
        # envelope with a box filter): a 2 cm PSF point-sampled on 2.25 cm bins would alias, making
        # echo levels depend on where a reflector falls within a bin.
        box = max(1, int(round(self.grid.range_step / self._r_step)))
        self._r0, self._renv2 = dr[0], np.convolve(env ** 2, np.ones(box) / box, mode="same")
        self._u_step = du[1] - du[0]
        self._beam2 = bp ** 2
        self.r_c = self.grid.range_centres()
        self.u_c = np.sin(self.grid.azimuth_centres())
        # noise correlation lengths in bins: the PSF widths at broadside (Gaussian sigma)
        sig = (max(0.0085 / self.grid.range_step, 0.3), max(np.radians(2.4) / self.grid.azimuth_step, 0.3))
        fr, fa = np.fft.fftfreq(self.grid.n_range), np.fft.fftfreq(self.grid.n_azimuth)
        self._noise_tf = np.exp(-2 * np.pi ** 2 * ((fr[:, None] * sig[0]) ** 2 + (fa[None, :] * sig[1]) ** 2)).astype(np.float32)
        support = np.abs(dr[self._renv2 > 1e-8]).max() + self.grid.range_step
        k = int(np.ceil(support / self.grid.range_step)) + 1
        self._offsets = np.arange(-k, k + 1)
        self.e_full = self._full_scale()

    def _full_scale(self) -> float:
        """Peak energy of a perfect wall at normal incidence at the grid's minimum range."""
        r0 = max(self.grid.range_min_m, 0.05) + self.grid.range_step / 2
        world = World("cal", np.array([[r0, -50.0]]), np.array([[r0, 50.0]]), np.ones(1),
                      np.zeros((0, 2)), np.zeros(0), np.zeros(0))
        ech = visible_echoes(world, np.zeros(3), r0 + 1.0)
        return float(self.energy(ech).max())

    def energy(self, echoes: Echoes) -> np.ndarray:
        """Noise-free echo energy on the grid, (n_range, n_azimuth)."""
        R, A = self.grid.shape
        if not len(echoes):
            return np.zeros((R, A))
        # The range PSF spans a few bins: evaluate it only there (a sparse R x N matrix).
        i0 = np.floor((echoes.r - self.r_c[0]) / self.grid.range_step).astype(np.int64)
        bins = i0[:, None] + self._offsets[None, :]  # (N, K)
        ir = np.rint((self.r_c[np.clip(bins, 0, R - 1)] - echoes.r[:, None] - self._r0) / self._r_step).astype(np.int64)
        ok = (bins >= 0) & (bins < R) & (ir >= 0) & (ir < len(self._renv2))
        w = self._renv2[np.where(ok, ir, 0)] * ok
        cols = np.broadcast_to(np.arange(len(echoes))[:, None], bins.shape)
        Hs = sparse.csr_matrix((w[ok], (bins[ok], cols[ok])), shape=(R, len(echoes)))
        iu = np.rint((self.u_c[None, :] - np.sin(echoes.theta)[:, None] + 2.0) / self._u_step).astype(np.int64)
        return np.asarray(Hs @ (self._beam2[iu] * (echoes.amp ** 2)[:, None]))

    def noise_sigma(self, energy: np.ndarray, snr_db: float) -> float:
        """Image-domain noise std for a frame: SNR below its strongest echo, never under the floor.

        The PSFs peak at 1, so the image peak is the strongest echo's amplitude at a microphone
        (for a wall, the whole specular return); matched filter and beamformer then lower the
        noise by the processing gain.
        """
        peak = float(np.sqrt(energy.max())) if energy.size else 0.0
        sigma = peak * 10 ** (-(snr_db + PROCESSING_GAIN_DB) / 20)
        return max(sigma, float(np.sqrt(self.e_full)) * 10 ** (NOISE_FLOOR_DB / 20))

    def effective_snr_db(self, energy: np.ndarray, sigma: float) -> float:
        """The SNR at the microphones that a frame really has (below the nominal one near the floor)."""
        peak = float(np.sqrt(energy.max())) if energy.size else 0.0
        return 20 * np.log10(max(peak, 1e-30) / sigma) - PROCESSING_GAIN_DB

    def noise_energy(self, sigma: float, rng: np.random.Generator) -> np.ndarray:
        """Noise energy per pixel: complex Gaussian noise of std ``sigma``, shaped like the PSF."""
        shape = self.grid.shape
        parts = rng.standard_normal((2, *shape), dtype=np.float32)
        # Matched filter and beamformer correlate the noise over one PSF: shape it in one FFT pass
        # (single precision: a noise field needs no more).
        n = sfft.ifft2(sfft.fft2(parts[0] + 1j * parts[1]) * self._noise_tf)
        e = n.real ** 2 + n.imag ** 2
        return e * (sigma ** 2 / e.mean())

    def encode(self, energy: np.ndarray) -> np.ndarray:
        db = 10 * np.log10(np.maximum(energy, 1e-30) / self.e_full)
        return np.clip((db + self.dynamic_range_db) / self.dynamic_range_db, 0, 1).astype(np.float32)

    def render(self, world: World, robot_pose: np.ndarray, rng: np.random.Generator | None,
               snr_db: float | None = None, return_snr: bool = False):
        """The energyscape seen from ``robot_pose``; no noise when ``rng`` is None.

        With ``return_snr`` also returns the frame's effective SNR at the microphones (dB).
        """
        ech = visible_echoes(world, sensor_pose(robot_pose), self.grid.range_max_m + 0.1)
        e = self.energy(ech)
        eff = float("inf")
        if rng is not None:
            sigma = self.noise_sigma(e, self.snr_db if snr_db is None else snr_db)
            eff = self.effective_snr_db(e, sigma)
            e = e + self.noise_energy(sigma, rng)
        img = self.encode(e)
        return (img, eff) if return_snr else img
