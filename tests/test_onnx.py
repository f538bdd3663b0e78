"""EchoPT as ONNX: export, parity with torch, and ``echopt:PATH.onnx`` through onnxruntime."""

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")

from sonarset import GridMismatchError, SonarSetError, open_store  # noqa: E402
from sonarset.cli.app import app  # noqa: E402
from sonarset.models.echopt.checkpoint import save_checkpoint  # noqa: E402
from sonarset.models.echopt.config import grid_and_rig, make_config  # noqa: E402
from sonarset.models.echopt.model import EchoPT  # noqa: E402
from sonarset.models.eval.evaluate import evaluate  # noqa: E402
from sonarset.models.echopt.onnx_export import PARITY_TOLERANCE, export_onnx, random_windows  # noqa: E402
from sonarset.models.echopt.onnx_runtime import CARD_KEY, OnnxEchoPTPredictor, open_session, read_onnx_card  # noqa: E402
from sonarset.models.registry import make_predictor  # noqa: E402
from sonarset.format.attrs import SensorGrid  # noqa: E402
from sonarset.sim import generate  # noqa: E402

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)
runner = CliRunner()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A tiny flow-prior checkpoint whose correction is not zero (an untrained one is its prior
    alone), its ONNX export, and a store on its grid."""
    root = tmp_path_factory.mktemp("onnx")
    generate(root / "s.zarr", runs=0, test_runs=1, minutes=0.5, seed=5, workers=1, grid=GRID)
    store = open_store(root / "s.zarr")
    torch.manual_seed(0)
    model = EchoPT(make_config("tiny", *GRID.shape, **grid_and_rig(store.grid, store.rig)))
    torch.nn.init.normal_(model.head[-1].weight, std=0.05)
    card = {"format": "echopt-card/1", "preset": "tiny", "grid": store.grid.model_dump(),
            "processing": store.processing.model_dump(mode="json"), "rig": store.rig.model_dump(mode="json"),
            "training": {"precision": "fp32"}}
    ckpt = save_checkpoint(root / "tiny" / "model.safetensors", model, card)
    e = export_onnx(ckpt, root / "tiny.onnx")
    return store, ckpt, e


def test_export_matches_torch_with_a_dynamic_batch(exported):
    store, ckpt, e = exported
    assert e.path.is_file() and e.bytes == e.path.stat().st_size
    assert e.max_abs_diff is not None and e.max_abs_diff <= PARITY_TOLERANCE
    torch_pred = make_predictor(f"echopt:{ckpt}", store.grid, store.rig, precision="fp32")
    onnx_pred = make_predictor(f"echopt:{e.path}", store.grid, store.rig)
    assert isinstance(onnx_pred.predictor, OnnxEchoPTPredictor) and onnx_pred.n_in == 3  # the registry's checked view
    for batch in (1, 7, 70):  # one graph for every batch size
        frames, commands = (t.numpy() for t in random_windows(torch_pred.predictor.model, batch, seed=batch))
        got, ref = onnx_pred.predict(frames, commands), torch_pred.predict(frames, commands)
        assert got.shape == (batch, *GRID.shape)
        assert np.abs(got - ref).max() <= 1e-4
        assert np.abs(ref - frames[:, -1]).max() > 1e-3  # the correction is in play, not only the prior


def test_the_card_travels_in_the_onnx_metadata(exported):
    store, ckpt, e = exported
    card = read_onnx_card(e.path)
    assert card["preset"] == "tiny" and card["config"]["prior"] == "flow"
    assert SensorGrid.model_validate(card["grid"]).matches(store.grid)
    assert card["processing"]["profile"] == store.processing.profile
    meta = open_session(e.path).get_modelmeta().custom_metadata_map
    assert {CARD_KEY, "echopt.grid", "echopt.processing", "echopt.rig", "echopt.inputs", "echopt.trained_precision"} <= set(meta)
    assert json.loads(meta["echopt.grid"])["n_range"] == 50


def test_eval_scores_torch_and_onnxruntime_alike(exported):
    store, ckpt, e = exported
    res = evaluate(store, ["flow", f"echopt:{ckpt}", f"echopt:{e.path}"], horizons=(1, 3), samples=20, precision="fp32")
    torch_name, onnx_name = [m for m in res.methods if m.startswith("echopt")]
    assert onnx_name == f"echopt {e.path.name}"
    for h in (1, 3):
        for metric in ("cc", "nrmsd"):
            a, b = res.per_window[torch_name][h][metric], res.per_window[onnx_name][h][metric]
            assert np.abs(a - b).max() <= 1e-3, (h, metric)
    assert res.precision[onnx_name] == "fp32"


def test_export_and_eval_from_the_command_line(exported, tmp_path):
    store, ckpt, _ = exported
    out = tmp_path / "cli.onnx"
    r = runner.invoke(app, ["export-onnx", str(ckpt), str(out)])
    assert r.exit_code == 0, r.output
    assert "onnxruntime matches torch" in r.output and out.is_file()
    r = runner.invoke(app, ["eval", str(store.location), "--models", f"flow,echopt:{out}", "--samples", "8",
                            "--horizons", "1,2", "--out", str(tmp_path / "ev"), "--no-figures"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "ev" / "metrics.json").read_text())["results"]["echopt"]["1"]["n"] == 8


def test_bad_onnx_inputs_are_one_line_errors(exported, tmp_path):
    store, ckpt, e = exported
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a protobuf at all")
    for spec, message in ((garbage, "not a readable ONNX model"), (tmp_path / "missing.onnx", "no ONNX model here")):
        r = runner.invoke(app, ["eval", str(store.location), "--models", f"echopt:{spec}", "--samples", "4",
                                "--out", str(tmp_path / "x"), "--no-figures"])
        assert r.exit_code == 1 and message in r.output and str(spec) in r.output, r.output
        assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1
    other = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=100, azimuth_min_rad=-1.5, azimuth_max_rad=1.5,
                       n_azimuth=30)
    with pytest.raises(GridMismatchError, match="trained on grid"):
        OnnxEchoPTPredictor(e.path, other)
    r = runner.invoke(app, ["export-onnx", str(ckpt), str(tmp_path / "model.bin")])
    assert r.exit_code == 1 and "must be an .onnx file" in r.output
    with pytest.raises(SonarSetError, match="no EchoPT checkpoint"):
        export_onnx(tmp_path / "nothing", tmp_path / "n.onnx")
    assert not (tmp_path / "n.onnx").exists()


@pytest.mark.parametrize("geometry_channels", [0, 4])
def test_an_aligned_model_exports_with_its_warps_in_the_graph(exported, tmp_path, geometry_channels):
    """inputs="aligned" warps every input frame inside the graph (chained grid samples), and the
    geometry branch computes its per-pixel inputs there: the export matches torch within the parity
    tolerance."""
    store = exported[0]
    torch.manual_seed(1)
    model = EchoPT(make_config("tiny", *GRID.shape, inputs="aligned", geometry_channels=geometry_channels,
                               **grid_and_rig(store.grid, store.rig)))
    torch.nn.init.normal_(model.head[-1].weight, std=0.05)
    if geometry_channels:
        torch.nn.init.normal_(model.geo_weights[-1].weight, std=0.05)
    card = {"format": "echopt-card/1", "preset": "tiny", "grid": store.grid.model_dump(),
            "processing": store.processing.model_dump(mode="json"), "rig": store.rig.model_dump(mode="json"),
            "training": {"precision": "fp32"}}
    e = export_onnx(save_checkpoint(tmp_path / "al" / "model.safetensors", model, card), tmp_path / "al.onnx")
    assert e.max_abs_diff is not None and e.max_abs_diff <= PARITY_TOLERANCE
    assert read_onnx_card(tmp_path / "al.onnx")["config"]["inputs"] == "aligned"
