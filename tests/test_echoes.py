"""Echo-aware metrics on synthetic images: detection, matching, precision, recall, F1, position error."""

import math

import numpy as np
import pytest

from sonarset.scoring.echoes import ECHO_METRICS, EchoMatching, echo_scores, find_echoes
from sonarset.format.attrs import SensorGrid

GRID = SensorGrid.default()  # 200 x 90: 2.25 cm x 2 deg bins
MATCH = EchoMatching()


def echo_image(*echoes, width_r=2.0, width_a=1.5):
    """An image with Gaussian echoes at (range bin, azimuth bin, peak value) on a zero floor."""
    r, a = np.mgrid[:GRID.n_range, :GRID.n_azimuth]
    img = np.zeros(GRID.shape, np.float32)
    for i, j, v in echoes:
        img = np.maximum(img, v * np.exp(-((r - i) / width_r) ** 2 / 2 - ((a - j) / width_a) ** 2 / 2))
    return img


def scores(pred, target):
    out = echo_scores(np.asarray(pred)[None], np.asarray(target)[None], GRID, MATCH)
    return {k: float(v[0]) for k, v in out.items()}


def test_detects_echoes_at_their_positions():
    img = echo_image((40, 20, 0.8), (120, 70, 0.6), (150, 10, 0.2))  # the last is below the level
    p = find_echoes(img, GRID, MATCH)
    assert len(p.range_m) == 2 and p.image.tolist() == [0, 0]
    assert p.range_m[0] == pytest.approx(GRID.range_centres()[40]) and p.range_m[1] == pytest.approx(GRID.range_centres()[120])
    assert p.azimuth_deg[0] == pytest.approx(math.degrees(GRID.azimuth_centres()[20]))
    # a saturated plateau is one echo, at its centre
    flat = np.zeros(GRID.shape, np.float32)
    flat[60:63, 44:47] = 1.0
    q = find_echoes(flat, GRID, MATCH)
    assert len(q.range_m) == 1 and q.range_m[0] == pytest.approx(GRID.range_centres()[61])


def test_the_target_against_itself_scores_one():
    target = echo_image((40, 20, 0.8), (120, 70, 0.6), (90, 45, 0.9))
    s = scores(target, target)
    assert s["echo_f1"] == s["echo_precision"] == s["echo_recall"] == 1.0
    assert s["echo_range_cm"] == 0.0 and s["echo_azimuth_deg"] == 0.0


def test_a_shifted_echo_lowers_f1_and_raises_the_error():
    target = echo_image((40, 20, 0.8), (120, 70, 0.6))
    near = scores(echo_image((43, 20, 0.8), (120, 70, 0.6)), target)  # 6.75 cm: within 10 cm
    assert near["echo_f1"] == 1.0 and near["echo_range_cm"] == pytest.approx(100 * 3 * GRID.range_step / 2)
    far = scores(echo_image((40, 26, 0.8), (120, 70, 0.6)), target)  # 12 deg: out of the 6 deg tolerance
    assert far["echo_f1"] == 0.5 and far["echo_precision"] == 0.5 and far["echo_recall"] == 0.5
    farther = scores(echo_image((80, 26, 0.8), (10, 70, 0.6)), target)
    assert farther["echo_f1"] == 0.0 and math.isnan(farther["echo_range_cm"])
    assert near["echo_range_cm"] > scores(target, target)["echo_range_cm"]


def test_a_blurred_echo_lowers_precision():
    """An uncertain prediction spreads an echo over the places it might be: a smear whose crests
    are echoes where the target has none."""
    target = echo_image((100, 45, 0.9))
    smear = np.mean([echo_image((100 + dr, 45 + da, 0.9)) for dr, da in ((0, 0), (12, 0), (-12, 0), (0, 8), (0, -8))],
                    axis=0) * 2.0
    s = scores(smear, target)
    assert s["echo_recall"] == 1.0 and s["echo_precision"] < 0.5 and s["echo_f1"] < 1.0


def test_undefined_where_there_is_nothing_to_count():
    empty, target = np.zeros(GRID.shape, np.float32), echo_image((40, 20, 0.8))
    both = scores(empty, empty)
    assert all(math.isnan(both[k]) for k in ECHO_METRICS)
    miss = scores(empty, target)
    assert miss["echo_recall"] == 0.0 and miss["echo_f1"] == 0.0 and math.isnan(miss["echo_precision"])
    ghost = scores(target, empty)
    assert ghost["echo_precision"] == 0.0 and math.isnan(ghost["echo_recall"])


def test_batches_score_each_pair_on_its_own():
    a, b = echo_image((40, 20, 0.8)), echo_image((120, 70, 0.6), (60, 30, 0.7))
    batch = echo_scores(np.stack([a, b, a]), np.stack([a, b, b]), GRID, MATCH)
    assert batch["echo_f1"].tolist() == [1.0, 1.0, 0.0]


def reference_echoes(x, half_r, half_a, level):
    """Echo detection the plain way: a maximum filter, ndimage.label, ndimage.center_of_mass."""
    from scipy import ndimage

    local_max = ndimage.maximum_filter(x, size=(1, 2 * half_r + 1, 2 * half_a + 1), mode="constant", cval=-np.inf)
    structure = np.zeros((3, 3, 3), bool)
    structure[1] = True
    labels, n = ndimage.label((x >= local_max) & (x >= level), structure=structure)
    return np.array(ndimage.center_of_mass(np.ones_like(x), labels, range(1, n + 1))).reshape(-1, 3)


@pytest.mark.parametrize("share", [0.01, 0.05, 0.3])
def test_detection_matches_a_plain_maximum_filter(monkeypatch, share):
    """find_echoes compares only pixels >= level with their windows when they are few, and groups
    plateaus on a sparse graph: both paths must give the plain detection, edges (clipped windows),
    touching plateaus and ties included."""
    import sonarset.scoring.echoes as echoes

    rng = np.random.default_rng(7)
    x = rng.random((6, *GRID.shape)).astype(np.float32) * 0.25
    hot = rng.random(x.shape) < share
    x[hot] = rng.choice([0.3, 0.5, 0.9, 1.0], size=int(hot.sum())).astype(np.float32)  # ties, plateaus
    x[:, 0, :5] = x[:, -1, -5:] = 1.0  # plateaus on the image's edges and corners
    x[2, 50:53, 30] = 1.0
    x[2, 53, 31] = 1.0  # a diagonal touch
    want = reference_echoes(x, 5, 3, MATCH.level)  # 10 cm / 2.25 cm bins, rounded up; 6 deg / 2 deg bins
    assert len(want) > 10
    for threshold in (1.0, 0.0):  # the sparse path, then the filter
        monkeypatch.setattr(echoes, "_SPARSE_SHARE", threshold)
        got = find_echoes(x, GRID, MATCH)
        np.testing.assert_array_equal(got.image, np.rint(want[:, 0]))
        np.testing.assert_allclose(got.range_m, GRID.range_min_m + (want[:, 1] + 0.5) * GRID.range_step, atol=1e-12)
        np.testing.assert_allclose(got.azimuth_deg, np.degrees(GRID.azimuth_min_rad + (want[:, 2] + 0.5)
                                                              * GRID.azimuth_step), atol=1e-9)
