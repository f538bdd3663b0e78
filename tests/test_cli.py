import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from sonarset.cli.app import app
from sonarset.format.attrs import FORMAT_VERSION
from tests.conftest import TINY, make_run

runner = CliRunner()
FIX = Path(__file__).resolve().parents[1] / "spec" / "fixtures"


def test_info_and_json(store):
    r = runner.invoke(app, ["info", store.location])
    assert r.exit_code == 0 and "run_001" in r.output and "3 complete run(s), 75 frames" in r.output
    assert "processing: raw (das, no post-processing)" in r.output and "rig: not recorded" in r.output
    r = runner.invoke(app, ["info", store.location, "--json"])
    doc = json.loads(r.output)
    assert doc["frames"] == 75 and doc["grid"]["n_range"] == 8 and doc["format_version"] == FORMAT_VERSION
    assert doc["processing"]["profile"] == "raw" and doc["rig"] is None


def test_info_shows_processing_and_rig_of_1_0_and_1_1_stores():
    r = runner.invoke(app, ["info", str(FIX / "valid" / "format_1_1.zarr")])
    assert r.exit_code == 0 and "processing: ertis (dmas3-cf, smoothing 0.0675 m x 2 deg" in r.output
    assert "rig: 0.2 s frames, sensor 0.15 m ahead of the axle, wheel base 0.3 m" in r.output
    r = runner.invoke(app, ["info", str(FIX / "valid" / "format_1_0.zarr")])
    assert "SonarSet 1.0" in r.output and "processing: raw" in r.output
    assert "(from the simulator's run provenance)" in r.output
    doc = json.loads(runner.invoke(app, ["info", str(FIX / "valid" / "format_1_0.zarr"), "--json"]).output)
    assert doc["rig"]["sensor_offset_m"] == 0.15 and doc["rig_recorded"] is False


def test_validate_exit_codes(store):
    assert runner.invoke(app, ["validate", store.location]).exit_code == 0
    r = runner.invoke(app, ["validate", str(FIX / "invalid" / "nan_images.zarr")])
    assert r.exit_code == 1 and "NaN or infinite" in r.output


def test_validate_consolidate_repairs_stale_metadata(store):
    store.write_run("late", **make_run(6, 8), consolidate=False)
    assert runner.invoke(app, ["validate", store.location]).exit_code == 1
    assert runner.invoke(app, ["validate", store.location, "--consolidate"]).exit_code == 0


def test_import_cli(tmp_path):
    src = tmp_path / "r.npz"
    np.savez(src, **make_run(8, 1), range=TINY.range_centres(), azimuth=TINY.azimuth_centres())
    r = runner.invoke(app, ["import", str(src), str(tmp_path / "o.zarr"), "--split", "test"])
    assert r.exit_code == 0, r.output
    assert runner.invoke(app, ["validate", str(tmp_path / "o.zarr")]).exit_code == 0


def test_schema_cli():
    r = runner.invoke(app, ["schema", "recording"])
    assert r.exit_code == 0 and json.loads(r.output)["title"] == "RecordingMeta"
    assert runner.invoke(app, ["schema", "nope"]).exit_code == 2


def test_bad_input_gives_one_line_and_no_traceback(tmp_path):
    """The installed console script, as a user runs it."""
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"garbage")
    for args in (["info", str(tmp_path / "missing.zarr")], ["validate", str(bad)],
                 ["import", str(bad), str(tmp_path / "o.zarr")], ["info", str(FIX / "invalid" / "unknown_major_version.zarr")]):
        res = subprocess.run([sys.executable, "-m", "sonarset.cli", *args], capture_output=True, text=True)
        assert res.returncode == 1, (args, res.stderr)
        assert "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
        assert str(Path(args[1]).name) in res.stderr
    assert not (tmp_path / "o.zarr").exists()


def test_demo_on_a_short_fresh_run(tmp_path):
    """The README's main job, on a 30 s run and 10 windows: the shipped model against the baselines,
    with both ceilings, the fade check and the report; a bad model fails before any simulation."""
    r = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "d"), "--minutes", "0.5", "--samples", "10",
                                 "--device", "cpu"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "d" / "metrics.json").read_text())
    assert list(doc["results"]) == ["persistence", "naive", "flow", "echowarp", "ceiling", "observable"]
    assert set(doc["observable"]["gap_closed_vs_flow"]) == {"persistence", "naive", "echowarp"}
    assert doc["windows"]["n"] == 10 and doc["windows"]["horizons"] == [1, 3, 5, 10]
    assert all(doc["results"]["echowarp"][h]["n"] == 10 for h in ("1", "3", "5", "10"))
    assert set(doc["fade"]) == {"persistence", "naive", "flow", "echowarp"}
    assert "| echowarp |" in (tmp_path / "d" / "report.md").read_text() and "one-shot cc: EchoWarp - flow" in r.output
    assert "AR-10: EchoWarp closes" in r.output
    bad = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "e"), "--model", str(tmp_path / "nope")])
    assert bad.exit_code == 1 and "no EchoPT checkpoint" in bad.output and not (tmp_path / "e").exists()


def test_closed_choices_are_the_librarys():
    """typer checks these choices and lists them in --help; cli/choices.py makes them from the
    library's light lists, and this says they are the lists the code that uses them checks against
    (the network's presets and priors, the simulator's PSF tables, the beamformers)."""
    import pytest

    from sonarset.cli import choices
    from sonarset.models.echopt.config import PRIORS
    from sonarset.models.echopt.precision import PRECISIONS
    from sonarset.format.attrs import Processing
    from sonarset.format.attrs import BEAMFORMERS
    from sonarset.sim.sonar import BEAMS

    values = lambda enum: {c.value for c in enum}  # noqa: E731
    assert values(choices.Prior) == set(PRIORS)
    assert values(choices.Psf) == set(BEAMS) and values(choices.Beamformer) == set(BEAMFORMERS)
    assert values(choices.Precision) == set(PRECISIONS)
    for profile in values(choices.ProcessingProfile):
        Processing.named(profile)
    with pytest.raises(ValueError, match="choose from " + ", ".join(c.value for c in choices.ProcessingProfile) + "$"):
        Processing.named("nope")
    r = runner.invoke(app, ["train", "x", "--out", "y", "--preset", "huge"])
    assert r.exit_code == 2 and "small" in r.output and "tiny" in r.output


def test_library_errors_name_the_commands_flags(store, tmp_path):
    """The library names parameters; the command line names the flag that sets one, in place of the
    parameter's name where the message opens with it, else after the message."""
    r = runner.invoke(app, ["train", store.location, "--out", str(tmp_path / "t"), "--curriculum", "2:3"])
    assert r.exit_code == 1 and "error: --curriculum '2:3': must start at step 0" in r.output, r.output
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "x").write_text("")
    r = runner.invoke(app, ["train", store.location, "--out", str(busy)])
    assert r.exit_code == 1 and "exists and is not empty" in r.output and r.output.rstrip().endswith("(--out)"), r.output
    r = runner.invoke(app, ["eval", store.location, "--models", "magic", "--out", str(tmp_path / "e")])
    assert r.exit_code == 1 and "unknown model 'magic'" in r.output and "(--models)" in r.output, r.output


def test_echowarp_on_the_options_defaults_is_noted(store, tmp_path):
    """EchoWarp with the paper EchoPT's one-step default learns one horizon: said before training
    (here refused at once, its --out taken), and not said for a recipe's ten steps."""
    from sonarset.models.echopt.train_config import TrainConfig

    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "x").write_text("")
    r = runner.invoke(app, ["train", store.location, "--model", "echowarp", "--out", str(busy)])
    assert r.exit_code == 1 and r.output.startswith("note: EchoWarp on one-step windows"), r.output
    assert TrainConfig(model="echowarp", curriculum="10").notes() == [] and TrainConfig().notes() == []


def test_a_parameter_no_option_sets_is_left_as_the_library_says_it():
    """... and a parenthesis that opens with the parameter's name opens with its flag."""
    import typer

    from sonarset.cli.common import user_errors
    from sonarset.errors import SonarSetError

    probe = typer.Typer()

    @probe.command()
    @user_errors
    def one(batch: int = typer.Option(1, "--batch"), allow_more: bool = typer.Option(False, "--allow-more")) -> None:
        if batch > 2:
            raise SonarSetError(f"batch_size {batch} is too large", parameter="batch_size")
        raise SonarSetError(f"{batch} is too few (allow_more takes it)", parameter="allow_more")

    r = CliRunner().invoke(probe, ["--batch", "3"])
    assert r.exit_code == 1 and "error: batch_size 3 is too large" in r.output and "--" not in r.output, r.output
    r = CliRunner().invoke(probe, ["--batch", "1"])
    assert r.exit_code == 1 and "error: 1 is too few (--allow-more takes it)\n" == r.output, r.output
