"""The predictor protocol and the open registry: objects checked in one line, predict-only objects
evaluated with the defaults, and outside predictors (a plugin package, a module:factory) named on
the command line."""

import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from sonarset import SonarSetError
from sonarset.cli.app import app
from sonarset.format.attrs import RobotRig
from sonarset.models import BasePredictor, Predictor
from sonarset.models.baselines import AcousticFlow, rollout
from sonarset.models.eval.evaluate import evaluate
from sonarset.models.eval.report import results_table
from sonarset.models.predictor import as_predictor
from sonarset.models.registry import available_predictors, make_predictor, model_option_spec
from sonarset.store.store import create_store
from tests.conftest import TINY, make_run

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "sonarset-plugin-example"
runner = CliRunner()


@pytest.fixture
def store(tmp_path):
    s = create_store(tmp_path / "s.zarr", TINY)
    s.write_run("test_000", **make_run(40, 2), split="test", chunk_frames=8)
    return s


class LastFrame:
    """A predict-only object: the protocol's three members and nothing else."""

    name = "last"
    n_in = 3

    def predict(self, frames, commands):
        return frames[:, -1]


def test_a_predict_only_object_is_evaluated_with_the_defaults(store):
    assert isinstance(LastFrame(), Predictor)
    res = evaluate(store, ["persistence"], predictors={"mine": LastFrame()}, horizons=(1, 3), samples=10)
    assert res.methods == ["mine", "persistence"] and res.precision == {}
    for h in (1, 3):  # chained predict: the same frames as the baseline that copies the last one
        np.testing.assert_array_equal(res.per_window["mine"][h]["cc"], res.per_window["persistence"][h]["cc"])


def test_a_predictors_own_rollout_is_used(store):
    class Oracle(BasePredictor):
        name, calls = "oracle", []

        def predict(self, frames, commands):
            raise AssertionError("a predictor with a rollout is not chained")

        def rollout(self, frames, commands, horizon):
            self.calls.append(horizon)
            return np.repeat(frames[:, -1:], horizon, axis=1)

    res = evaluate(store, [], predictors={"oracle": Oracle()}, horizons=(1, 2), samples=5)
    assert Oracle.calls == [2] and np.isfinite(res.per_window["oracle"][2]["cc"]).all()
    # the thin function of models/baselines.py: the predictor's own rollout, else predict chained
    frames, commands = np.random.default_rng(0).random((2, 3, *TINY.shape), np.float32), np.zeros((2, 5, 2), np.float32)
    shape = (2, 2, *TINY.shape)
    assert rollout(Oracle(), frames, commands, 2).shape == rollout(LastFrame(), frames, commands, 2).shape == shape
    flow = AcousticFlow(TINY, RobotRig())
    np.testing.assert_array_equal(rollout(flow, frames, commands, 2), as_predictor(flow).rollout(frames, commands, 2))


@pytest.mark.parametrize("members, says", [
    ({"name": "x", "n_in": 3}, "predictor 'mine': has no predict(frames, commands) method"),
    ({"name": "x", "n_in": 0, "predict": lambda f, c: f}, "predictor 'mine': its n_in is 0, not an int >= 1"),
    ({"name": "x", "n_in": "3", "predict": lambda f, c: f}, "its n_in is '3', not an int >= 1"),
    ({"name": "", "predict": lambda f, c: f}, "has no n_in (input frames per window, an int >= 1); its name is ''"),
    ({"name": "x", "n_in": 3, "predict": lambda f, c: f, "rollout": 5}, "its rollout is not a method"),
    ({"name": "x", "n_in": 3, "predict": lambda f, c: f, "card": "v1"}, "its card is a str, not a dict or None"),
    ({}, "predictor 'mine': it is a Bare object, not a predictor"),
])
def test_protocol_errors_are_one_line_naming_the_predictor(members, says):
    bare = type("Bare", (), {k: staticmethod(v) if callable(v) else v for k, v in members.items()})()
    with pytest.raises(SonarSetError) as exc:
        as_predictor(bare, "mine")
    assert says in str(exc.value) and "\n" not in str(exc.value)


def test_outputs_of_the_wrong_shape_are_refused_in_one_line(store):
    class Cropped(LastFrame):
        def predict(self, frames, commands):
            return frames[:, -1, :-1]

    with pytest.raises(SonarSetError, match=r"^predictor 'crop': predict returned shape \(5, 7, 6\), "
                                            r"not \(B, R, A\) = \(5, 8, 6\)$"):
        evaluate(store, [], predictors={"crop": Cropped()}, horizons=(1,), samples=5)

    class ShortRollout(LastFrame):
        name = "short"

        def rollout(self, frames, commands, horizon):
            return np.repeat(frames[:, -1:], horizon - 1, axis=1)

    with pytest.raises(SonarSetError, match=r"rollout returned shape \(5, 2, 8, 6\), not \(B, horizon, R, A\)"):
        evaluate(store, [], predictors={"short": ShortRollout()}, horizons=(3,), samples=5)


def test_a_predictor_that_writes_into_its_inputs_changes_no_other_models_windows(store):
    class Scribbler(LastFrame):
        name = "scribbler"

        def rollout(self, frames, commands, horizon):
            out = np.repeat(frames[:, -1:], horizon, axis=1).copy()
            frames *= 0  # a plugin's own bug: the windows are everyone's
            commands *= 0
            return out

    alone = evaluate(store, [], predictors={"last": LastFrame()}, horizons=(1, 2), samples=6)
    after = evaluate(store, [], predictors={"scribbler": Scribbler(), "last": LastFrame()}, horizons=(1, 2), samples=6)
    for h in (1, 2):
        np.testing.assert_array_equal(after.per_window["last"][h]["cc"], alone.per_window["last"][h]["cc"])
        np.testing.assert_array_equal(after.per_window["scribbler"][h]["cc"], alone.per_window["last"][h]["cc"])


def test_outputs_that_are_no_real_numbers_are_refused_and_out_of_range_ones_noted(store):
    class Outputs(LastFrame):
        def __init__(self, convert):
            self.convert = convert

        def predict(self, frames, commands):
            return self.convert(frames[:, -1])

    for name, convert, says in [("complex", lambda x: x + 1j, "predict returned complex64 values, not real numbers"),
                                ("text", lambda x: x.astype(str), "values, not real numbers"),
                                ("object", lambda x: x.astype(object), "object values, not real numbers")]:
        with pytest.raises(SonarSetError, match=rf"^predictor '{name}': .*{says}") as exc:
            evaluate(store, [], predictors={name: Outputs(convert)}, horizons=(1,), samples=5)
        assert "\n" not in str(exc.value)
    res = evaluate(store, [], predictors={"big": Outputs(lambda x: x * 1000 + 5), "last": LastFrame()},
                   horizons=(1, 2), samples=5)
    assert "big: 10 of its 10 forecast images hold values outside [0, 1], the energyscapes' range; they are scored " \
           "as they are" in res.notes and not any(n.startswith("last:") for n in res.notes)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an infinite forecast is undefined in the scores, not numpy's warning
        res = evaluate(store, [], predictors={"inf|nite": Outputs(lambda x: np.full_like(x, np.inf))}, horizons=(1,), samples=5)
    assert np.isnan(res.per_window["inf|nite"][1]["cc"]).all()
    assert "| inf\\|nite |" in results_table(res, with_paper=False)


def test_a_card_is_anyones_dict(store):
    class Carded(LastFrame):
        card = {"config": 3, "rig": "a robot"}

    res = evaluate(store, [], predictors={"carded": Carded()}, horizons=(1,), samples=5)
    assert any("model card has an invalid processing or rig" in n for n in res.notes)


def test_a_predictor_named_as_a_ceiling_is_refused_or_renamed(store, tmp_path, monkeypatch):
    with pytest.raises(SonarSetError, match="predictor 'ceiling': that name is the ceiling row's"):
        evaluate(store, [], predictors={"ceiling": LastFrame()}, horizons=(1,), samples=5)
    (tmp_path / "sonarset_test_ceiling.py").write_text(
        "class P:\n    name, n_in = 'observable', 3\n    def predict(self, f, c):\n        return f[:, -1]\n"
        "def make(grid, rig):\n    return P()\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    res = evaluate(store, ["flow", "sonarset_test_ceiling:make"], horizons=(1,), samples=5, ceiling=False)
    assert res.predictors == ["flow", "sonarset_test_ceiling:make"]
    assert any(c.a == "sonarset_test_ceiling:make" or c.b == "sonarset_test_ceiling:make" for c in res.comparisons)
    sys.modules.pop("sonarset_test_ceiling", None)


def test_an_error_inside_a_predictor_is_named_in_one_line(store):
    class Broken(LastFrame):
        def predict(self, frames, commands):
            return frames[:, -1] @ np.ones((3, 3))  # a plugin's own bug: shapes that do not multiply

    with pytest.raises(SonarSetError, match=r"^predictor 'broken': predict raised ValueError: matmul"):
        evaluate(store, [], predictors={"broken": Broken()}, horizons=(1,), samples=5)


def test_the_registry_lists_its_names_and_resolves_model_options():
    entries = {e.name: e.source for e in available_predictors()}
    assert entries["flow"] == "built-in" and entries["echopt:PATH"] == "built-in"
    assert entries["pretrained"] == entries["echopt:pretrained"] == "shipped checkpoint"
    p = make_predictor("flow", TINY, RobotRig())
    assert (p.name, p.label, p.any_context, p.card, p.precision) == ("flow", "flow", True, None, None)
    # a --model option: names and specs as they are, a bare path as an EchoPT checkpoint's
    assert [model_option_spec(m) for m in ("pretrained", "flow", "echopt:x", "pkg.mod:make", "runs/a", "m.onnx")] == \
        ["pretrained", "flow", "echopt:x", "pkg.mod:make", "echopt:runs/a", "echopt:m.onnx"]


def last_frame_factory(grid, rig):
    return LastFrame()


def test_plugins_are_found_by_entry_point_and_never_shadow_a_built_in(store, monkeypatch):
    from importlib.metadata import EntryPoint

    import sonarset.models.registry as registry

    points = [EntryPoint("flow", "json:dumps", registry.PLUGIN_GROUP),
              EntryPoint("last", "tests.test_plugins:last_frame_factory", registry.PLUGIN_GROUP),
              EntryPoint("broken", "no_such_module_here:make", registry.PLUGIN_GROUP)]
    monkeypatch.setattr(registry, "entry_points", lambda group: [ep for ep in points if ep.group == group])
    sources = {e.name: e.source for e in available_predictors()}
    assert sources["flow"] == "built-in" and sources["last"] == "plugin an unknown distribution"
    assert isinstance(make_predictor("flow", TINY, RobotRig()).predictor, AcousticFlow)
    assert isinstance(make_predictor("last", TINY, RobotRig()).predictor, LastFrame)
    with pytest.raises(SonarSetError, match="^predictor 'last:x': its factory .* takes nothing after ':'"):
        make_predictor("last:x", TINY, RobotRig())
    with pytest.raises(SonarSetError, match="^predictor 'broken': plugin 'broken' of an unknown distribution does "
                                            "not load .*ModuleNotFoundError"):
        make_predictor("broken", TINY, RobotRig())
    res = evaluate(store, ["flow", "last"], horizons=(1,), samples=5)
    assert res.methods == ["flow", "last"]
    assert any("plugin 'flow'" in n and "shadowed by the built-in 'flow'" in n for n in res.notes), res.notes


def test_the_protocol_loads_no_torch():
    code = "import sys, sonarset.models, sonarset.models.registry; print('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"


def test_module_factory_errors_are_one_line(store, tmp_path, monkeypatch):
    (tmp_path / "sonarset_test_broken.py").write_text("raise RuntimeError('boom at import')\n")
    # text from a predictor is printed as it is: neither markup ("[/]" was a traceback) nor emoji codes
    (tmp_path / "sonarset_test_markup.py").write_text(
        "class P:\n    name, n_in = 'p[/]:factory:', 3\n"
        "    def predict(self, f, c):\n        raise ValueError('bad [/] [red]x :factory:')\n"
        "def make(grid, rig):\n    return P()\n")
    monkeypatch.chdir(tmp_path)  # a module beside the data imports, as with python -m
    monkeypatch.setattr(sys, "path", list(sys.path))
    cases = {
        "sonarset_test_broken:make": "predictor 'sonarset_test_broken:make': module 'sonarset_test_broken' does not "
                                     "import (RuntimeError: boom at import)",
        "json:nope": "has no attribute 'nope'",
        "json:dumps": "predictor 'json:dumps': its factory json:dumps raised TypeError",
        "collections:OrderedDict": "predictor 'collections:OrderedDict': it is an OrderedDict object, not a predictor",
        "no_such_module_here:make": "unknown model 'no_such_module_here:make': no module 'no_such_module_here'",
        "magic": "name any other predictor as package.module:factory",
        "flow:2": "model 'flow:2': flow takes nothing after ':'",
        "sonarset_test_markup:make": "predict raised ValueError: bad [/] [red]x :factory:",
    }
    for spec, says in cases.items():
        r = runner.invoke(app, ["eval", store.location, "--models", spec, "--out", str(tmp_path / "o")])
        assert r.exit_code == 1 and says in r.output, (spec, r.output)
        assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    sys.modules.pop("sonarset_test_broken", None)
    sys.modules.pop("sonarset_test_markup", None)


def test_a_module_factory_takes_an_argument_after_a_second_colon(store, tmp_path, monkeypatch):
    """``module:factory:ARG`` hands ARG (a checkpoint of one's own, say: a path with its own ':'
    and '/') to a factory with an ``arg`` parameter, and is refused in one line by one without."""
    (tmp_path / "sonarset_test_arg.py").write_text(
        "class Scaled:\n    n_in = 3\n    def __init__(self, arg):\n        self.name, self.arg = 'scaled', arg\n"
        "    def predict(self, f, c):\n        return f[:, -1] * 0.5\n"
        "def make(grid, rig, arg):\n    return Scaled(arg)\n"
        "def plain(grid, rig):\n    return Scaled('none')\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    p = make_predictor("sonarset_test_arg:make:runs/a:b", TINY, RobotRig())
    assert p.predictor.arg == "runs/a:b" and p.label == "scaled"
    assert model_option_spec("sonarset_test_arg:make:runs/a") == "sonarset_test_arg:make:runs/a"
    with pytest.raises(SonarSetError, match="^predictor 'sonarset_test_arg:plain:x': its factory "
                                            "sonarset_test_arg:plain takes nothing after ':'"):
        make_predictor("sonarset_test_arg:plain:x", TINY, RobotRig())
    r = runner.invoke(app, ["eval", store.location, "--models", "flow,sonarset_test_arg:make:runs/a", "--horizons", "1",
                            "--samples", "5", "--out", str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    assert "| scaled |" in (tmp_path / "o" / "report.md").read_text()
    sys.modules.pop("sonarset_test_arg", None)


def test_an_installed_plugin_is_listed_and_evaluated(store, tmp_path):
    """The example package installed (into a folder on PYTHONPATH, so the environment is left as it
    was): ``sonarset models`` lists its entry point, eval scores it by name, by name:ARG and by
    module:factory."""
    src, site = tmp_path / "src", tmp_path / "site"
    shutil.copytree(EXAMPLE, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                    "--disable-pip-version-check", "--target", str(site), str(src)], check=True, capture_output=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))}
    script = Path(sys.executable).parent / "sonarset"  # the console script, as a user runs it
    sonarset = [str(script)] if script.exists() else [sys.executable, "-m", "sonarset.cli"]

    listed = subprocess.run([*sonarset, "models"], env=env, capture_output=True, text=True, check=True).stdout
    assert any("example-decay" in line and "plugin sonarset-plugin-example" in line for line in listed.splitlines())
    specs = ["flow", "example-decay", "sonarset_plugin_example.decay:factory", "example-decay:0.5"]
    r = subprocess.run([*sonarset, "eval", store.location, "--models", ",".join(specs), "--samples", "20",
                        "--horizons", "1,3", "--no-figures", "--out", str(tmp_path / "o")],
                       env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    results = json.loads((tmp_path / "o" / "metrics.json").read_text())["results"]
    # a second model of the same name is listed under its spec
    assert list(results) == ["flow", "example-decay", *specs[2:]]
    one_shot = {m: results[m]["1"]["nrmsd"]["mean"] for m in results}
    assert one_shot["example-decay"] == one_shot["sonarset_plugin_example.decay:factory"]
    assert len({one_shot["flow"], one_shot["example-decay"], one_shot["example-decay:0.5"]}) == 3
