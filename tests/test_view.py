"""sonarset view: the recording Rerun's own tools read back (rerun rrd verify / print)."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from collections import Counter

import pytest
from typer.testing import CliRunner

pytest.importorskip("rerun")

from sonarset import open_store  # noqa: E402
from sonarset.cli.app import app  # noqa: E402
from sonarset.format.attrs import SensorGrid  # noqa: E402
from sonarset.models.view import record_run  # noqa: E402

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from sonarset.sim import generate

    where = tmp_path_factory.mktemp("view") / "sim.zarr"
    generate(where, runs=0, test_runs=1, minutes=0.3, seed=2, grid=GRID, workers=1)
    return open_store(where)


def rerun_tool(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rerun", "rrd", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


def rows_per_entity(path) -> Counter:
    """Rows of every entity, summed over the chunks ``rerun rrd print`` lists."""
    rows: Counter = Counter()
    for m in re.finditer(r"with (\d+) rows .*? - (/\S+) - data columns", rerun_tool("print", path).stdout):
        rows[m[2]] += int(m[1])
    return rows


def test_a_recording_rerun_verifies_with_every_frame_and_the_predictions(sim, tmp_path):
    out = record_run(sim, "test_000", tmp_path / "v.rrd", models=["naive", "flow"], horizon=3, block=32)
    verified = rerun_tool("verify", out)
    assert verified.returncode == 0, verified.stderr
    rows = rows_per_entity(out)
    n = sim.run("test_000").n_frames
    for entity in ("/sonar/image", "/sonar/fan", "/commands/v", "/commands/omega", "/map/robot", "/map/fov",
                   "/signal/snr_db", "/robot/slip"):
        assert rows[entity] == n, (entity, rows)
    for method in ("naive", "flow"):  # every frame with 3 frames of context 3 steps before it
        assert rows[f"/predictions/{method}/image"] == rows[f"/predictions/{method}/error"] == n - 5
    assert rows["/map/world/walls"] + rows["/map/world/circles"] >= 1 and rows["/map/path"] == 1


def test_view_cli_records_a_frame_range_and_says_how_to_open_it(sim, tmp_path):
    out = tmp_path / "part.rrd"
    res = CliRunner().invoke(app, ["view", sim.location, "--model", "naive", "--horizon", "2", "--frames", "10:40",
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "open it with: rerun" in res.output
    rows = rows_per_entity(out)
    assert rows["/sonar/image"] == 30 and rows["/predictions/naive/image"] == 30
    bad = CliRunner().invoke(app, ["view", sim.location, "--frames", "ten", "--out", str(tmp_path / "x.rrd")])
    assert bad.exit_code == 1 and "--frames must be A:B" in bad.output
    missing = CliRunner().invoke(app, ["view", sim.location, "--run", "nope", "--out", str(tmp_path / "y.rrd")])
    assert missing.exit_code == 1 and "no complete run 'nope'" in missing.output


def test_view_refuses_outputs_it_cannot_write_in_one_line(sim, tmp_path):
    import os

    folder = tmp_path / "a_folder.rrd"
    folder.mkdir()
    fifo = tmp_path / "pipe.rrd"
    os.mkfifo(fifo)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    cases = [(folder, "is a folder"), (fifo, "is a FIFO"), (a_file / "x.rrd", "cannot write the recording there")]
    if os.geteuid() != 0:  # root writes into a read-only folder
        cases.append((locked / "x.rrd", "cannot write the recording there (Permission denied)"))
    try:
        for target, problem in cases:
            res = CliRunner().invoke(app, ["view", sim.location, "--frames", "0:3", "--out", str(target)])
            assert res.exit_code == 1 and f"{target}: {problem}" in res.output, res.output
            assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1, res.output
    finally:
        locked.chmod(0o700)
    deep = tmp_path / "new" / "folder" / "x.rrd"  # a missing parent is made, as a user expects
    res = CliRunner().invoke(app, ["view", sim.location, "--frames", "0:3", "--out", str(deep)])
    assert res.exit_code == 0 and deep.is_file(), res.output


def test_a_failing_recording_leaves_the_previous_one_and_no_leftovers(sim, tmp_path, monkeypatch):
    import sonarset.models.view as view

    out = record_run(sim, "test_000", tmp_path / "v.rrd", frames=slice(0, 5))
    good = out.read_bytes()

    def broken(*args, **kwargs):
        raise RuntimeError("the model broke")

    monkeypatch.setattr(view, "_predict", broken)
    with pytest.raises(RuntimeError, match="the model broke"):
        record_run(sim, "test_000", out, models=["naive"], frames=slice(0, 40), block=8)
    assert out.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.rrd"]


def test_a_killed_recorders_leftover_is_removed_by_the_next(sim, tmp_path):
    import socket

    host = "".join(c if c.isalnum() or c == "-" else "_" for c in socket.gethostname())[:40]
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    leftover = tmp_path / f".v.rrd.{host}-{dead}-0.tmp"
    leftover.write_bytes(b"half")
    record_run(sim, "test_000", tmp_path / "v.rrd", frames=slice(0, 3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.rrd"]


def test_two_models_of_one_name_are_refused_not_merged(sim, tmp_path, monkeypatch):
    """A model named like a built-in and the built-in itself would be one entity of the recording:
    refused in one line, as eval refuses them."""
    (tmp_path / "sonarset_test_named_flow.py").write_text(
        "class P:\n    name, n_in = 'flow', 3\n    def predict(self, f, c):\n        return f[:, -1]\n"
        "def make(grid, rig):\n    return P()\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    out = tmp_path / "v.rrd"
    res = CliRunner().invoke(app, ["view", sim.location, "--model", "sonarset_test_named_flow:make", "--model", "flow",
                                   "--frames", "0:8", "--out", str(out)])
    sys.modules.pop("sonarset_test_named_flow", None)
    said = "model 'flow': another model ('flow') would be logged as the same entity"
    assert res.exit_code == 1 and said in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1 and not out.exists()


def test_a_model_named_with_spaces_and_slashes_is_one_entity(sim, tmp_path, monkeypatch):
    """A predictor's name is the user's: a '/' would open sub-entities, a space warns in Rerun."""
    (tmp_path / "sonarset_test_odd_name.py").write_text(
        "class P:\n    name, n_in = 'my model/v2', 3\n    def predict(self, f, c):\n        return f[:, -1]\n"
        "def make(grid, rig):\n    return P()\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [str(tmp_path), *sys.path])
    try:
        out = record_run(sim, "test_000", tmp_path / "v.rrd", models=["sonarset_test_odd_name:make"],
                         frames=slice(0, 8))
    finally:
        sys.modules.pop("sonarset_test_odd_name", None)
    rows = rows_per_entity(out)
    assert rows["/predictions/my_model_v2/image"] == rows["/predictions/my_model_v2/error"] == 8 - 3
