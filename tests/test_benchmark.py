"""``sonarset benchmark``: protocol v1 frozen in code, its stores cached and checked, one results file
per run that compares only with files of its own protocol version."""

import dataclasses
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from typer.testing import CliRunner

from sonarset.cli.app import app
from sonarset.errors import SonarSetError
from sonarset.format.attrs import NAMESPACE, SensorGrid
from sonarset.sim import FAMILIES
from sonarset.sim.runs import plan_runs
from sonarset.sim.spec import GenerationSpec
from sonarset.store.store import open_store

from sonarset.models.benchmark import PROTOCOL_V1, PROTOCOL_V1_QUICK, Protocol, StoreRecipe, compare_results
from sonarset.models.benchmark.protocol import V1_FAMILIES
from sonarset.models.benchmark.stores import MARKER, ensure_store

runner = CliRunner()


def test_v1_is_the_families_fresh_runs_and_the_demos_run():
    """v1 simulates what README's family tables and the demo simulate today, from held-out seeds."""
    assert set(V1_FAMILIES) <= set(FAMILIES)
    assert [d.name for d in PROTOCOL_V1.datasets] == [*V1_FAMILIES, "demo-lab"]
    families, demo = PROTOCOL_V1.stores().values()
    today = GenerationSpec(world="lab:0,corridor:0,orchard:0,warehouse:0,rooms:0", test_runs=1, minutes=10, seed=4242)
    assert plan_runs(families.spec(PROTOCOL_V1)) == plan_runs(today)
    # models/demo.py's simulate_fresh_run(minutes=25, seed=2026)
    assert plan_runs(demo.spec(PROTOCOL_V1)) == plan_runs(GenerationSpec(runs=0, test_runs=1, minutes=25.0, seed=2026,
                                                                         grid=SensorGrid.default()))
    assert PROTOCOL_V1.sensor_grid().matches(SensorGrid.default()) and 0 not in (families.seed, demo.seed)
    assert PROTOCOL_V1.samples == 1000 and PROTOCOL_V1.horizons == (1, 3, 5, 10) and PROTOCOL_V1.ceiling
    assert json.loads(json.dumps(PROTOCOL_V1.to_dict()))["stores"]["families"]["seed"] == 4242


def test_quick_end_to_end_through_the_cli(tmp_path):
    cache, first, second = tmp_path / "cache", tmp_path / "a", tmp_path / "b"
    args = ["benchmark", "flow", "persistence", "naive", "--quick", "--cache", str(cache), "--device", "cpu"]
    r = runner.invoke(app, [*args, "--out", str(first)])
    assert r.exit_code == 0, r.output
    assert "lab: 40 windows in" in r.output and "simulating families-quick" in r.output
    doc = json.loads((first / "results.json").read_text())
    assert doc["protocol"]["version"] == "v1-quick" and doc["protocol"]["definition"] == PROTOCOL_V1_QUICK.to_dict()
    assert [m["method"] for m in doc["models"]] == ["flow", "persistence", "naive"]
    for ds in PROTOCOL_V1_QUICK.datasets:
        entry = doc["datasets"][ds.name]
        assert entry["windows"] == 40
        for h in PROTOCOL_V1_QUICK.horizons:
            per_h = entry["horizons"][str(h)]
            assert set(per_h["ceilings"]) == {"ceiling", "observable"}
            for k in PROTOCOL_V1_QUICK.metrics:
                assert per_h["methods"]["flow"][k]["n"] > 0 and per_h["methods"]["persistence"][k]["n"] > 0
                c = per_h["methods"]["persistence"]["vs_reference"][k]
                assert set(c) >= {"mean_diff", "t_paired_p", "p_holm", "wilcoxon_p", "ci_low", "ci_high", "t_hac_p",
                                  "p_hac_holm"}
            assert math.isclose(per_h["methods"]["persistence"]["vs_reference"]["cc"]["mean_diff"],
                                per_h["methods"]["persistence"]["cc"]["mean"] - per_h["methods"]["flow"]["cc"]["mean"])
            assert per_h["methods"]["persistence"]["gap_share"]["cc"] < 0  # persistence is worse than flow
            # the models against each other: each against every model before it in the file
            assert "vs_models" not in per_h["methods"]["persistence"]
            head = per_h["methods"]["naive"]["vs_models"]["persistence"]["cc"]
            assert math.isclose(head["mean_diff"], per_h["methods"]["naive"]["cc"]["mean"]
                                - per_h["methods"]["persistence"]["cc"]["mean"]) and head["p_holm"] >= head["t_paired_p"]
            assert head["t_hac_p"] is not None and head["p_hac_holm"] >= head["t_hac_p"] > 0
    # Holm over the whole file: 3 datasets x 2 horizons x 7 metrics x 2 models against flow; and apart,
    # naive against persistence
    assert doc["statistics"]["tests"] == 3 * 2 * len(PROTOCOL_V1_QUICK.metrics) * 2
    assert doc["statistics"]["head_to_head_tests"] == 3 * 2 * len(PROTOCOL_V1_QUICK.metrics)
    assert all(doc["stores"][s]["generated"] for s in ("families-quick", "demo-lab-quick"))
    assert doc["machine"]["cores"] >= 1 and doc["machine"]["sonarset"] and doc["timings"]["per_method"]["flow"] > 0
    md = (first / "results.md").read_text()
    rows = [line.split(" | ")[0] for line in md.splitlines()]
    assert rows.count("| flow") == 4 and rows.count("| persistence") == 4 and rows.count("| naive") == 4
    assert "## demo-lab" in md and "| *observable ceiling* |" in md
    assert "## Cells not resolved" in md and "- persistence vs flow: better at Holm p < 0.05 in " in md

    stamp = (cache / "families-quick.zarr" / "zarr.json").stat().st_mtime_ns
    r = runner.invoke(app, [*args, "--out", str(second)])
    assert r.exit_code == 0, r.output
    assert "simulating" not in r.output
    again = json.loads((second / "results.json").read_text())
    assert not any(s["generated"] for s in again["stores"].values())
    assert (cache / "families-quick.zarr" / "zarr.json").stat().st_mtime_ns == stamp
    assert again["datasets"]["lab"]["horizons"] == doc["datasets"]["lab"]["horizons"]  # same windows, same numbers
    assert {d["n_in"] for d in doc["datasets"].values()} == {3}  # the context the windows have room for

    r = runner.invoke(app, ["benchmark", "--compare", str(first / "results.json"), str(second / "results.json")])
    assert r.exit_code == 0, r.output
    assert r.output.count(" | persistence | ") == 2 and "v1-quick" in r.output
    other = tmp_path / "other.json"
    other.write_text(json.dumps({**doc, "protocol": {**doc["protocol"], "version": "v1"}}))
    r = runner.invoke(app, ["benchmark", "--compare", str(first / "results.json"), str(other)])
    assert r.exit_code == 1 and "protocol sonarset-benchmark v1, not sonarset-benchmark v1-quick" in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_unknown_model_fails_in_one_line_before_any_simulation(tmp_path):
    r = runner.invoke(app, ["benchmark", "flow", "nope", "--quick", "--cache", str(tmp_path / "c"),
                            "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and "nope" in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists() and not (tmp_path / "o").exists()


def test_compare_refuses_files_scored_on_other_windows(tmp_path):
    """Models of another context draw other windows from the same seed: such files do not compare
    (a file from before the context was recorded has the paper's 3)."""
    paths = []
    for name, dataset in (("old", {}), ("five", {"n_in": 5})):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps({"protocol": {"name": "p", "version": "v1"}, "datasets": {"lab": dataset}}))
    with pytest.raises(SonarSetError, match="five.json: windows with room for 5 input frames, not 3 as .*old.json's"):
        compare_results(paths)


def test_compare_refuses_what_is_not_a_results_file(tmp_path):
    bad = tmp_path / "x.json"
    bad.write_text("{}")
    with pytest.raises(SonarSetError, match="not a benchmark results file"):
        compare_results([bad])


TINY_GRID = SensorGrid(range_min_m=0.5, range_max_m=2.5, n_range=40, azimuth_min_rad=-1.2, azimuth_max_rad=1.2,
                       n_azimuth=18)
TINY = Protocol(version="test", datasets=(), samples=4, horizons=(1,),
                grid=tuple((k, getattr(TINY_GRID, k)) for k in ("range_min_m", "range_max_m", "n_range",
                                                                 "azimuth_min_rad", "azimuth_max_rad", "n_azimuth")))
RECIPE = StoreRecipe("tiny", "corridor:0", minutes=0.1, seed=7)  # one run: simulated in this process


def test_cached_store_is_completed_after_a_kill_and_regenerated_when_stale(tmp_path):
    store, info = ensure_store(RECIPE, TINY, tmp_path)
    assert info["generated"] and store.runs("test") == ["test_000"]
    images = store.run("test_000").read("images")
    assert ensure_store(RECIPE, TINY, tmp_path)[1]["generated"] is False
    # a variant of the protocol that scores fewer windows (bench/bench_echowarp_parts.py): its runs
    # are the recipe's, so the store is marked for it, not simulated again
    fewer = dataclasses.replace(TINY, version="test-2", samples=2)
    assert ensure_store(RECIPE, fewer, tmp_path)[1]["generated"] is False
    assert open_store(tmp_path / "tiny.zarr").group.attrs[MARKER]["version"] == "test-2"

    # a generation killed while writing test_000: the run is there but not complete
    path = tmp_path / "tiny.zarr"
    group = zarr.open_group(path / "test_000", mode="r+")
    group.attrs[NAMESPACE] = {**group.attrs[NAMESPACE], "complete": False}
    store, info = ensure_store(RECIPE, TINY, tmp_path)
    assert info["generated"] and "test_000 is incomplete" in info["reason"]
    np.testing.assert_array_equal(store.run("test_000").read("images"), images)  # deterministic

    # a store of the benchmark's made with other settings (an older simulator): discarded, made anew
    group = zarr.open_group(path / "test_000", mode="r+")
    group.attrs[NAMESPACE] = {**group.attrs[NAMESPACE], "source": {**group.attrs[NAMESPACE]["source"],
                                                                     "simulator": "sonarset 0.0.1"}}
    store, info = ensure_store(RECIPE, TINY, tmp_path)
    assert info["generated"] and "other settings (simulator)" in info["reason"]
    assert open_store(path).group.attrs[MARKER]["seed"] == 7

    # a store the benchmark did not make is never removed
    shutil.rmtree(path)
    from sonarset.sim import generate

    generate(path, world="corridor:0", test_runs=1, minutes=0.1, seed=8, grid=TINY_GRID)
    with pytest.raises(SonarSetError, match="not a store the benchmark made"):
        ensure_store(RECIPE, TINY, tmp_path)
    assert (path / "zarr.json").exists()


def test_unresolved_cells_say_how_many_windows_a_difference_needs():
    from sonarset.models.benchmark.tables import unresolved_cells, unresolved_table
    from sonarset.scoring.stats import windows_to_pass

    def test(diff, p):
        return {"n": 100, "mean_diff": diff, "t_paired_p": p, "t_hac_p": 2 * p, "p_holm": min(1.0, 3 * p)}

    results = {"statistics": {"reference": "flow", "tests": 3, "head_to_head_tests": 3},
               "datasets": {"lab": {"horizons": {"1": {"methods": {
                   "flow": {},
                   "m": {"vs_reference": {"cc": test(+0.1, 1e-6), "nrmsd": test(-0.01, 0.1), "echo_f1": test(-0.02, 0.5)}},
               }}}}}}
    cells = unresolved_cells(results)[("m", "flow")]
    assert cells["resolved"] == 1 and cells["worse"] == 1  # CC passes; echo F1 is lower on the mean
    [nrmsd] = cells["open"]  # lower NRMSD is better: not significant
    assert nrmsd["metric"] == "nrmsd" and nrmsd["windows_to_pass"] == [windows_to_pass(0.1, 100, 0.05 / 3),
                                                                       windows_to_pass(0.2, 100, 0.05 / 3)]
    assert 200 < nrmsd["windows_to_pass"][0] < nrmsd["windows_to_pass"][1]  # the robust test's p is the larger
    table = unresolved_table(results)
    assert "- m vs flow: better at Holm p < 0.05 in 1 cells, better on the mean but not significantly in 1, " \
           "worse on the mean in 1" in table and "| m vs flow | lab | one-shot | NRMSD | -0.0100 | 100 |" in table
    assert unresolved_cells(results, alpha=1e-7)[("m", "flow")]["resolved"] == 0  # CC's Holm p 3e-6 is above it


def test_a_method_named_with_a_bar_keeps_its_tables_columns():
    """A predictor's name is the user's: a '|' in it must not end its table cell."""
    from sonarset.models.benchmark import load_results
    from sonarset.models.benchmark.tables import dataset_table, summary_table, unresolved_table

    shipped = Path(__file__).resolve().parents[1] / "docs/results/benchmark-v1.json"
    results = json.loads(json.dumps(load_results(shipped)).replace('"echopt"', '"echo|pt"'))
    for table in (summary_table(results), dataset_table(results, "lab"), unresolved_table(results)):
        rows = [r for r in table.splitlines() if r.startswith("|")]
        widths = {len(re.split(r"(?<!\\)\|", r)) for r in rows}
        assert len(widths) == 1 and any("echo\\|pt" in r for r in rows), table
