"""Training recipes: ``sonarset train --config RECIPE.toml``, the recipe a card records, and the
shipped model's lineage as recipe files."""

from __future__ import annotations

import json
import math
import os
import re
import shlex
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings, strategies as st
from typer.testing import CliRunner

from sonarset.cli.app import app
from sonarset.format.attrs import SensorGrid
from sonarset.models.echopt.recipes import (RECIPE_KEYS, config_of, dump_recipe, load_recipe, portable_command,
                                            recipe_of)
from sonarset.models.echopt.train_config import TrainConfig
from sonarset.store.store import create_store

from tests.conftest import make_run

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)
#: A short run, as options (flags) and as recipe settings.
FLAGS = ["--preset", "tiny", "--max-steps", "2", "--batch-size", "4", "--n-val", "4", "--device", "cpu",
         "--test-samples", "0", "--loss", "cc=1,w1=100", "--lr", "0.001", "--curriculum", "2", "--seed", "3",
         "--optimizer", "adamw", "--pushforward"]
SETTINGS = {"preset": "tiny", "max_steps": 2, "batch_size": 4, "n_val": 4, "device": "cpu", "test_samples": 0,
            "loss": "cc=1,w1=100", "lr": 0.001, "curriculum": "2", "seed": 3, "optimizer": "adamw",
            "pushforward": True}
#: How the program's path looks on the machine that trained (the card must not say it).
PROGRAM = os.path.join(os.sep, "opt", "venv", "bin", "sonarset")


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A directory holding a small store (random images: training runs, its numbers don't matter)."""
    root = tmp_path_factory.mktemp("recipes")
    s = create_store(root / "s.zarr", GRID)
    s.write_run("run_000", **make_run(24, 0, grid=GRID), chunk_frames=8)
    s.write_run("run_001", **make_run(24, 1, grid=GRID), chunk_frames=8)
    s.write_run("test_000", **make_run(24, 2, grid=GRID), split="test", chunk_frames=8)
    return root


def _train(monkeypatch, args: list[str]) -> dict:
    """Run ``sonarset train ARGS`` as typed (``sys.argv`` too, which the card records); the card."""
    monkeypatch.setattr(sys, "argv", [PROGRAM, "train", *args])
    r = CliRunner().invoke(app, ["train", *args])
    assert r.exit_code == 0, r.output
    return json.loads((Path(args[args.index("--out") + 1]) / "model.json").read_text())


def _write(path: Path, recipe: dict) -> Path:
    path.write_text(dump_recipe(recipe))
    return path


def _strings(node):
    if isinstance(node, dict):
        for v in node.values():
            yield from _strings(v)
    elif isinstance(node, list):
        for v in node:
            yield from _strings(v)
    elif isinstance(node, str):
        yield node


def _absolute_paths(card: dict) -> list[str]:
    """Every string of the card, or word of one (a command), or flag value, that is an absolute path."""
    words = [w.split("=", 1)[-1] for s in _strings(card) for w in s.split()]
    return [w for w in words if os.path.isabs(w) or re.match(r"^[A-Za-z]:[\\/]", w)]


def test_a_recipe_trains_the_run_its_flags_train(work, monkeypatch):
    store = str(work / "s.zarr")
    by_flags = _train(monkeypatch, [store, "--out", str(work / "flags"), *FLAGS])
    recipe = _write(work / "r.toml", {"store": store, "out": str(work / "recipe"), **SETTINGS})
    by_recipe = _train(monkeypatch, ["--config", str(recipe), "--out", str(work / "recipe")])
    assert by_recipe["training"]["config"] == by_flags["training"]["config"]
    assert by_recipe["training"]["recipe"] == by_flags["training"]["recipe"]
    assert by_recipe["val_loss"] == by_flags["val_loss"]  # the same steps: the same weights
    recorded = by_flags["training"]["recipe"]
    assert recorded == {**{k: v for k, v in vars(TrainConfig()).items() if k != "command"}, **SETTINGS,
                        "store": "../s.zarr", "out": "."}
    assert list(recorded) == list(RECIPE_KEYS)
    # the command as typed, with the program as `sonarset` and its paths relative to the run directory
    assert by_flags["training"]["command"] == "sonarset train ../s.zarr --out . " + " ".join(FLAGS)
    assert by_recipe["training"]["command"] == "sonarset train --config ../r.toml --out ."


def test_the_card_holds_no_path_of_this_machine(work, monkeypatch):
    init = work / "flags" / "model.safetensors"  # an absolute --init, given as --init=PATH
    flags = list(FLAGS)
    flags[flags.index("--test-samples") + 1] = "4"  # the test metrics name the store too
    card = _train(monkeypatch, [str(work / "s.zarr"), "--out", str(work / "init"), *flags, f"--init={init}"])
    text = json.dumps(card)
    assert str(work) not in text and os.path.dirname(PROGRAM) not in text
    assert _absolute_paths(card) == []
    assert card["training"]["store"] == "../s.zarr"
    assert card["training"]["recipe"]["init"] == card["training"]["config"]["init"] == "../flags/model.safetensors"
    assert "--init=../flags/model.safetensors" in card["training"]["command"]
    assert card["test"]["store"] == "../s.zarr" and card["test"]["windows"] == 4


def test_flags_given_override_the_recipe(work, monkeypatch):
    recipe = _write(work / "o.toml", {**SETTINGS, "store": str(work / "s.zarr"), "out": str(work / "nowhere"),
                                      "seed": 5, "lr": 0.002})
    card = _train(monkeypatch, ["--config", str(recipe), "--out", str(work / "override"), "--seed", "9",
                                "--no-pushforward", "--lr", "0.001"])
    config = card["training"]["config"]
    assert (config["seed"], config["pushforward"], config["lr"]) == (9, False, 0.001)
    assert (config["max_steps"], config["loss"]) == (2, "cc=1,w1=100")  # the file's, where no flag is given
    # a flag given with the default's value still overrides (given, not compared with the default)
    card = _train(monkeypatch, ["--config", str(recipe), "--out", str(work / "override-default"), "--seed", "0"])
    assert card["training"]["config"]["seed"] == 0 and card["training"]["config"]["lr"] == 0.002
    assert not (work / "nowhere").exists()


def test_the_recipe_a_card_records_trains_the_run_again(work, monkeypatch):
    card = json.loads((work / "flags" / "model.json").read_text())
    recipe = _write(work / "card-recipe.toml", card["training"]["recipe"])
    monkeypatch.chdir(work / "flags")  # the card's paths are relative to its run directory
    again = _train(monkeypatch, ["--config", str(recipe), "--out", str(work / "again")])
    assert again["training"]["recipe"] == card["training"]["recipe"]
    assert again["training"]["config"] == card["training"]["config"]
    assert again["val_loss"] == card["val_loss"]


@pytest.mark.parametrize("text, message", [
    ("max_step = 2\n", "unknown key 'max_step' (did you mean 'max_steps'?)"),
    ("max_steps = \"2\"\n", 'max_steps must be an integer, got "2" (a string)'),
    ("pushforward = 1\n", "pushforward must be true or false, got 1 (an integer)"),
    ("lr = true\n", "lr must be a number, got true (a boolean)"),
    ("max_steps = 2\nmax_steps 3\n", "not valid TOML: Expected '=' after a key in a key/value pair (at line 2, "),
    ("resume = true\n", "resume is not a recipe key"),
    ("epochs = 0\n", "epochs = 0: "),
    ("preset = \"huge\"\n", "preset = \"huge\": "),
])
def test_a_bad_recipe_is_refused_in_one_line(tmp_path, text, message):
    recipe = tmp_path / "bad.toml"
    recipe.write_text(text)
    r = CliRunner().invoke(app, ["train", "s.zarr", "--out", str(tmp_path / "run"), "--config", str(recipe)])
    assert r.exit_code == 1, r.output
    assert r.output.strip().startswith(f"error: {recipe}: {message}") and len(r.output.strip().splitlines()) == 1, \
        r.output
    assert not (tmp_path / "run").exists()


def test_store_and_out_come_from_the_recipe_or_the_command_line(tmp_path):
    r = CliRunner().invoke(app, ["train", "--out", str(tmp_path / "run")])
    assert r.exit_code == 2 and r.output.strip() == ("error: missing STORE: give it on the command line, or as store "
                                                     "in a recipe (--config)"), r.output
    recipe = _write(tmp_path / "r.toml", {"store": str(tmp_path / "absent.zarr")})
    r = CliRunner().invoke(app, ["train", "--config", str(recipe)])
    assert r.exit_code == 2 and "missing --out" in r.output, r.output
    r = CliRunner().invoke(app, ["train", "--config", str(tmp_path / "nope.toml"), "--out", "x"])
    assert r.exit_code == 1 and f"{tmp_path / 'nope.toml'}: no such recipe file" in r.output, r.output


def test_recipe_files_of_the_shipped_lineage(tmp_path, monkeypatch):
    """One file a leg of the shipped card's lineage, each from the leg before, each a valid run
    (checked as ``sonarset train`` checks it: it gets as far as opening the store)."""
    from sonarset.models.echopt.checkpoint import PRETRAINED
    from sonarset.models.echopt.losses import parse_loss

    lineage = json.loads(PRETRAINED.with_suffix(".json").read_text())["training"]["lineage"]
    legs = sorted((RECIPES / "echopt-small").glob("*.toml"))
    assert [p.name[:3] for p in legs] == [f"{i:02d}-" for i in range(1, len(lineage) + 1)]
    monkeypatch.chdir(tmp_path)
    previous = None
    for path, leg in zip(legs, lineage):
        recipe = load_recipe(path)
        config_of(recipe).check()
        parse_loss(recipe.get("loss", "mse"))
        assert recipe["out"] == f"runs/{path.stem}" and recipe["store"] in ("lab.zarr", "multi.zarr", "gpu.zarr")
        assert recipe.get("init", "") == ("" if previous is None else f"{previous}/model.safetensors")
        assert path.read_text().startswith("# ")  # what the leg did
        flags = _flags(leg["command"])
        assert {k: v for k, v in recipe.items() if k not in ("store", "out", "init")} == \
            {k: type(recipe[k])(v) for k, v in flags.items() if k not in ("out", "init", "resume")}, path
        r = CliRunner().invoke(app, ["train", "--config", str(path)])
        assert r.exit_code == 1 and f"{recipe['store']}: no such file or directory" in r.output, (path, r.output)
        previous = recipe["out"]
    for path in RECIPES.rglob("*.toml"):
        load_recipe(path)


def test_every_shipped_recipe_passes_the_commands_checks(tmp_path, monkeypatch):
    """Each recipe's settings (its network's preset included) pass every check of ``train``, which
    then stops only at its store, absent here: no recipe fails after its store is read."""
    monkeypatch.chdir(tmp_path)
    for path in sorted(RECIPES.rglob("*.toml")):
        r = CliRunner().invoke(app, ["train", "--config", str(path)])
        assert r.exit_code == 1 and "no such file or directory" in r.output, (path, r.output)


def _flags(command: str) -> dict[str, str | bool]:
    """{recipe key: value} of a command line's flags (a flag without a value: True)."""
    argv = shlex.split(command)
    flags = {}
    for i, word in enumerate(argv):
        if word.startswith("--"):
            value = argv[i + 1] if i + 1 < len(argv) and not argv[i + 1].startswith("--") else True
            flags[word[2:].replace("-", "_")] = value
    return flags


def test_the_shipped_card_names_no_path_of_a_machine():
    from sonarset.models.echopt.checkpoint import PRETRAINED

    card = json.loads(PRETRAINED.with_suffix(".json").read_text())
    assert _absolute_paths(card) == []
    assert all(leg["command"].startswith("sonarset train ") for leg in card["training"]["lineage"])


def test_portable_command():
    run = os.path.join(os.sep, "data", "runs", "a")
    store = os.path.join(os.sep, "data", "s.zarr")
    command = f"{PROGRAM} train {store} --out {run} --init={run}/../b --loss 'cc=1,w1=2' --worlds 'a b'"
    assert portable_command(command, run) == ("sonarset train ../../s.zarr --out . --init=../b --loss cc=1,w1=2 "
                                              "--worlds 'a b'")
    assert portable_command("sonarset train s3://bucket/s.zarr --out r", run) == \
        "sonarset train s3://bucket/s.zarr --out r"
    cfg = TrainConfig(init="pretrained", command="")
    assert recipe_of(cfg, "https://host/s.zarr", run, relative_to=run)["store"] == "https://host/s.zarr"
    assert recipe_of(cfg, store, run, relative_to=run)["init"] == "pretrained"


_SCALARS = st.one_of(st.text(), st.booleans(), st.integers(-2**63, 2**63 - 1),
                     st.floats(allow_nan=False), st.just(math.nan))


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.text(min_size=1), _SCALARS, max_size=6))
def test_dump_recipe_writes_toml_that_reads_back(recipe):
    back = tomllib.loads(dump_recipe(recipe, comment="a\nb"))
    assert back.keys() == recipe.keys()
    for key, value in recipe.items():
        assert type(back[key]) is type(value)
        assert back[key] == value or (value != value and back[key] != back[key])


def test_load_recipe_reads_what_dump_recipe_writes(tmp_path):
    recipe = {**recipe_of(TrainConfig(loss="cc=1,w1=100", command=""), "s.zarr", "run"), "lr": 1e-05,
              "worlds": 'lab,"quoted"\\ \t\n', "max_minutes": 46.0}
    path = _write(tmp_path / "r.toml", recipe)
    assert load_recipe(path) == recipe
    path.write_text("max_minutes = 46\n")
    assert load_recipe(path) == {"max_minutes": 46.0} and type(load_recipe(path)["max_minutes"]) is float
