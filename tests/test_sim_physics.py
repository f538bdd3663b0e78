"""Physics of the simulator against docs/physics.md and the acoustic-flow geometry."""

import math

import numpy as np
import pytest

from sonarset.format.attrs import Processing, SensorGrid
from sonarset.sim.robot import SENSOR_OFFSET, apply_slip, integrate, sensor_pose
from sonarset.sim.sonar import ABSORPTION_DB_PER_M, Echoes, SonarModel, visible_echoes
from sonarset.sim.world import CircleSpec, SpawnBox, WallSpec, World, WorldSpec

GRID = SensorGrid.default()


def world(walls=(), circles=()):
    return World.from_spec(WorldSpec(walls=list(walls), circles=list(circles), spawn=[SpawnBox(x=(0, 1), y=(0, 1))]))


def peak(img: np.ndarray, grid: SensorGrid) -> tuple[float, float]:
    i, j = np.unravel_index(np.argmax(img), img.shape)
    return grid.range_centres()[i], grid.azimuth_centres()[j]


def test_static_reflector_follows_its_flow_line_under_translation():
    model = SonarModel(GRID)
    w = world(circles=[CircleSpec(centre=(3.5, 1.2), radius=0.03)])
    pose = np.array([0.0, 0.0, 0.0])
    r0, th0 = peak(model.render(w, pose, None), GRID)
    y0 = r0 * math.sin(th0)
    for _ in range(8):
        pose = integrate(pose, 0.3, 0.0, 0.2)
        r, th = peak(model.render(w, pose, None), GRID)
        # r sin(theta) = const: the azimuth expected from the measured range, within one bin
        th_flow = math.asin(y0 / r)
        assert abs(th - th_flow) <= GRID.azimuth_step + 1e-9, (r, math.degrees(th), math.degrees(th_flow))
    assert r < r0 - 0.4  # it did move closer


def test_pure_rotation_shifts_azimuth_by_omega_dt():
    model = SonarModel(GRID)
    w = world(circles=[CircleSpec(centre=(4.0, 0.5), radius=0.05)])
    pose = np.array([0.0, 0.0, 0.0])
    _, th0 = peak(model.render(w, pose, None), GRID)
    for omega in (0.5, -1.0):
        p = integrate(pose, 0.0, omega, 0.2)
        assert np.allclose(p[:2], pose[:2])  # in place
        _, th = peak(model.render(w, p, None), GRID)
        # the sensor sits SENSOR_OFFSET ahead of the rotation axis, so allow one bin
        assert abs((th0 - th) - omega * 0.2) <= GRID.azimuth_step, (math.degrees(th0 - th), omega * 0.2)


def _fine(centre_deg: float) -> SensorGrid:
    c = math.radians(centre_deg)
    return SensorGrid(range_min_m=1.9, range_max_m=2.1, n_range=200, azimuth_min_rad=c - 0.4,
                      azimuth_max_rad=c + 0.4, n_azimuth=800)


def _width(profile: np.ndarray, axis_values: np.ndarray, level: float) -> float:
    above = np.flatnonzero(profile >= level * profile.max())
    return float(axis_values[above[-1]] - axis_values[above[0]])


@pytest.mark.parametrize("az_deg,expected_deg", [(0.0, 5.0), (60.0, 10.0)])
def test_point_spread_function_widths_match_design(az_deg, expected_deg):
    grid = _fine(az_deg)
    e = SonarModel(grid).energy(Echoes(np.array([2.0]), np.array([math.radians(az_deg)]), np.array([1.0])))
    i, j = np.unravel_index(np.argmax(e), e.shape)
    fwhm_range = _width(np.sqrt(e[:, j]), grid.range_centres(), 0.5)  # amplitude envelope FWHM
    width_az = math.degrees(_width(e[i], grid.azimuth_centres(), 0.5))  # -3 dB of energy
    assert fwhm_range == pytest.approx(0.02, rel=0.2)
    assert width_az == pytest.approx(expected_deg, rel=0.2)
    # side lobes exist (a 32-element sparse array), well below the main lobe
    d = SonarModel(GRID).energy(Echoes(np.array([2.0]), np.array([math.radians(az_deg)]), np.array([1.0])))
    row = d[np.argmax(d.max(1))]
    side = row[np.abs(GRID.azimuth_centres() - math.radians(az_deg)) > math.radians(2 * expected_deg)]
    assert 1e-3 < side.max() / row.max() < 0.2


def test_echo_level_falls_with_spreading_and_absorption():
    model = SonarModel(GRID)
    levels = []
    ranges = tuple(GRID.range_centres()[[22, 67, 156]])  # on bin centres: the sampled peak is the echo
    for r in ranges:
        w = world(circles=[CircleSpec(centre=(r + SENSOR_OFFSET + 0.05, 0.0), radius=0.05)])
        levels.append(model.energy(visible_echoes(w, sensor_pose(np.zeros(3)), 5.1)).max())
    for r, e in zip(ranges[1:], levels[1:]):
        expected_db = -30 * math.log10(r / ranges[0]) - ABSORPTION_DB_PER_M * 2 * (r - ranges[0])  # pole: 1/r^1.5
        got_db = 10 * math.log10(e / levels[0])
        assert got_db == pytest.approx(expected_db, abs=0.5)


def test_wall_is_strongest_at_normal_incidence():
    # The echo model, seen through delay-and-sum. Under the coherence factor the point of normal
    # incidence is darker: its range bin holds echoes from many directions at once (tested below).
    model = SonarModel(GRID, processing=Processing.raw())
    az = GRID.azimuth_centres()
    for heading in (0.0, 0.5, -0.7):
        # the wall's normal range on a bin centre: 2 cm PSF on 2.25 cm bins otherwise adds ~1 dB ripple
        d = GRID.range_centres()[60]
        wx = d + SENSOR_OFFSET * math.cos(heading)
        w = world(walls=[WallSpec(start=(wx, -6.0), end=(wx, 6.0))])
        img = model.render(w, np.array([0.0, 0.0, heading]), None)
        arc = img.max(0)  # the wall's arc, strongest pixel per azimuth
        normal = -heading  # the normal from the sensor to the wall points along world +x
        peak_az = az[np.argmax(arc)]
        if heading == 0.0:
            assert abs(peak_az - normal) <= GRID.azimuth_step / 2 + 1e-9
        else:
            # tilted, the emitter's directivity pulls the peak from the normal towards the axis
            assert min(0.0, normal) - 1e-9 <= peak_az <= max(0.0, normal) + 1e-9
            assert abs(peak_az - normal) <= math.radians(12)
        off = np.abs(az - normal) > math.radians(40)
        assert 60 * (arc.max() - arc[off & (np.abs(az) < math.radians(80))].max()) > 10  # dB below
        r_arc = GRID.range_centres()[np.argmax(img[:, np.argmin(np.abs(az - normal))])]
        assert r_arc == pytest.approx(d, abs=GRID.range_step / 2)


def test_occluded_reflector_returns_nothing():
    pole = CircleSpec(centre=(3.0, 0.0), radius=0.1)
    screen = WallSpec(start=(1.5, -0.3), end=(1.5, 0.3))
    sp = sensor_pose(np.zeros(3))
    open_echoes = visible_echoes(world(circles=[pole]), sp, 5.1)
    hidden = visible_echoes(world(walls=[screen], circles=[pole]), sp, 5.1)
    assert np.any(np.abs(open_echoes.r - 2.75) < 0.01)
    assert not np.any(hidden.r > 2.0), "an echo from behind the wall got through"
    # a pole beside the screen is still seen
    side = visible_echoes(world(walls=[screen], circles=[CircleSpec(centre=(3.0, 2.0), radius=0.1)]), sp, 5.1)
    assert np.any(side.r > 2.5)


def test_exact_se2_integration():
    p = integrate(np.array([1.0, 2.0, 0.3]), 0.3, 1.0, 0.2)
    # the arc of radius v/w about the instantaneous centre
    c = np.array([1.0, 2.0]) + 0.3 * np.array([-math.sin(0.3), math.cos(0.3)])
    assert np.linalg.norm(p[:2] - c) == pytest.approx(0.3, abs=1e-12)
    assert p[2] == pytest.approx(0.5)
    q = integrate(np.zeros(3), 0.2, 0.0, 0.2)
    assert np.allclose(q, [0.04, 0, 0])


def test_slip_changes_motion_not_the_command():
    v, w = 0.3, 0.0
    assert apply_slip(v, w, (1.0, 1.0)) == pytest.approx((0.3, 0.0))
    stall = apply_slip(v, w, (0.0, 0.0))
    assert stall == pytest.approx((0.0, 0.0))
    vs, ws = apply_slip(v, w, (0.2, 1.0))  # left wheel slips: the robot turns left unexpectedly
    assert ws > 0.5 and vs < v


def test_noise_sets_the_floor_and_bursts_bury_the_scene():
    model = SonarModel(GRID, snr_db=5.0, processing=Processing.raw())
    w = world(walls=[WallSpec(start=(2.0, -6.0), end=(2.0, 6.0))])
    rng = np.random.default_rng(0)
    clean = model.render(w, np.zeros(3), rng)
    floor_db = 60 * (np.median(clean) - clean.max())  # dB below the peak
    assert -48 < floor_db < -28  # 5 dB SNR + 33 dB processing gain
    burst = model.render(w, np.zeros(3), rng, snr_db=-80.0)
    corr = np.corrcoef(burst.ravel(), model.render(w, np.zeros(3), None).ravel())[0, 1]
    assert abs(corr) < 0.2 and burst.mean() > 0.9


def test_ertis_energyscapes_remove_the_noise_floor_and_bursts_still_bury_the_scene():
    model = SonarModel(GRID, snr_db=5.0)
    w = world(walls=[WallSpec(start=(2.0, -6.0), end=(2.0, 6.0))], circles=[CircleSpec(centre=(3.5, 1.5), radius=0.05)])
    rng = np.random.default_rng(0)
    clean, truth = model.render(w, np.zeros(3), rng), model.render(w, np.zeros(3), None)
    assert np.median(clean) == 0 and clean.max() > 0.6  # arcs and blobs on black
    assert np.corrcoef(clean.ravel(), truth.ravel())[0, 1] > 0.9  # the noise is (nearly) gone
    bursts = [model.render(w, np.zeros(3), rng, snr_db=-80.0) for _ in range(4)]
    for burst in bursts:
        assert abs(np.corrcoef(burst.ravel(), truth.ravel())[0, 1]) < 0.2
        # not a black frame: bright noise blobs everywhere, at every range and azimuth band
        rows, cols = (burst > 0.3).any(1), (burst > 0.3).any(0)
        assert rows.reshape(10, -1).any(1).all() and cols.reshape(9, -1).any(1).all(), (rows.mean(), cols.mean())
    assert abs(np.corrcoef(bursts[0].ravel(), bursts[1].ravel())[0, 1]) < 0.2  # and never the same twice


def test_coherence_factor_darkens_range_bins_shared_by_many_directions():
    """A wall at normal incidence puts many directions into the same range bins; a pole of the same
    echo amplitude is alone in its bin. Delay-and-sum shows both alike; DMAS3-CF dims the wall."""
    wall = visible_echoes(world(walls=[WallSpec(start=(2.15, -6.0), end=(2.15, 6.0))]), sensor_pose(np.zeros(3)), 5.1)
    point = Echoes(np.array([2.0]), np.array([0.0]), np.array([float(np.sqrt((wall.amp ** 2).max()))]))
    das, cf = SonarModel(GRID, processing=Processing.raw()), SonarModel(GRID, processing=Processing.ertis())
    ratio_das = das.amplitude(wall, 1)[0].max() / das.amplitude(point, 1)[0].max()
    ratio_cf = cf.amplitude(wall, 1)[0].max() / cf.amplitude(point, 1)[0].max()
    assert ratio_cf < 0.7 * ratio_das, (ratio_das, ratio_cf)  # measured: 0.52, -5.6 dB


def test_a_batch_renders_as_its_frames_one_by_one():
    from sonarset.sim.families import lab_world

    model, w = SonarModel(GRID.model_copy(update={"n_range": 60, "n_azimuth": 45})), lab_world(3)
    poses = np.array([[2.0, 2.0, 0.3], [2.1, 2.05, 0.4], [6.0, 5.0, -2.0], [6.0, 5.0, 2.5]])
    batch, snr = model.render_batch(w, poses, np.random.default_rng(5), snr_db=np.array([5.0, 5.0, -80.0, 5.0]))
    rng = np.random.default_rng(5)
    for k, (pose, s) in enumerate(zip(poses, [5.0, 5.0, -80.0, 5.0])):
        img, eff = model.render(w, pose, rng, snr_db=s, return_snr=True)
        np.testing.assert_allclose(batch[k], img, atol=1e-6)
        assert eff == pytest.approx(snr[k])
    # the echoes of a batch are those of each pose, tagged with the frame they belong to
    ech = visible_echoes(w, sensor_pose(poses), 5.1)
    for k, pose in enumerate(poses):
        one = visible_echoes(w, sensor_pose(pose), 5.1)
        np.testing.assert_array_equal(ech.r[ech.frame == k], one.r)


@pytest.mark.parametrize("shape", [(16, 13), (12, 9), (3, 3)])
@pytest.mark.parametrize("processing", [Processing.raw(), Processing.ertis()], ids=["raw", "ertis"])
def test_coarse_grids_render_their_reflector_in_the_right_bin(shape, processing):
    """Range bins wider than the range-PSF table once crashed the model (16 bins over 4.5 m) or lost
    the echo (12 bins)."""
    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=shape[0], azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=shape[1])
    w = world(circles=[CircleSpec(centre=(2.6, 0.0), radius=0.05)])
    img = SonarModel(grid, processing=processing).render(w, np.zeros(3), None)
    assert img.shape == shape and np.isfinite(img).all() and img.max() > 0.3
    r, th = peak(img, grid)
    r_true = 2.6 - 0.05 - SENSOR_OFFSET
    assert abs(r - r_true) <= grid.range_step and abs(th) <= grid.azimuth_step
