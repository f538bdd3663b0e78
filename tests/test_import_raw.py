"""import-raw: microphone signals -> energyscapes, as the simulator makes them.

The round trip renders a simulated run's scene to microphone signals with the signal-level
reference, imports them and compares with the simulator's own images of the run; malformed inputs
each get one-line errors and leave nothing behind; a killed import leaves no complete run.
"""

import json
import math
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from sonarset import open_store
from sonarset.cli.app import app
from sonarset.errors import InputValidationError, SonarSetError
from sonarset.ingest.raw import import_raw, load_raw
from sonarset.ingest.files import RawSource
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.sensor.beamform import SignalBeamformer
from sonarset.sensor.ertis import read_layout_csv, sweep
from sonarset.sensor.exact import steering_projection
from sonarset.sim.reference import microphone_signals, reference_amplitude, write_raw_recording
from sonarset.sim.sonar import Echoes, SonarModel
from sonarset.store.validate import validate_store

SMALL = SensorGrid(range_min_m=0.5, range_max_m=1.5, n_range=24, azimuth_min_rad=-1.2, azimuth_max_rad=1.2,
                   n_azimuth=12)
FS = 200e3


def _cc(a, b):
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _signals(T, grid=SMALL, seed=0):
    """T measurements of a few point echoes that move between measurements: (T, 32, n) float32."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(T):
        r = rng.uniform(grid.range_min_m + 0.1, grid.range_max_m - 0.1, 3)
        echoes = Echoes(r, rng.uniform(-1, 1, 3), rng.uniform(0.05, 0.3, 3))
        out.append(microphone_signals(echoes, grid, coherent=True)[0])
    return np.stack(out)


def _sidecar(grid=SMALL, **over):
    doc = {"sample_rate_hz": FS, "speed_of_sound_m_s": 343.0, "microphones": "ertis32", "split": "test",
           "sweep": {"f_start_hz": 25e3, "f_end_hz": 50e3, "duration_s": 0.0025, "window": "hann"},
           "grid": {"range_min": grid.range_min_m, "range_max": grid.range_max_m, "n_range": grid.n_range,
                    "azimuth_min": grid.azimuth_min_rad, "azimuth_max": grid.azimuth_max_rad,
                    "n_azimuth": grid.n_azimuth}}
    doc.update(over)
    return {k: v for k, v in doc.items() if v is not None}


def _write(tmp_path, name="rec", T=4, signals=None, meta=None, **arrays):
    sig = _signals(T) if signals is None else signals
    T = len(sig)
    base = {"signals": sig, "velocity": np.c_[np.full(T, 0.1), np.zeros(T)].astype(np.float32),
            "time": np.arange(T) * 0.2}
    base.update(arrays)
    src = tmp_path / f"{name}.npz"
    np.savez(src, **{k: v for k, v in base.items() if v is not None})
    src.with_suffix(".json").write_text(json.dumps(_sidecar() if meta is None else meta))
    return src


@pytest.fixture(scope="module")
def signals4():
    return _signals(4)


# ---- the beamformer -----------------------------------------------------------------------------

@pytest.mark.parametrize("beamformer", ["das", "dmas3-cf"])
def test_fast_path_matches_the_exact_one_and_the_reference(beamformer, signals4):
    """The fast path (rounded delays on a 1.6 MHz grid, one compiled loop) against frequency-domain
    steering on the same signals, and that against the signal-level reference's own images."""
    sig = signals4[0]
    sb = SignalBeamformer(SMALL, read_layout_csv(), sweep(FS), FS, sig.shape[1], beamformer)
    fast, exact = sb.amplitude(sig), sb.exact_amplitude(sig)
    assert fast.shape == SMALL.shape and fast.dtype == np.float32
    assert _cc(fast, exact) > 0.999
    assert abs(fast.max() / exact.max() - 1) < 0.015  # the same scale: a lone echo of amplitude a peaks at a
    # a lone broadside echo of amplitude 0.2 at a bin centre reads 0.2 x the bin's mean of the PSF
    echo = Echoes(np.array([SMALL.range_centres()[10]]), np.array([SMALL.azimuth_centres()[6]]), np.array([0.2]))
    one = sb.amplitude(microphone_signals(echo, SMALL, coherent=True)[0])
    model = SonarModel(SMALL, processing=Processing.raw() if beamformer == "das" else
                       Processing.ertis().model_copy(update={"smoothing_range_m": 0.0, "smoothing_azimuth_deg": 0.0}))
    sim = model.amplitude(echo, 1)[0][0]
    assert np.unravel_index(one.argmax(), one.shape) == (10, 6)
    assert one.max() == pytest.approx(sim.max(), rel=0.05)


def test_reference_bit_identical_after_the_refactor():
    """reference_amplitude runs beamform's exact path; these numbers were taken before that refactor
    (DAS) and after rectification replaced |hilbert| as DMAS3-CF's detector (issue 24)."""
    grid = SensorGrid(range_min_m=0.5, range_max_m=3.0, n_range=40, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=20)
    e = Echoes(np.array([1.0, 2.2, 2.9]), np.radians([0.0, 35.0, -55.0]), np.array([0.3, 0.15, 0.1]))
    assert reference_amplitude(e, grid, "das", coherent=True).sum() == pytest.approx(0.5979414793429497, rel=1e-12)
    assert reference_amplitude(e, grid, "dmas3-cf", realizations=3, seed=4).sum() == pytest.approx(
        0.04566878195254939, rel=1e-12)


# ---- the envelope: no streak along a target's azimuth ------------------------------------------

def _point_target(grid, fs, emitted, r, azimuth, n):
    """Signals (32, n) of one far-field point target of unit amplitude, delays exact (frequency domain)."""
    from scipy import fft as sfft

    proj = steering_projection(read_layout_csv(), np.array([azimuth]))[0]
    N = sfft.next_fast_len(n + len(emitted), real=True)
    f = sfft.rfftfreq(N, 1 / fs)
    t0 = (2 * r - proj) / 343.0
    return sfft.irfft(sfft.rfft(emitted, N)[None] * np.exp(-2j * np.pi * f[None] * t0[:, None]), N)[:, :n]


@pytest.mark.parametrize("fs,f_start,f_end", [(450e3, 80e3, 20e3), (450e3, 25e3, 50e3), (200e3, 25e3, 50e3)])
def test_isolated_point_target_column_stays_at_the_floor(fs, f_start, f_end):
    """After the ertis post-processing, the column through an isolated target at +30 deg stays black
    away from its range, for both beamformers. At a 450 kHz recording DMAS3's odd harmonics fold onto
    0 Hz at the 225 kHz output rate; |hilbert| of that baseband spreads it over all ranges (the
    streak of issue 24), which the rectifier (the toolbox's order, the default) and the square law keep at the echo's range."""
    from sonarset.sim.sonar import SonarModel

    grid = SensorGrid(range_min_m=0.5, range_max_m=3.5, n_range=120, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=60)
    emitted = sweep(fs, f_start, f_end, 0.0025)
    n = int((2 * grid.range_max_m / 343 + 0.004) * fs)
    sig = _point_target(grid, fs, emitted, 1.5, math.radians(30), n).astype(np.float32)
    column = np.argmin(np.abs(grid.azimuth_centres() - math.radians(30)))
    away = np.abs(grid.range_centres() - 1.5) > 0.3

    def column_away(beamformer, detector=None):
        sb = SignalBeamformer(grid, read_layout_csv(), emitted, fs, n, beamformer, detector=detector)
        amp = sb.amplitude(sig)
        model = SonarModel(grid, processing=Processing.ertis().model_copy(update={"beamformer": beamformer}))
        px = model.pixels(amp / amp.max())  # the target at full scale: the streak at its strongest
        assert px.max() > 0.5  # the target itself, bright (smoothing and the azimuth mean lower it)
        return float(px[away, column].max())

    for beamformer in ("das", "dmas3-cf"):
        assert column_away(beamformer) < 0.01, beamformer  # under 0.6 dB above the -60 dB floor
    assert column_away("dmas3-cf", "square") < 0.01  # the square law does the same
    if fs == 450e3:
        assert column_away("dmas3-cf", "analytic") > 0.05  # the streak this test is there to catch


def test_the_sidecars_ertis_sweep_is_the_simulators_sample_for_sample(tmp_path, signals4):
    """One sweep for the simulator and the importer: the eRTIS parameters in a sidecar give the very
    samples the simulator emits; other parameters and an unwindowed chirp differ from it."""
    rec, _ = load_raw(_write(tmp_path, signals=signals4), scan=False)
    assert rec.sweep.tobytes() == sweep(FS).tobytes()
    other = _sidecar(sweep={"f_start_hz": 25e3, "f_end_hz": 50e3, "duration_s": 0.0025, "window": "none"})
    flat, _ = load_raw(_write(tmp_path, "flat", signals=signals4, meta=other), scan=False)
    assert len(flat.sweep) == len(rec.sweep) and flat.sweep[0] != 0 and rec.sweep[0] == 0
    assert np.abs(sweep(FS, 25e3, 50e3, 0.0025, "none") * np.hanning(len(rec.sweep)) - rec.sweep).max() < 1e-12


def test_detector_choices_are_checked():
    with pytest.raises(ValueError, match="detector must be one of"):
        SignalBeamformer(SMALL, read_layout_csv(), sweep(FS), FS, 4000, "dmas3-cf", detector="peak")
    with pytest.raises(ValueError, match="analytic"):
        SignalBeamformer(SMALL, read_layout_csv(), sweep(FS), FS, 4000, "das", detector="square")


# ---- round trip: a simulated run's scene, rendered to microphone signals ------------------------

@pytest.fixture(scope="module")
def round_trip(tmp_path_factory):
    """A short simulated test run on the default grid (the simulator's ertis images), its scene
    rendered to raw signals by the reference (one realization of the echo phases per frame) and
    imported with the CLI."""
    from sonarset.sim import generate

    tmp = tmp_path_factory.mktemp("rt")
    generate(tmp / "sim.zarr", runs=0, test_runs=1, minutes=0.02, seed=3, workers=1, snr_db=40.0)
    run = open_store(tmp / "sim.zarr").run("test_000")
    raw = write_raw_recording(run, tmp / "raw", seed=1)
    r = CliRunner().invoke(app, ["import-raw", str(raw), str(tmp / "imp.zarr")])
    assert r.exit_code == 0, r.output
    return run, open_store(tmp / "imp.zarr"), tmp


def test_round_trip_matches_the_simulators_images(round_trip, capsys):
    sim, imp, _ = round_trip
    run = imp.run("test_000")
    assert imp.processing == Processing.ertis() and imp.grid == sim.store.grid and imp.rig == sim.store.rig
    assert run.split == "test" and run.attrs.source["kind"] == "import-raw"
    np.testing.assert_array_equal(run.velocity[:], sim.velocity[:])
    np.testing.assert_array_equal(run["pose"][:], sim["pose"][:])
    a, b = sim.images[:].astype(np.float32), run.images[:].astype(np.float32)
    ccs = [_cc(x, y) for x, y in zip(a, b)]
    with capsys.disabled():
        print(f"\nimport-raw round trip (ertis, default grid, {len(ccs)} frames): 2D correlation with the "
              f"simulator's images per frame {np.round(ccs, 3).tolist()}, mean {np.mean(ccs):.3f}")
    # one realization of the echo phases per frame: speckle that the simulator's expected energies lack
    assert np.mean(ccs) >= 0.9 and min(ccs) >= 0.85, ccs
    assert validate_store(imp.location) == []


@pytest.mark.parametrize("profile", ["ertis", "raw"])
def test_signal_path_matches_the_fast_model_like_for_like(round_trip, profile, capsys):
    """The round trip above compares a noise-free recording of one realization of the echo phases
    with images that carry the simulator's noise floor (-55 dB re full scale) and no speckle. Like
    for like: the run's scenes without noise, 4 realizations a frame through import-raw's
    beamformer, their energy averaged, against the fast model's noise-free images."""
    from sonarset.sim.families import load_world
    from sonarset.sim.robot import sensor_pose
    from sonarset.sim.sonar import visible_echoes

    sim, _, _ = round_trip
    grid, src = sim.store.grid, sim.attrs.source
    world = load_world(src["world"], int(src["world_seed"]))
    proc = Processing.named(profile)
    model = SonarModel(grid, processing=proc)
    pixels = (lambda a: model.pixels(a)) if proc.post_processed else (lambda a: model.encode(a * a))
    sb = None
    ccs = []
    for k, pose in enumerate(sim["pose"][:]):
        echoes = visible_echoes(world, sensor_pose(pose), grid.range_max_m + 0.1)
        sig = microphone_signals(echoes, grid, seed=k, realizations=4)
        if sb is None:
            sb = SignalBeamformer(grid, read_layout_csv(), sweep(FS), FS, sig.shape[2], proc.beamformer)
        amp = np.sqrt(np.mean([sb.amplitude(x) ** 2 for x in sig], axis=0)).astype(np.float32)
        ccs.append(_cc(pixels(amp), pixels(model.amplitude(echoes, 1)[0][0])))
    with capsys.disabled():
        print(f"\nsignal path vs fast model, noise-free, 4 realizations ({profile}): per frame "
              f"{np.round(ccs, 3).tolist()}, mean {np.mean(ccs):.3f}")
    assert np.mean(ccs) >= 0.97 and min(ccs) >= 0.95, ccs


def test_pretrained_echopt_evaluates_on_the_imported_run(round_trip):
    pytest.importorskip("torch")
    _, imp, tmp = round_trip
    r = CliRunner().invoke(app, ["eval", imp.location, "--models", "flow,echopt:pretrained", "--horizons", "1",
                                 "--samples", "3", "--out", str(tmp / "ev"), "--no-figures"])
    assert r.exit_code == 0, r.output
    metrics = json.loads((tmp / "ev" / "metrics.json").read_text())
    assert "echopt" in json.dumps(metrics) and "trained on" not in r.output  # same images: no mismatch note


# ---- streaming, processing options, appending ------------------------------------------------------

def test_npz_and_npy_directory_stream_the_same_blocks(tmp_path, signals4):
    src = _write(tmp_path, signals=signals4)
    d = tmp_path / "dir"
    d.mkdir()
    np.save(d / "signals.npy", signals4)
    for reader in (RawSource(src), RawSource(d)):
        got = list(reader.blocks("signals", 3, start=1))
        assert [i for i, _ in got] == [1] and got[0][1].shape == (3, *signals4.shape[1:])
        np.testing.assert_array_equal(got[0][1], signals4[1:])


def test_memory_stays_bounded_whatever_the_length(tmp_path):
    """Peak numpy allocation (tracemalloc) of importing 16 and 96 measurements: the same, and far
    below the longer recording's size."""
    import tracemalloc

    rng = np.random.default_rng(0)
    peaks = {}
    for T in (16, 96):
        sig = rng.normal(0, 0.01, (T, 32, 3100)).astype(np.float32)  # 96: 38 MB of noise
        size = sig.nbytes
        src = _write(tmp_path, f"r{T}", signals=sig)
        del sig
        tracemalloc.start()
        try:
            run = import_raw(src, tmp_path / f"o{T}.zarr", processing="raw", workers=1)
            peaks[T] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert run.n_frames == T
    assert peaks[96] < 1.15 * peaks[16] + 1e6 and peaks[96] < 0.75 * size, peaks


def test_processing_and_beamformer_are_recorded_and_appending_must_match(tmp_path, signals4):
    src = _write(tmp_path, signals=signals4)
    import_raw(src, tmp_path / "a.zarr", processing="ertis", beamformer="das", name="one")
    s = open_store(tmp_path / "a.zarr")
    assert s.processing.beamformer == "das" and s.processing.profile == "custom" and s.processing.post_processed
    import_raw(src, tmp_path / "a.zarr", processing="ertis", beamformer="das", name="two")  # same images: appended
    assert open_store(tmp_path / "a.zarr").runs() == ["one", "two"]
    with pytest.raises(SonarSetError, match="store images are custom"):
        import_raw(src, tmp_path / "a.zarr", name="three")  # ertis = dmas3-cf: other images
    with pytest.raises(SonarSetError, match="run 'two' already exists"):
        import_raw(src, tmp_path / "a.zarr", processing="ertis", beamformer="das", name="two")
    with pytest.raises(SonarSetError, match="unknown processing profile 'fancy'"):
        import_raw(src, tmp_path / "b.zarr", processing="fancy")
    raw = import_raw(src, tmp_path / "r.zarr", processing="raw", name="r")
    assert raw.store.processing == Processing.raw() and raw.images.dtype == np.float16
    # a recording in other units (x1000) with amplitude_scale 1000 makes the same images
    src2 = _write(tmp_path, "scaled", signals=signals4 * 1000, meta=_sidecar(amplitude_scale=1000.0))
    scaled = import_raw(src2, tmp_path / "r.zarr", processing="raw")
    np.testing.assert_allclose(scaled.images[:].astype(np.float32), raw.images[:].astype(np.float32), atol=2e-3)


def test_velocity_alignment_next_drops_the_first_measurement(tmp_path, signals4):
    src = _write(tmp_path, signals=signals4, meta=_sidecar(velocity_alignment="next"),
                 velocity=np.c_[np.arange(4) * 0.01, np.zeros(4)].astype(np.float32))
    run = import_raw(src, tmp_path / "o.zarr", processing="raw")
    full = import_raw(_write(tmp_path, "b", signals=signals4), tmp_path / "p.zarr", processing="raw")
    assert run.n_frames == 3
    np.testing.assert_allclose(run.velocity[:, 0], [0.0, 0.01, 0.02])
    np.testing.assert_array_equal(run.images[:], full.images[1:])


# ---- malformed inputs: one line each, nothing written -------------------------------------------------

def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _corrupt_member(path: Path) -> None:
    """Flip bytes inside the stored signals: the archive opens, its CRC fails when streamed."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("signals.npy")
    data = bytearray(path.read_bytes())
    at = info.header_offset + 30 + len(info.filename) + 4096
    data[at:at + 64] = bytes(64)
    path.write_bytes(bytes(data))


MALFORMED = {
    "wrong channel count": (dict(signals=lambda s: s[:, :16]), None, None,
                            "signals: 16 channels but the microphone layout has 32 microphones"),
    "sample rate missing": (dict(), dict(sample_rate_hz=None), None, "rec.json: sample_rate_hz: Field required"),
    "layout mismatch (CSV)": (dict(), dict(microphones="mics.csv"), "layout",
                              "mics.csv: not a microphone layout CSV (header x,y lacks column(s) z)"),
    "layout in millimetres": (dict(), dict(microphones=[[0, -38.4, 15.1], [0, -23.2, 10.1], [0, 5, 1]]), None,
                              "metadata.microphones: microphones up to 38.4 from the emitter; positions must be metres"),
    "NaN in a signal": (dict(signals=lambda s: _nan(s)), None, None,
                        "signals: NaN or infinite values in measurement 2, channel 5"),
    "truncated file": (dict(), None, "truncate", "not a readable .npz file"),
    "corrupt archive member": (dict(), None, "corrupt", "signals: unreadable"),
    "dead microphone": (dict(signals=lambda s: _dead(s)), None, None,
                        "signals: channel(s) 7 are zero in every measurement"),
    "velocity rows": (dict(velocity=np.zeros((3, 2), np.float32)), None, None,
                      "velocity: 3 rows but signals has 4 measurements"),
    "time not increasing": (dict(time=np.array([0, 0.2, 0.2, 0.6])), None, None,
                            "time: not strictly increasing (first at measurement 2)"),
    "signals too short for the grid": (dict(signals=lambda s: s[..., :1200]), None, None,
                                       "signals: 1200 samples at 200000 Hz hold complete echoes out to 0.60 m"),
    "sample rate below the sweep's Nyquist": (dict(), dict(sample_rate_hz=96000.0), None,
                                              "metadata.sample_rate_hz: 96000 Hz cannot carry the sweep's 50000 Hz"),
    "no sweep": (dict(), dict(sweep=None), None, "no emitted sweep"),
    "speed of sound in km/s": (dict(), dict(speed_of_sound_m_s=0.343), None,
                               "rec.json: speed_of_sound_m_s: Input should be greater than or equal to 300"),
    "signals 2-D": (dict(signals=lambda s: s[:, 0]), None, None, "signals: expected 3-D (measurement, channel, sample)"),
    "complex signals": (dict(signals=lambda s: s.astype(np.complex64)), None, None,
                        "signals: dtype complex64 is not a real number type"),
    "unknown array": (dict(images=np.zeros((4, 2, 2))), None, None, "unknown array 'images'"),
    "speed in cm/s declared m/s": (dict(velocity=np.c_[np.full(4, 25.0), np.zeros(4)]), None, None,
                                   "velocity: linear speed up to 25 m/s exceeds 10 m/s"),
}


def _nan(s):
    s = s.copy()
    s[2, 5, 100] = np.nan
    return s


def _dead(s):
    s = s.copy()
    s[:, 7] = 0
    return s


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_raw_input_one_line_error_nothing_written(tmp_path, case, signals4):
    arrays, meta_over, action, expect = MALFORMED[case]
    arrays = {k: (v(signals4) if callable(v) else v) for k, v in arrays.items()}
    sig = arrays.pop("signals", signals4)
    meta = _sidecar(**(meta_over or {}))
    if meta_over:
        meta = {k: v for k, v in {**_sidecar(), **meta_over}.items() if v is not None}
    src = _write(tmp_path, signals=sig, meta=meta, **arrays)
    if action == "layout":
        (tmp_path / "mics.csv").write_text("x,y\n0,0.01\n0,0.02\n")
    elif action == "truncate":
        _truncate(src)
    elif action == "corrupt":
        _corrupt_member(src)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(InputValidationError) as info:
        import_raw(src, tmp_path / "out.zarr")
    assert any(expect in p for p in info.value.problems), info.value.problems
    assert all("\n" not in p for p in info.value.problems) and str(src) in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no store, no temporary directory
    # the CLI: one line per problem, naming the file, exit 1, no traceback
    r = CliRunner().invoke(app, ["import-raw", str(src), str(tmp_path / "out.zarr")])
    assert r.exit_code == 1 and "Traceback" not in r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert lines and all(ln.startswith("error: ") and src.name in ln for ln in lines), r.output
    assert not (tmp_path / "out.zarr").exists()


def test_missing_sidecar_and_existing_store_left_untouched(tmp_path, signals4):
    src = _write(tmp_path, signals=signals4)
    src.with_suffix(".json").unlink()
    with pytest.raises(InputValidationError, match="rec.json: metadata file not found"):
        load_raw(src)
    good = _write(tmp_path, "good", signals=signals4)
    import_raw(good, tmp_path / "s.zarr", processing="raw")
    bad = _write(tmp_path, "bad", signals=_nan(signals4))
    with pytest.raises(InputValidationError):
        import_raw(bad, tmp_path / "s.zarr", processing="raw")
    assert open_store(tmp_path / "s.zarr").runs(include_incomplete=True) == ["good"]
    # overwrite swaps the new run in only once it is complete
    again = import_raw(good, tmp_path / "s.zarr", processing="raw", overwrite=True)
    assert again.n_frames == 4 and open_store(tmp_path / "s.zarr").runs() == ["good"]
    with pytest.raises(SonarSetError, match="invalid run name 'a b': a run name is 1-128 letters"):
        import_raw(good, tmp_path / "s.zarr", name="a b")


# ---- a killed import ------------------------------------------------------------------------------

KILLER = """
import os, signal, sys
from sonarset.ingest import raw as rawimport
real = rawimport.RawProcessor.images
calls = []
def images(self, block):
    calls.append(1)
    if len(calls) == 2:  # a block is beamformed, the run group exists: die without cleaning up
        os.kill(os.getpid(), signal.SIGKILL)
    return real(self, block)
rawimport.RawProcessor.images = images
rawimport.import_raw(sys.argv[1], sys.argv[2], processing="raw", workers=1, block=8, name="killed")
"""


@pytest.mark.parametrize("into", ["new store", "existing store"])
def test_killed_import_leaves_no_complete_looking_run(tmp_path, into):
    rng = np.random.default_rng(1)
    src = _write(tmp_path, signals=rng.normal(0, 0.01, (24, 32, 3100)).astype(np.float32))
    out = tmp_path / "out.zarr"
    if into == "existing store":
        import_raw(_write(tmp_path, "first", T=2), out, processing="raw")
    p = subprocess.run([sys.executable, "-c", KILLER, str(src), str(out)], capture_output=True, text=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert p.returncode == -9, p.stderr
    if into == "new store":
        assert not out.exists()  # only a hidden directory beside it, which the next import removes
    else:
        s = open_store(out)
        assert s.runs(include_incomplete=True) == ["first"]  # the run was being built beside the store
        assert validate_store(out) == []
    import_raw(src, out, processing="raw", name="killed")
    assert open_store(out).run("killed").n_frames == 24
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.zarr")] == []  # the dead one's aside


def test_a_450_khz_int16_directory_recording_makes_the_same_images(tmp_path, signals4):
    """eRTIS-like 450 kHz ADC counts in a .npy directory, with the sweep as an array and the layout
    as a CSV: the same images as the 200 kHz float recording of the same echoes."""
    rng = np.random.default_rng(0)
    fs = 450e3
    sig = []
    for _ in range(2):
        r = rng.uniform(0.6, 1.4, 3)
        echoes = Echoes(r, rng.uniform(-1, 1, 3), rng.uniform(0.05, 0.3, 3))
        sig.append((microphone_signals(echoes, SMALL, coherent=True, fs=FS)[0],
                    microphone_signals(echoes, SMALL, coherent=True, fs=fs)[0]))
    ref = import_raw(_write(tmp_path, "f200", signals=np.stack([a for a, _ in sig])), tmp_path / "a.zarr",
                     processing="raw")
    d = tmp_path / "adc"
    d.mkdir()
    np.save(d / "signals.npy", np.round(np.stack([b for _, b in sig]) * 20000).astype(np.int16))
    np.save(d / "velocity.npy", np.zeros((2, 2)))
    np.save(d / "time.npy", np.array([0.0, 0.2]))
    np.save(d / "sweep.npy", sweep(fs))
    (d / "mics.csv").write_text("# eRTIS, metres\nx,y,z\n" + "\n".join(f"{x},{y},{z}" for x, y, z in read_layout_csv()))
    (d / "recording.json").write_text(json.dumps(_sidecar(sample_rate_hz=fs, sweep=None, microphones="mics.csv",
                                                          amplitude_scale=20000.0)))
    adc = import_raw(d, tmp_path / "a.zarr", processing="raw", name="adc")
    a, b = ref.images[:].astype(np.float32), adc.images[:].astype(np.float32)
    assert _cc(a, b) > 0.99 and np.abs(a - b).max() < 0.03
