"""Format 1.1: a store records what its images are (processing) and the robot that made them (rig)."""

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from sonarset import SonarSetError, create_store, open_store
from sonarset.errors import InputValidationError
from sonarset.ingest.images import import_recording
from sonarset.format.attrs import FORMAT_VERSION, Processing, RobotRig
from sonarset.sim.robot import SENSOR_OFFSET, V_MAX, W_MAX, WHEEL_BASE
from sonarset.store.store import open_or_create_store
from sonarset.store.validate import validate_store
from tests.conftest import TINY, make_run

FIX = Path(__file__).resolve().parents[1] / "spec" / "fixtures"
SIM_RIG = RobotRig(frame_interval_s=0.2, sensor_offset_m=SENSOR_OFFSET, wheel_base_m=WHEEL_BASE,
                   v_max_m_s=V_MAX, omega_max_rad_s=W_MAX)


def test_a_1_0_store_reads_as_raw_with_the_simulators_rig():
    s = open_store(FIX / "valid" / "format_1_0.zarr")
    assert s.format_version == "1.0" and "processing" not in s.group.attrs["sonarset"]
    assert s.processing == Processing.raw()
    assert s.attrs.rig is None and s.rig == SIM_RIG  # derived from the runs' simulator provenance


def test_rig_is_unknown_without_simulator_provenance(tmp_path, store):
    assert store.rig is None  # conftest's store: no rig, runs without provenance
    s = create_store(tmp_path / "mixed.zarr", TINY)
    sim = {"kind": "simulator", "dt": 0.2, "sensor_offset_m": 0.15, "wheel_base_m": 0.3}
    s.write_run("a", **make_run(5), source=sim)
    assert s.rig == SIM_RIG
    s.write_run("b", **make_run(5), source={**sim, "sensor_offset_m": 0.1})  # runs disagree: unknown
    assert s.rig is None
    s.delete_run("b")
    s.write_run("c", **make_run(5), source={"kind": "import", "file": "x.npz"})
    assert s.rig is None


def test_the_current_format_round_trips(tmp_path):
    rig = RobotRig(frame_interval_s=0.1, sensor_offset_m=0.05, wheel_base_m=0.4, v_max_m_s=0.5, omega_max_rad_s=2.0)
    s = create_store(tmp_path / "s.zarr", TINY, processing=Processing.ertis(), rig=rig, frame_rate_hz=10.0)
    s.write_run("run_000", **{**make_run(6), "time": np.arange(6) * 0.1})  # a 10 Hz store has 10 Hz stamps
    doc = json.loads((tmp_path / "s.zarr" / "zarr.json").read_text())["attributes"]["sonarset"]
    assert doc["format_version"] == FORMAT_VERSION and doc["processing"]["beamformer"] == "dmas3-cf"
    assert doc["rig"]["wheel_base_m"] == 0.4
    back = open_store(tmp_path / "s.zarr")
    assert back.processing == Processing.ertis() and back.rig == rig
    assert validate_store(tmp_path / "s.zarr") == []
    # no rig given: none recorded (absent, not null)
    create_store(tmp_path / "t.zarr", TINY)
    assert "rig" not in json.loads((tmp_path / "t.zarr" / "zarr.json").read_text())["attributes"]["sonarset"]


def test_open_or_create_refuses_other_images_or_rig(tmp_path):
    loc = tmp_path / "s.zarr"
    s = open_or_create_store(loc, TINY, processing=Processing.ertis(), rig=SIM_RIG, description="sim")
    assert s.processing == Processing.ertis() and s.attrs.description == "sim"
    # the same images under another profile name, and no declaration at all, are fine
    open_or_create_store(loc, TINY, processing=Processing.ertis().model_copy(update={"profile": "mine"}), rig=SIM_RIG)
    open_or_create_store(loc, TINY)
    with pytest.raises(SonarSetError, match=r"s\.zarr: store images are ertis .* the data's are raw"):
        open_or_create_store(loc, TINY, processing=Processing.raw())
    with pytest.raises(SonarSetError, match=r"s\.zarr: store robot rig is .* wheel base 0\.3 m.* wheel base 0\.5 m"):
        open_or_create_store(loc, TINY, rig=SIM_RIG.model_copy(update={"wheel_base_m": 0.5}))


def test_1_0_store_resumes_only_with_raw_images_and_its_rig(tmp_path):
    import shutil

    loc = tmp_path / "old.zarr"
    shutil.copytree(FIX / "valid" / "format_1_0.zarr", loc)
    grid = open_store(loc).grid
    open_or_create_store(loc, grid, processing=Processing.raw(), rig=SIM_RIG)
    with pytest.raises(SonarSetError, match="store images are raw"):
        open_or_create_store(loc, grid, processing=Processing.ertis(), rig=SIM_RIG)


def test_validator_reports_bad_processing_and_rig_in_one_line(tmp_path):
    for name in ("unknown_beamformer.zarr", "bad_rig.zarr", "rig_frame_rate_mismatch.zarr"):
        problems = [str(p) for p in validate_store(FIX / "invalid" / name)]
        assert len(problems) == 1 and "\n" not in problems[0] and name in problems[0], problems


def test_later_minor_keys_inside_processing_and_rig_are_kept(tmp_path):
    s = open_store(FIX / "valid" / "future_minor.zarr")
    assert s.processing.model_extra == {"new_stage": "added in 1.7"}
    assert not s.processing.same_images(Processing.raw())  # an unknown stage: not the same images
    assert s.rig.model_extra == {"wheel_count": 2}


# ---- importer ---------------------------------------------------------------------------------

def _recording(tmp_path, name="rec", **meta):
    src = tmp_path / f"{name}.npz"
    np.savez(src, **make_run(8, 1), range=TINY.range_centres(), azimuth=TINY.azimuth_centres())
    src.with_suffix(".json").write_text(json.dumps(meta))
    return src


def test_import_records_processing_and_rig(tmp_path):
    rig = SIM_RIG.model_dump()
    import_recording(_recording(tmp_path, processing=Processing.ertis().model_dump(), rig=rig), tmp_path / "a.zarr")
    a = open_store(tmp_path / "a.zarr")
    assert a.processing == Processing.ertis() and a.rig == SIM_RIG
    # appending: what the sidecar declares must match the store
    with pytest.raises(SonarSetError, match="a.zarr: store images are ertis"):
        import_recording(_recording(tmp_path, "r2", processing={"profile": "raw"}), tmp_path / "a.zarr")
    import_recording(_recording(tmp_path, "r3"), tmp_path / "a.zarr")  # declares nothing: appended
    # nothing declared in a new store: processing 'unknown', rig unknown
    import_recording(_recording(tmp_path, "r4"), tmp_path / "b.zarr")
    b = open_store(tmp_path / "b.zarr")
    assert b.processing.profile == "unknown" and b.rig is None
    assert validate_store(tmp_path / "b.zarr") == []


def test_a_named_profile_in_a_sidecar_is_that_profiles_settings(tmp_path):
    """{"profile": "ertis"} is the ertis images, not ertis's name on the per-key defaults' images;
    a setting given overrides the profile's, as import-raw's --beamformer does."""
    import_recording(_recording(tmp_path, processing={"profile": "ertis"}), tmp_path / "a.zarr")
    assert open_store(tmp_path / "a.zarr").processing == Processing.ertis()
    import_recording(_recording(tmp_path, processing={"profile": "ertis", "beamformer": "das"}), tmp_path / "b.zarr")
    assert open_store(tmp_path / "b.zarr").processing == Processing.ertis().model_copy(update={"beamformer": "das"})


@pytest.mark.parametrize("meta,expect", [
    ({"processing": {"beamformer": "mvdr"}}, "metadata.processing.beamformer: Input should be 'das' or 'dmas3-cf'"),
    ({"processing": {"smoothing_rang_m": 0.1}}, "metadata.processing: Value error, unknown key(s) smoothing_rang_m"),
    ({"rig": {"wheel_base_m": -1}}, "metadata.rig.wheel_base_m: Input should be greater than 0"),
])
def test_import_refuses_bad_processing_or_rig_in_one_line(tmp_path, meta, expect):
    src = _recording(tmp_path, **meta)
    with pytest.raises(InputValidationError) as info:
        import_recording(src, tmp_path / "o.zarr")
    assert info.value.problems == [expect] and str(src) in str(info.value)
    assert not (tmp_path / "o.zarr").exists()


# ---- models: cards and the evaluation's notes -------------------------------------------------

@pytest.fixture
def ertis_model(tmp_path):
    """A tiny EchoPT whose card says it was trained on 'ertis' images with the simulator's rig."""
    pytest.importorskip("torch")
    from sonarset.models.echopt.checkpoint import save_checkpoint
    from sonarset.models.echopt.config import make_config
    from sonarset.models.echopt.model import EchoPT

    model = EchoPT(make_config("tiny", *TINY.shape, patch=(4, 3)))
    return save_checkpoint(tmp_path / "m" / "echopt-tiny", model, {
        "grid": TINY.model_dump(), "preset": "tiny", "processing": Processing.ertis().model_dump(mode="json"),
        "rig": SIM_RIG.model_dump(mode="json")})


def test_eval_notes_a_model_trained_on_other_images(store, ertis_model, tmp_path):
    from sonarset.models.eval.report import write_report
    from sonarset.models.eval.evaluate import evaluate

    res = evaluate(store, ["persistence", f"echopt:{ertis_model}"], horizons=(1,), samples=5)
    assert res.notes[0].startswith("note: the store records no robot rig")
    assert res.notes[1] == (
        "note: echopt-tiny was trained on 'ertis' images (dmas3-cf, smoothing 0.0675 m x 2 deg, 1.5 x azimuth "
        "mean removed, -60 dB floor over 60 dB); this store's images are 'raw' (das, no post-processing): "
        "scores are not comparable to its training")
    write_report(res, tmp_path / "out", figures=False)
    report = (tmp_path / "out" / "report.md").read_text()
    assert "> note: echopt-tiny was trained on 'ertis' images" in report and "> note: the store records no robot rig" in report
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["notes"] == res.notes


def test_eval_is_quiet_when_model_and_store_agree(tmp_path, ertis_model):
    from sonarset.models.eval.evaluate import evaluate

    s = create_store(tmp_path / "e.zarr", TINY, processing=Processing.ertis(), rig=SIM_RIG)
    s.write_run("test_000", **make_run(12), split="test")
    res = evaluate(s, ["flow", f"echopt:{ertis_model}"], horizons=(1,), samples=5)
    assert res.notes == []


def test_old_cards_mean_raw_images():
    from sonarset.models.echopt.cards import card_processing, card_rig, training_notices

    card = {"format": "echopt-card/1", "preset": "small", "config": {"residual": True}}  # before format 1.1
    assert "processing" not in card and card_processing(card) == Processing.raw() and card_rig(card) is None
    assert training_notices("echopt-small", card, Processing.raw(), SIM_RIG) == []
    note, = training_notices("echopt-small", card, Processing(profile="unknown"))
    assert "unknown processing: scores may not be comparable" in note


def test_eval_cli_prints_the_notes(store, ertis_model, tmp_path):
    from sonarset.cli.app import app

    r = CliRunner().invoke(app, ["eval", store.location, "--models", f"naive,echopt:{ertis_model}", "--samples", "5",
                                 "--horizons", "1", "--out", str(tmp_path / "o"), "--no-figures"])
    assert r.exit_code == 0, r.output
    assert "note: echopt-tiny was trained on 'ertis' images" in r.output and "records no robot rig" in r.output
