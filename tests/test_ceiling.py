"""The noise ceiling (``eval --ceiling``): target frames re-rendered with independent noise."""

import csv
import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from sonarset import open_store
from sonarset.scoring.ceiling import CeilingUnavailable, RunRenderer, rerender
from sonarset.cli.app import app
from sonarset.models.eval.report import write_report
from sonarset.models.eval.evaluate import evaluate
from sonarset.format.attrs import SensorGrid
from sonarset.sim import generate
from sonarset.sim import sonar
from sonarset.store.store import create_store

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=100, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=45)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    path = tmp_path_factory.mktemp("ceiling") / "sim.zarr"
    generate(path, runs=0, test_runs=1, minutes=1.0, seed=3, snr_db=5, workers=1, grid=GRID)
    return open_store(path)


@pytest.fixture(scope="module")
def mixed(sim, tmp_path_factory):
    """The simulated run, a copy whose world file is gone, and a copy marked as imported."""
    s = create_store(tmp_path_factory.mktemp("mixed") / "mixed.zarr", GRID, processing=sim.processing)
    d = sim.run("test_000").load()
    src = dict(sim.run("test_000").attrs.source)
    arrays = dict(images=d.images, velocity=d.velocity, time=d.time, pose=d.pose, snr_db=d.snr_db, slip=d.slip)
    s.write_run("test_000", **arrays, split="test", source=src)
    s.write_run("test_001", **arrays, split="test", source={**src, "world": "/nowhere/gone.json"})
    s.write_run("test_002", **arrays, split="test", source={"kind": "import", "file": "rec.npz"})
    return s


def test_ceiling_row_bounds_the_predictors(sim, tmp_path):
    res = evaluate(sim, ["persistence", "naive"], horizons=(1, 3), samples=120, seed=1, ceiling=True)
    assert res.methods == ["persistence", "naive", "ceiling", "observable"]
    assert res.predictors == ["persistence", "naive"]
    assert not res.ceiling_skipped and not any(n.startswith("ceiling") for n in res.notes)
    s = res.summary()
    for h in ("1", "3"):
        assert s["ceiling"][h]["n"] == 120
        assert s["ceiling"][h]["cc"]["mean"] > s["persistence"][h]["cc"]["mean"] + 0.02, h
        assert s["ceiling"][h]["nrmsd"]["mean"] < s["persistence"][h]["nrmsd"]["mean"], h
        # what the context could know lies between the baselines and the whole scene
        assert s["persistence"][h]["cc"]["mean"] < s["observable"][h]["cc"]["mean"] <= s["ceiling"][h]["cc"]["mean"], h
    # the farther ahead, the more of the target entered the view after the context
    assert s["observable"]["3"]["cc"]["mean"] < s["observable"]["1"]["cc"]["mean"]
    assert all({"ceiling", "observable"}.isdisjoint((c.a, c.b)) for c in res.comparisons)  # no paired tests
    assert {(c.a, c.b) for c in res.comparisons} == {("persistence", "naive")}
    write_report(res, tmp_path)
    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert doc["results"]["ceiling"]["3"]["n"] == 120 and doc["ceiling"]["skipped_runs"] == {}
    rows = list(csv.DictReader(open(tmp_path / "per_window.csv")))
    assert sum(r["method"] == "ceiling" for r in rows) == 2 * 120
    assert sum(r["method"] == "observable" for r in rows) == 2 * 120
    gap = doc["observable"]["gap_closed_vs_flow"]
    assert gap == {}  # no flow among the methods: no share to report
    report = (tmp_path / "report.md").read_text()
    assert "| *ceiling (noise ceiling, not a predictor)* |" in report and "independent noise draw" in report
    assert (tmp_path / "fig_horizon.png").stat().st_size > 5_000


def test_ceiling_is_one_without_noise(monkeypatch, tmp_path):
    """No sensor noise at all (SNR 300 dB, no noise floor): the re-render is the recorded frame, so
    the ceiling scores exactly 1 at every horizon; any misaligned target frame would show."""
    monkeypatch.setattr(sonar, "NOISE_FLOOR_DB", -400.0)
    path = tmp_path / "clean.zarr"
    generate(path, runs=0, test_runs=1, minutes=0.5, seed=4, snr_db=300, workers=1, grid=GRID)
    res = evaluate(open_store(path), ["persistence"], horizons=(1, 2, 5), samples=60, seed=0, ceiling=True)
    s = res.summary()
    for h in res.horizons:
        assert s["ceiling"][str(h)]["n"] == 60
        assert s["ceiling"][str(h)]["cc"]["mean"] > 0.9999 and s["ceiling"][str(h)]["nrmsd"]["mean"] < 1e-3
        assert s["persistence"][str(h)]["cc"]["mean"] < 0.99


def test_ceiling_is_deterministic_given_the_seed(sim):
    frames = np.array([3, 4, 10, 40, 41, 200])
    a = rerender(sim, "test_000", frames, seed=7)
    np.testing.assert_array_equal(a, rerender(sim, "test_000", frames, seed=7, batch_size=4))
    b = rerender(sim, "test_000", frames, seed=8)
    assert np.abs(a - b).max() > 0.05  # another seed, another noise draw
    recorded = sim.run("test_000").images[:][frames].astype(np.float32)
    assert np.abs(a - recorded).max() > 0.05  # independent of the generator's own noise
    r1 = evaluate(sim, ["persistence"], horizons=(2,), samples=50, seed=2, ceiling=True)
    r2 = evaluate(sim, ["persistence"], horizons=(2,), samples=50, seed=2, ceiling=True)
    np.testing.assert_array_equal(r1.per_window["ceiling"][2]["cc"], r2.per_window["ceiling"][2]["cc"])


def test_runs_it_cannot_render_are_skipped_with_a_reason(mixed):
    with pytest.raises(CeilingUnavailable, match="world cannot be rebuilt: /nowhere/gone.json"):
        RunRenderer(mixed, "test_001")
    res = evaluate(mixed, ["persistence"], horizons=(1,), samples=200, seed=0, ceiling=True)
    assert set(res.ceiling_skipped) == {"test_001", "test_002"}
    assert "an imported recording" in res.ceiling_skipped["test_002"]
    notes = [n for n in res.notes if n.startswith("ceiling")]
    assert len(notes) == 2 and notes[0].startswith("ceiling: run test_001 not re-rendered: world cannot be rebuilt")
    pw = res.per_window["ceiling"][1]["cc"]
    in_sim = np.array([r == "test_000" for r, _ in res.window_ids])
    assert np.isfinite(pw[in_sim]).all() and np.isnan(pw[~in_sim]).all() and in_sim.any()
    assert res.summary()["ceiling"]["1"]["n"] == in_sim.sum()


def test_store_without_simulated_runs_omits_the_row(store, tmp_path):
    res = evaluate(store, ["persistence"], split="test", horizons=(1,), samples=5, ceiling=True)
    assert {"ceiling", "observable"}.isdisjoint(res.methods) and {"ceiling", "observable"}.isdisjoint(res.per_window)
    assert res.notes[-2:] == ["ceiling: run test_000 not re-rendered: no simulator provenance (source kind missing)",
                              "ceiling: no run of split 'test' can be re-rendered; the ceiling rows are omitted"]
    write_report(res, tmp_path, figures=False)
    assert "no run of split 'test' can be re-rendered" in (tmp_path / "report.md").read_text()
    assert evaluate(store, ["persistence"], split="test", horizons=(1,), samples=5).notes == \
        [n for n in res.notes if not n.startswith("ceiling")]  # nothing about it unless asked


def test_eval_cli_ceiling(sim, mixed, tmp_path):
    r = CliRunner().invoke(app, ["eval", sim.location, "--models", "persistence", "--samples", "30",
                                 "--horizons", "1,3", "--out", str(tmp_path / "o"), "--no-figures", "--ceiling"])
    assert r.exit_code == 0, r.output
    assert "noise ceiling, not a predictor" in r.output
    assert "ceiling" in json.loads((tmp_path / "o" / "metrics.json").read_text())["results"]
    r = CliRunner().invoke(app, ["eval", mixed.location, "--models", "persistence", "--samples", "30",
                                 "--horizons", "1", "--out", str(tmp_path / "p"), "--no-figures", "--ceiling"])
    assert r.exit_code == 0, r.output
    line = "ceiling: run test_002 not re-rendered: an imported recording, not a simulated run"
    assert line in r.output and line in (tmp_path / "p" / "report.md").read_text()


def test_observed_world_keeps_only_what_the_context_heard():
    from sonarset.scoring.ceiling import observed_world
    from sonarset.sim.sonar import SonarModel
    from sonarset.sim.world import World, WorldSpec

    world = World.from_spec(WorldSpec(
        walls=[{"start": (3.0, -1.0), "end": (3.0, 1.0)}, {"start": (-3.0, -1.0), "end": (-3.0, 1.0)}],
        circles=[{"centre": (2.0, 1.5), "radius": 0.1}, {"centre": (-2.0, 0.0), "radius": 0.1}],
        spawn=[{"x": (0, 0.1), "y": (0, 0.1)}]))
    model = SonarModel(GRID)
    facing_east = np.zeros((3, 3))  # the context: three frames facing +x
    seen = observed_world(world, model, facing_east)
    # the wall ahead (its normal-incidence stretch: off-normal samples are below the noise) and
    # the pole ahead; nothing behind the robot
    assert len(seen.seg_a) >= 1 and np.allclose(seen.seg_a[:, 0], 3.0) and np.allclose(seen.seg_b[:, 0], 3.0)
    assert -1.0 <= seen.seg_a[:, 1].min() < 0 < seen.seg_b[:, 1].max() <= 1.0
    assert seen.circ_c.tolist() == [[2.0, 1.5]]
    turned = np.array([[0.0, 0.0, math.pi]])
    # turned around, the whole world shows the wall behind; what the context heard does not
    behind = model.render_batch(world, turned, None)[0]
    known = model.render_batch(seen, turned, None)[0]
    assert behind.max() > 0.5 and known.max() < 0.05
    # facing +y, both walls' far ends are in view and heard, their near halves behind the sonar are not
    side = observed_world(world, model, np.array([[0.0, 0.0, math.pi / 2]]))
    assert len(side.seg_a) == 2 and (side.seg_a[:, 1] > 0).all() and (side.seg_b[:, 1] > 0).all()


def test_observable_ceiling_on_a_window(sim):
    from sonarset.scoring.ceiling import OBSERVABLE_STREAM

    r = RunRenderer(sim, "test_000", seed=4).with_stream(OBSERVABLE_STREAM)
    again = RunRenderer(sim, "test_000", seed=4, stream=OBSERVABLE_STREAM)
    assert np.array_equal(r.render_observed(np.arange(7, 10), np.array([10])),
                          again.render_observed(np.arange(7, 10), np.array([10])))
    target = sim.run("test_000").read("images", 10, 20).astype(np.float32)
    from sonarset.scoring.metrics import cc

    near = r.render_observed(np.arange(7, 10), np.array([10]))
    assert near.shape == (1, *GRID.shape) and near.dtype == np.float32
    assert cc(near[0], target[0]) > 0.8
