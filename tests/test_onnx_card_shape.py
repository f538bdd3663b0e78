"""An ONNX graph whose output is not its card's image shape: one line naming the file, at load or
at the first run, never a NumPy broadcasting error."""

from __future__ import annotations

import json

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from sonarset.errors import SonarSetError  # noqa: E402
from sonarset.models.echopt.onnx_runtime import CARD_KEY, OnnxEchoPTPredictor  # noqa: E402

N_IN, R, A = 3, 40, 18


def transposing_graph(path, declared_output, transpose: bool = True):
    """frames (B, n_in, R, A) -> the mean frame transposed (B, A, R): the card says R x A."""
    from onnx import TensorProto, helper

    nodes = [helper.make_node("ReduceMean", ["frames"], ["mean"], axes=[1], keepdims=0),
             helper.make_node("Transpose", ["mean"], ["next_frame"], perm=[0, 2, 1] if transpose else [0, 1, 2])]
    graph = helper.make_graph(
        nodes, "wrong", [helper.make_tensor_value_info("frames", TensorProto.FLOAT, ["B", N_IN, R, A]),
                         helper.make_tensor_value_info("commands", TensorProto.FLOAT, ["B", N_IN + 1, 2])],
        [helper.make_tensor_value_info("next_frame", TensorProto.FLOAT, declared_output)])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {CARD_KEY: json.dumps({"config": {"n_in": N_IN, "n_range": R, "n_azimuth": A}})})
    onnx.save(model, path)
    return path


def test_a_declared_output_shape_unlike_the_card_is_refused_at_load(tmp_path):
    path = transposing_graph(tmp_path / "declared.onnx", ["B", A, R])
    with pytest.raises(SonarSetError, match=rf"declared.onnx: the graph's next_frame has shape Bx{A}x{R}, "
                                            rf"its card says {R}x{A}"):
        OnnxEchoPTPredictor(path)


def test_an_output_shape_unlike_the_card_is_refused_at_the_run(tmp_path):
    """A graph whose shape onnxruntime cannot infer ahead: the run's output is checked."""
    from sonarset.models.echopt.onnx_runtime import open_session

    predictor = OnnxEchoPTPredictor(transposing_graph(tmp_path / "right.onnx", ["B", R, A], transpose=False))
    predictor.path = tmp_path / "dynamic.onnx"
    predictor.session = open_session(transposing_graph(predictor.path, ["B", "H", "W"]))
    frames, commands = np.zeros((2, N_IN, R, A), np.float32), np.zeros((2, N_IN + 1, 2), np.float32)
    with pytest.raises(SonarSetError, match=rf"dynamic.onnx: the graph's next_frame came out 2x{A}x{R}"):
        predictor.predict(frames, commands)
