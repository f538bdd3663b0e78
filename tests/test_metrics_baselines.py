"""Metrics, baselines and the rollout against known answers."""

import math

import numpy as np
import pytest
from scipy import stats

from sonarset.scoring.metrics import cc, cc_and_nrmsd, nrmsd, slip_error
from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.scoring.stats import (WindowPlaces, auc, compare, hac_t_p, hac_variance, holm, mcnemar_p, wilcoxon_p,
                                    wilson_interval, windows_to_pass)
from sonarset.windows import N_IN
from sonarset.models.baselines import AcousticFlow, NaiveShift, Persistence, rollout
from sonarset.models.registry import make_predictor

GRID = SensorGrid.default()
RIG = RobotRig()
ON_AXLE = RobotRig(sensor_offset_m=0.0)  # a rotation turns the sensor on the spot


def test_cc_nrmsd_slip_by_hand():
    m = np.array([[1.0, 2.0], [3.0, 4.0]])
    p = np.array([[2.0, 2.0], [3.0, 5.0]])
    # corr2 by hand: means 2.5 and 3; deviations (-1.5,-.5,.5,1.5), (-1,-1,0,2)
    num = 1.5 + 0.5 + 0 + 3.0
    den = math.sqrt((2.25 + 0.25 + 0.25 + 2.25) * (1 + 1 + 0 + 4))
    assert cc(p, m) == pytest.approx(num / den)
    assert nrmsd(p, m) == pytest.approx(math.sqrt(2) / math.sqrt(30))
    assert slip_error(p, m) == pytest.approx(math.sqrt(2) / math.sqrt(num / den))
    # vectorised over leading axes, and exact for identical images
    batch = np.random.default_rng(0).random((3, 4, 10, 6))
    assert cc(batch, batch).shape == (3, 4) and np.allclose(cc(batch, batch), 1)
    assert np.allclose(nrmsd(batch, batch), 0)
    assert cc(-batch, batch) == pytest.approx(-np.ones((3, 4)))


def test_the_one_pass_scores_match_the_textbook_formulas():
    """cc_and_nrmsd works from centred moments: it must equal the direct definitions, for
    near-identical images (where ||p - m|| cancels), constant images (NaN cc) and empty targets."""
    rng = np.random.default_rng(3)
    m = (rng.random((5, 40, 30)) ** 6).astype(np.float32)
    preds = [rng.random(m.shape).astype(np.float32), m + np.float32(1e-4) * rng.random(m.shape).astype(np.float32), m]
    for p in preds:
        pf, mf = p.reshape(5, -1).astype(np.float64), m.reshape(5, -1).astype(np.float64)
        pc, mc = pf - pf.mean(1, keepdims=True), mf - mf.mean(1, keepdims=True)
        want_cc = (pc * mc).sum(1) / np.sqrt((pc ** 2).sum(1) * (mc ** 2).sum(1))
        want_nrmsd = np.linalg.norm(pf - mf, axis=1) / np.linalg.norm(mf, axis=1)
        got_cc, got_nrmsd = cc_and_nrmsd(p, m)
        np.testing.assert_allclose(got_cc, want_cc, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got_nrmsd, want_nrmsd, rtol=1e-7, atol=1e-12)
    flat, empty = np.full((4, 3), 0.5), np.zeros((4, 3))
    assert math.isnan(cc(flat, m[0, :4, :3])) and nrmsd(flat, flat) == 0.0
    assert math.isinf(nrmsd(flat, empty)) and math.isnan(nrmsd(empty, empty))


def test_holm_and_paired_comparison():
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    rng = np.random.default_rng(1)
    a = rng.normal(0, 1, 300)
    c = compare(a + 0.2, a, metric="cc", horizon=1, names=("x", "y"))
    assert c.mean_diff == pytest.approx(0.2) and c.t_paired_p < 1e-10 and c.ci_low <= 0.2 <= c.ci_high
    # the paired test sees a small shift that the two-sample test (the paper's) cannot
    noisy = compare(a + 0.02 + rng.normal(0, 0.01, 300), a, metric="cc", horizon=1, names=("x", "y"))
    assert noisy.t_paired_p < 1e-6 < noisy.t_two_sample_p


def test_serial_robust_test_counts_correlated_windows_once():
    rng = np.random.default_rng(3)
    d = rng.normal(0.1, 1, 200)
    apart = np.arange(200) * 100.0  # farther apart than the kernel reaches: the paired t-test
    c = compare(d, np.zeros(200), metric="cc", horizon=1, names=("x", "y"),
                windows=WindowPlaces.of([("run", int(k)) for k in apart], span=13))
    assert c.t_hac_p == pytest.approx(c.t_paired_p, rel=1e-9)
    # every window twice at the same frame: no more evidence than once, the variance of the mean doubles
    twice = hac_variance(np.repeat(d, 2), np.repeat(apart, 2), np.zeros(400), bandwidth=50)
    assert twice == pytest.approx(2 * np.var(np.repeat(d, 2), ddof=1) / 400, rel=0.01)
    # the same frames of two runs are independent windows
    runs = np.repeat([0, 1], 200)
    assert hac_variance(np.r_[d, d], np.r_[apart, apart], runs, 50) == pytest.approx(np.var(np.r_[d, d], ddof=1) / 400)
    with pytest.raises(ValueError):  # positions and values must agree
        hac_variance(d, apart[:10], np.zeros(10), 50)
    with pytest.raises(ValueError):
        hac_variance(d, apart, np.zeros(200), 0)
    assert math.isnan(hac_t_p(np.ones(5), np.arange(5.0), np.zeros(5), 10))  # no spread: undefined


def test_serial_robust_test_holds_its_level_where_the_paired_t_test_does_not():
    """Differences with no mean but correlated neighbours (AR(1), rho 0.6, one window per frame): the
    paired t-test rejects 7 times as often as its 5 %; the robust test close to it (Newey-West's
    known small excess at this n)."""
    rng = np.random.default_rng(4)
    n, reps, rho = 600, 300, 0.6
    e = rng.normal(size=(reps, n))
    d = np.empty_like(e)
    d[:, 0] = e[:, 0]
    for i in range(1, n):
        d[:, i] = rho * d[:, i - 1] + np.sqrt(1 - rho ** 2) * e[:, i]
    frames, runs = np.arange(n, dtype=float), np.zeros(n)
    naive = np.mean([stats.ttest_1samp(x, 0).pvalue < 0.05 for x in d])  # compare's paired t-test
    robust = np.mean([hac_t_p(x, frames, runs, bandwidth=20) < 0.05 for x in d])
    assert naive > 0.25 and robust < 0.12, (naive, robust)


@pytest.mark.parametrize("d", [
    [0.5, -0.5, 1, 1, 0, 2, 1 / 3],  # ties and a zero: scipy's exact permutation test
    [1, 1, 1, 2, 2, -1, 3, 0, 0, 0.5, 0.5, 4, -4],  # 13, the most scipy permutes
    [0.2, 0.1, -0.3, 0.4, -0.05, 0.7],  # no ties: scipy's exact distribution
    np.round(np.random.default_rng(3).normal(size=14), 1),  # 14 with ties: the normal approximation
    [np.nan, 1, 1, 2],  # NaN: scipy's NaN, not a permutation test of it
])
def test_wilcoxon_p_is_scipys(d):
    """The vectorised permutation test gives scipy's p to the last bit where scipy permutes, and
    scipy's own everywhere else."""
    d = np.asarray(d, float)
    np.testing.assert_equal(wilcoxon_p(d), stats.wilcoxon(d).pvalue)
    ok = np.isfinite(d)  # compare drops the windows where a score is undefined
    assert compare(d, np.zeros_like(d), metric="cc", horizon=1, names=("a", "b")).wilcoxon_p == stats.wilcoxon(d[ok]).pvalue


def test_windows_to_pass_is_where_the_same_effect_reaches_the_level():
    def sample(n):  # an effect of 0.1 standard deviations, exactly, on n windows
        z = np.random.default_rng(n).standard_normal(n)
        return 0.1 + (z - z.mean()) / z.std(ddof=1)

    p = stats.ttest_1samp(sample(400), 0).pvalue  # t = 2: p 0.046
    need = windows_to_pass(p, 400, 1e-5)
    assert 1900 < need < 2000
    assert stats.ttest_1samp(sample(round(need)), 0).pvalue == pytest.approx(1e-5, rel=0.05)
    assert windows_to_pass(1e-9, 400, 1e-5) < 400  # already past the level: fewer would do
    assert windows_to_pass(1.0, 400, 1e-5) == math.inf
    assert math.isnan(windows_to_pass(float("nan"), 400, 1e-5)) and math.isnan(windows_to_pass(0.5, 2, 1e-5))


def test_persistence_copies_the_last_frame():
    frames = np.random.default_rng(0).random((2, 3, *GRID.shape)).astype(np.float32)
    out = Persistence(GRID).predict(frames, np.zeros((2, 4, 2)))
    assert np.array_equal(out, frames[:, -1])


@pytest.mark.parametrize("predictor", [NaiveShift(GRID, ON_AXLE), AcousticFlow(GRID, ON_AXLE),
                                       NaiveShift(GRID, ON_AXLE, backend="scipy")])
def test_pure_rotation_shifts_azimuth_exactly(predictor):
    rng = np.random.default_rng(2)
    frames = rng.random((1, 3, *GRID.shape)).astype(np.float32)
    k = 3  # bins
    omega = k * GRID.azimuth_step / ON_AXLE.frame_interval_s
    out = predictor.predict(frames, np.array([[[0, 0]] * 3 + [[0.0, omega]]]))
    # turning left by k bins: what was at azimuth theta + k bins is now at theta
    np.testing.assert_allclose(out[0, :, :-k], frames[0, -1, :, k:], atol=1e-4)  # float32 grids


def test_flow_moves_a_reflector_along_its_flow_line():
    r0, th0 = 3.0, math.radians(35)
    rr, tt = np.meshgrid(GRID.range_centres(), GRID.azimuth_centres(), indexing="ij")
    blob = np.exp(-(((rr - r0) / 0.02) ** 2 + ((tt - th0) / math.radians(2)) ** 2) / 2)
    frames = np.repeat(blob[None, None].astype(np.float32), 3, axis=1)
    v = 0.3
    one_second = RobotRig(frame_interval_s=1.0, sensor_offset_m=0.0)
    flow = AcousticFlow(GRID, one_second).predict(frames, np.array([[[0, 0]] * 3 + [[v, 0.0]]]))[0]
    naive = NaiveShift(GRID, one_second).predict(frames, np.array([[[0, 0]] * 3 + [[v, 0.0]]]))[0]
    # where the reflector really is after moving 0.3 m forward
    x, y = r0 * math.cos(th0) - v, r0 * math.sin(th0)
    r1, th1 = math.hypot(x, y), math.atan2(y, x)
    assert r1 * math.sin(th1) == pytest.approx(r0 * math.sin(th0))  # the flow line
    i, j = np.unravel_index(np.argmax(flow), flow.shape)
    assert abs(GRID.range_centres()[i] - r1) <= GRID.range_step
    assert abs(GRID.azimuth_centres()[j] - th1) <= GRID.azimuth_step
    i, j = np.unravel_index(np.argmax(naive), naive.shape)
    assert abs(GRID.azimuth_centres()[j] - th0) <= GRID.azimuth_step / 2  # naive keeps the azimuth: wrong


def test_torch_and_scipy_warps_agree():
    rng = np.random.default_rng(3)
    frames = rng.random((4, 3, *GRID.shape)).astype(np.float32)
    cmds = np.c_[rng.uniform(-0.3, 0.3, 16), rng.uniform(-1, 1, 16)].reshape(4, 4, 2)
    for cls in (NaiveShift, AcousticFlow):
        a = cls(GRID, RIG, backend="torch").predict(frames, cmds)
        b = cls(GRID, RIG, backend="scipy").predict(frames, cmds)
        np.testing.assert_allclose(a, b, atol=1e-4)


def test_baselines_take_the_rig_and_the_window_geometry():
    """The sensor offset and frame interval reach the baselines through the rig alone."""
    rig = RobotRig(frame_interval_s=0.1, sensor_offset_m=0.05)
    for spec in ("persistence", "naive", "flow"):
        p = make_predictor(spec, GRID, rig)
        assert p.n_in == N_IN and getattr(p, "rig", rig) is rig
    frames = np.random.default_rng(4).random((1, 3, *GRID.shape)).astype(np.float32)
    cmds = np.array([[[0, 0]] * 3 + [[0.3, 0.5]]])
    moved = AcousticFlow(GRID, rig).predict(frames, cmds)
    # the same motion: half the speed over twice the time
    slower = AcousticFlow(GRID, RobotRig(frame_interval_s=0.2, sensor_offset_m=0.05)).predict(frames, cmds / 2)
    np.testing.assert_allclose(moved, slower, atol=1e-5)
    on_axle = AcousticFlow(GRID, RobotRig(frame_interval_s=0.1, sensor_offset_m=0.0)).predict(frames, cmds)
    assert not np.allclose(moved, on_axle)  # the offset matters


def test_auc_wilson_and_mcnemar():
    assert auc(np.array([3.0, 4.0]), np.array([1.0, 2.0])) == 1.0
    assert auc(np.array([1.0, 2.0, np.nan]), np.array([1.0, 2.0])) == 0.5  # ties count half, NaN dropped
    assert math.isnan(auc(np.array([np.nan]), np.array([1.0])))
    lo, hi = wilson_interval(5, 10)
    assert lo == pytest.approx(0.2366, abs=1e-4) and hi == pytest.approx(0.7634, abs=1e-4)
    assert all(math.isnan(x) for x in wilson_interval(0, 0))
    a = np.array([True] * 8 + [False] * 2)
    assert mcnemar_p(a, ~a) == pytest.approx(0.109375)  # 8 vs 2 discordant pairs: binomial, two-sided
    assert math.isnan(mcnemar_p(a, a))


class AddOne:
    """Predicts the last input frame plus one: the rollout's input history becomes visible."""

    name, grid = "add-one", GRID

    def predict(self, frames, commands):
        assert frames.shape[1] == 3 and commands.shape[1] == 4
        return frames[:, -1] + 1.0


def test_rollout_feeds_predictions_back():
    frames = np.zeros((2, 3, 4, 5), np.float32)
    frames[:, -1] = 10.0
    out = rollout(AddOne(), frames, np.zeros((2, 3 + 5, 2)), 5)
    # if measured frames were used after step 1, every step would give 11
    assert [float(out[0, h, 0, 0]) for h in range(5)] == [11, 12, 13, 14, 15]
    with pytest.raises(ValueError, match="need 8 commands"):
        rollout(AddOne(), frames, np.zeros((2, 7, 2)), 5)


def test_rollout_passes_each_step_its_own_commands():
    seen = []

    class Spy(AddOne):
        def predict(self, frames, commands):
            seen.append(commands[0, :, 0].tolist())
            return frames[:, -1]

    cmds = np.zeros((1, 6, 2))
    cmds[0, :, 0] = np.arange(6)
    rollout(Spy(), np.zeros((1, 3, 4, 5), np.float32), cmds, 3)
    assert seen == [[0, 1, 2, 3], [1, 2, 3, 4], [2, 3, 4, 5]]


def test_report_formats_and_the_wilcoxon_guard():
    from sonarset.report.numbers import format_p, horizon_name
    from sonarset.scoring.stats import wilcoxon_p

    assert [format_p(p) for p in (None, float("nan"), 0.5, 0.0004, 1e-301)] == ["n/a", "n/a", "0.500", "4.0e-04",
                                                                                  "< 1e-300"]
    assert [horizon_name(h) for h in (1, 3, 10)] == ["one-shot", "AR-3", "AR-10"]
    assert np.isnan(wilcoxon_p([0.1, 0.2])) and np.isnan(wilcoxon_p(np.zeros(5)))
    assert wilcoxon_p(np.arange(1, 21, dtype=float)) < 1e-4
