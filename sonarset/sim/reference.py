"""Slow signal-level reference of the sonar, used to validate the fast image-domain model.

For each visible reflector it synthesises the 25->50 kHz sweep at each of the 32 microphones with
the true two-way delay (emitter at the array centre; far-field arrival across the array), then
does what eRTIS processing does: matched filter, beamforming towards every azimuth of the grid,
envelope, envelope low-pass, and sampling at the grid's range bins. Two beamformers, as in the
Cosys-Lab toolbox's ``calculateDMASCF``: delay-and-sum (in the frequency domain, as an analytic
signal), and DMAS3 with a coherence factor (in the time domain, on the steered channel signals).
Nothing here shares code with the fast model's PSF tables except the sweep definition and the
microphone positions; the post-processing of the envelope image (``energyscape.postprocess``) is
an image operation that both use. The beamforming is the exact path (``sensor.exact``), shared with
``sonarset import-raw``; ``microphone_signals`` renders the same echoes as time-domain recordings.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import fft as sfft

from sonarset.format.attrs import SensorGrid
from sonarset.sensor.ertis import C_SOUND, F_HI, F_LO, SWEEP_S, microphone_y, sweep
from sonarset.sensor.exact import band_bins, band_envelope, check_detector, range_samples, steering, sweep_norm
from sonarset.sim.sonar import Echoes

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
    The beamforming is the exact path (``sensor.exact``), which ``sonarset import-raw`` checks itself against.
    """
    detector = check_detector(beamformer, None)
    y = microphone_y()
    s = sweep(fs)
    n_fft = sfft.next_fast_len(2 * _n_signal(grid, fs))
    band, f = band_bins(n_fft, fs, (15e3, 60e3))  # the sweep has no energy elsewhere
    S = sfft.rfft(s, n_fft)[band]
    steer = steering(f, y[None, :] * np.sin(grid.azimuth_centres())[:, None])  # (F, A, M)
    norm = sweep_norm(s, fs, detector)
    t_idx = range_samples(grid, fs, n_fft)
    X = _echo_spectra(echoes, f, y, 1 if coherent else max(1, realizations), coherent, seed)
    Y = X * (np.abs(S) ** 2)[None, None, :]  # sweep spectrum times its matched filter
    env = band_envelope(Y, steer, band, n_fft, fs, t_idx, beamformer)
    amp = np.maximum(env[:, :, t_idx], 0) / norm  # (K, A, R)
    return np.sqrt((amp ** 2).mean(0).T)


def microphone_signals(echoes: Echoes, grid: SensorGrid, *, fs: float = FS_REF, coherent: bool = False,
                       seed: int = 0, realizations: int = 1, snr_db: float | None = None) -> np.ndarray:
    """The 32 eRTIS microphone signals (K, 32, n) float32 of ``echoes``, one measurement per
    realization: each echo is the emitted sweep (``ertis.sweep``) with amplitude ``echoes.amp``,
    delayed by its two-way travel time (sample 0 is the start of the emission), long enough for the
    grid's farthest range. Echo phases as ``reference_amplitude`` draws them (``seed``).

    ``snr_db``: white Gaussian noise at each microphone, this many dB below the strongest echo's
    amplitude (the simulator's SNR definition, docs/physics.md, "Noise").
    """
    y = microphone_y()
    s = sweep(fs)
    n_sig = _n_signal(grid, fs)
    n_fft = sfft.next_fast_len(n_sig, real=True)  # every echo ends inside n_sig: nothing wraps
    band, f = band_bins(n_fft, fs, (15e3, 60e3))
    X = _echo_spectra(echoes, f, y, max(1, realizations), coherent, seed)
    full = np.zeros((*X.shape[:2], n_fft // 2 + 1), complex)
    full[:, :, band] = X * sfft.rfft(s, n_fft)[band]
    out = sfft.irfft(full, n_fft, axis=2)[:, :, :n_sig].astype(np.float32)
    if snr_db is not None and len(echoes):
        sigma = float(echoes.amp.max()) * 10 ** (-snr_db / 20)
        rng = np.random.default_rng([seed, 1])
        out += rng.normal(0, sigma, out.shape).astype(np.float32)
    return out


def _n_signal(grid: SensorGrid, fs: float) -> int:
    return int(np.ceil((2 * grid.range_max_m / C_SOUND + 0.004) * fs)) + len(sweep(fs))


def _echo_spectra(echoes: Echoes, f: np.ndarray, y: np.ndarray, n_real: int, coherent: bool, seed: int) -> np.ndarray:
    """(K, M, F) spectra of the echoes' delays at each microphone, weighted by amplitude and phase."""
    # Each echo reaches mic m after r (out) + r - y_m sin(theta) (back, far field across the array).
    tau = (2 * echoes.r[:, None] - y[None, :] * np.sin(echoes.theta)[:, None]) / C_SOUND  # (N, M)
    rng = np.random.default_rng(seed)
    phase = np.zeros((1, len(echoes))) if coherent else rng.uniform(0, 2 * np.pi, (n_real, len(echoes)))
    weights = echoes.amp[None, :] * np.exp(1j * phase)  # (K, N): one row per realization
    X = np.empty((len(weights), len(y), len(f)), complex)
    for m in range(len(y)):  # per microphone, to bound memory: (N, F) phase terms at a time
        X[:, m] = weights @ np.exp(-2j * np.pi * tau[:, m, None] * f[None, :])
    return X


def write_raw_recording(run, out_dir, *, frames: slice | None = None, fs: float = FS_REF, seed: int = 0,
                        snr_db: float | None = None, name: str | None = None) -> Path:
    """Render the scene of a simulated run (its world and poses) as a raw recording that
    ``sonarset import-raw`` reads: a directory of ``.npy`` files (``signals`` written frame by frame
    into a memory map, ``velocity``, ``time``, ``pose``) with its ``recording.json``.

    Each frame is one realization of ``microphone_signals`` (random echo phases seeded by ``seed``
    and the frame index; microphone noise at ``snr_db`` when given).
    """
    import json

    from sonarset.sim.robot import sensor_pose
    from sonarset.sim.sonar import visible_echoes
    from sonarset.sim.families import load_world

    src = run.attrs.source
    if src.get("kind") != "simulator":
        raise ValueError(f"run {run.name!r} was not simulated: no world to render")
    grid = run.store.grid
    world = load_world(src["world"], int(src["world_seed"]))
    sl = frames or slice(None)
    pose = run["pose"][sl]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n = _n_signal(grid, fs)
    sig = np.lib.format.open_memmap(out / "signals.npy", "w+", np.float32, (len(pose), len(microphone_y()), n))
    start = sl.start or 0
    for k, p in enumerate(pose):
        echoes = visible_echoes(world, sensor_pose(p), grid.range_max_m + 0.1)
        sig[k] = microphone_signals(echoes, grid, fs=fs, seed=seed * 1_000_003 + start + k, snr_db=snr_db)[0]
    sig.flush()
    del sig
    np.save(out / "velocity.npy", run["velocity"][sl])
    np.save(out / "time.npy", run["time"][sl])
    np.save(out / "pose.npy", pose)
    g = grid
    meta = {"name": name or run.name, "split": run.split, "sample_rate_hz": fs, "speed_of_sound_m_s": C_SOUND,
            "sweep": {"f_start_hz": F_LO, "f_end_hz": F_HI, "duration_s": SWEEP_S, "window": "hann"},
            "microphones": "ertis32",
            "grid": {"range_min": g.range_min_m, "range_max": g.range_max_m, "n_range": g.n_range,
                     "azimuth_min": g.azimuth_min_rad, "azimuth_max": g.azimuth_max_rad, "n_azimuth": g.n_azimuth},
            "source": {"rendered_from": f"{run.store.location}/{run.name}", "seed": seed,
                       "snr_db": snr_db}}
    if run.store.rig is not None:
        meta["rig"] = run.store.rig.model_dump(mode="json")
    (out / "recording.json").write_text(json.dumps(meta, indent=2))
    return out
