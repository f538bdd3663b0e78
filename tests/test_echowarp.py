"""EchoWarp (models/echowarp/): untrained it is the composite flow (one warp of the last frame along
the composed motion, the older frames registered as EchoPT's aligned inputs), every horizon comes
from one causal pass, and its corrections move echoes through the warp."""

import numpy as np
import pytest
import torch

from sonarset.format.attrs import RobotRig, SensorGrid

from sonarset.models.baselines import AcousticFlow
from sonarset.models.echopt.config import ConfigError, grid_and_rig
from sonarset.models.echopt.networks import build
from sonarset.models.echopt.predictor import ForecastPredictor

GRID = SensorGrid(range_min_m=0.5, range_max_m=3.0, n_range=40, azimuth_min_rad=-1.4, azimuth_max_rad=1.4, n_azimuth=18)
RIG = RobotRig()


def _model(preset: str = "tiny", **overrides):
    torch.manual_seed(0)
    return build("echowarp", preset, *GRID.shape, **{**grid_and_rig(GRID, RIG), **overrides}).eval()


def _window(b: int = 3, k: int = 4, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    frames = torch.rand((b, 3, *GRID.shape), generator=g)
    commands = (torch.rand((b, 3 + k, 2), generator=g) * 2 - 1) * torch.tensor([0.3, 1.0])
    return frames, commands


def _trained_like(model):
    for p in model.parameters():
        torch.nn.init.normal_(p, std=0.3)
    return model


def test_untrained_it_is_the_composite_flow():
    model = _model()
    frames, commands = _window(k=4)
    with torch.no_grad():
        out = model.forecast(frames, commands, 4)
        # one step: the flow baseline's warp exactly
        flow = AcousticFlow(GRID, RIG).predict(frames.numpy(), commands[:, :4].numpy())
        np.testing.assert_allclose(out[:, 0].numpy(), flow, atol=1e-5)
        # h steps: the last frame sampled once where the chain of h one-step sources puts each pixel
        for h in (2, 4):
            points = model._centres()
            for t in range(3 + h - 1, 2, -1):
                points = model._source(points, commands[:, t])
            np.testing.assert_allclose(out[:, h - 1].numpy(), model._sample(frames[:, -1], *points).numpy(), atol=1e-4)
        # the older frames, registered to the predicted pose, are EchoPT's aligned inputs
        ir, ia, _ = model.sources(commands[:, :4], 3, (1,))
        registered = model.sample(frames, ir[:, 0], ia[:, 0])
        np.testing.assert_allclose(registered.numpy(), model.align(frames, commands[:, :4]).numpy(), atol=1e-4)


def test_every_horizon_in_one_causal_pass():
    model = _trained_like(_model())
    frames, commands = _window(k=4)
    with torch.no_grad():
        one = model(frames, commands[:, :4])
        assert one.shape == (3, *GRID.shape)
        for k in (1, 2, 4):
            out = model.forecast(frames, commands[:, :3 + k], k)
            assert out.shape == (3, k, *GRID.shape)
            torch.testing.assert_close(out[:, 0], one, atol=1e-5, rtol=1e-5)
        later = commands.clone()
        later[:, 5:] = -later[:, 5:]
        a, b = model.forecast(frames, commands, 4), model.forecast(frames, later, 4)
        torch.testing.assert_close(a[:, :2], b[:, :2], atol=1e-5, rtol=1e-5)  # step j sees no later command
        assert not torch.allclose(a[:, 2:], b[:, 2:])
    with pytest.raises(ValueError, match="1..4 steps"):
        model.forecast(frames, torch.zeros(3, 8, 2), 5)


def test_the_warp_correction_moves_an_echo_without_spreading_it():
    """A head that asks every pixel to sample one range bin further out moves a point echo one bin
    nearer, whole: the correction acts through the warp, not as an intensity residual."""
    model = _model()
    frames = torch.zeros(1, 3, *GRID.shape)
    frames[0, -1, 20, 9] = 1.0
    commands = torch.zeros(1, 4, 2)  # standing still: the composite flow is the last frame
    with torch.no_grad():
        model.head.bias[0] = float(np.arctanh(1 / model.cfg.max_shift))  # +1 range pixel
        out = model(frames, commands)
    assert out[0, 19, 9].item() == pytest.approx(1.0, abs=1e-4) and out.sum().item() == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("patch", [2, 3])
def test_in_patches_every_convolution_runs_coarser_and_each_pixel_keeps_its_place(patch):
    """``patch`` p folds each p x p patch of the inputs into channels (the grid padded to whole
    patches) and unfolds the head's outputs: untrained it is still the composite flow, every
    convolution reads the patches' grid or a coarser one, and folding and unfolding put each pixel's
    values back where they were."""
    model = _model(patch=patch)
    frames, commands = _window(k=3)
    with torch.no_grad():
        torch.testing.assert_close(model.forecast(frames, commands, 3), _model().forecast(frames, commands, 3))
    coarse = (-(-GRID.shape[0] // patch), -(-GRID.shape[1] // patch))
    g = torch.Generator().manual_seed(5)
    x = torch.rand((2, 5, *GRID.shape), generator=g).contiguous(memory_format=torch.channels_last)
    folded = model.folded(x)
    assert folded.shape == (2, 5 * patch ** 2, *coarse)
    assert torch.equal(folded[:, (1 * patch + 0) * 5 + 2, 3, 1], x[:, 2, 3 * patch + 1, patch])  # pixel (1, 0) of patch (3, 1)
    assert torch.equal(model.unfolded(folded, *GRID.shape), x)
    with pytest.raises(ConfigError, match="patch must be at most 16 pixels, got 17"):
        _model(patch=17)
    sizes = []
    hooks = [m.register_forward_hook(lambda m, i, o: sizes.append(tuple(i[0].shape[-2:])))
             for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        model.forecast(frames, commands, 1)
    for h in hooks:
        h.remove()
    assert sizes and all(r <= coarse[0] and a <= coarse[1] for r, a in sizes)


@pytest.mark.parametrize("patch", [1, 2])
def test_gradients_reach_every_part(patch):
    model = _trained_like(_model(patch=patch)).train()
    frames, commands = _window(k=2)
    model.forecast(frames, commands, 2).square().mean().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())


def test_its_full_resolution_layer_is_the_resize_then_concatenate_it_stands_for():
    model = _trained_like(_model())
    g = torch.Generator().manual_seed(3)
    y = torch.rand((2, model.cfg.channels[0], GRID.shape[0] // 2, (GRID.shape[1] + 1) // 2), generator=g)
    x = torch.rand((2, model.full[0][0].in_channels - y.shape[1], *GRID.shape), generator=g)
    resized = torch.nn.functional.interpolate(y, size=GRID.shape, mode="bilinear", align_corners=False)
    with torch.no_grad():
        expected = model.full(torch.cat([resized, x], 1))
        assert torch.allclose(model.full_resolution(y, x), expected, atol=1e-5)


@pytest.mark.parametrize("setting,value", [("prior", "last"), ("prior", "none"), ("inputs", "raw")])
def test_it_refuses_another_prior_or_inputs(setting, value):
    with pytest.raises(ConfigError, match=setting):
        _model(**{setting: value})


def test_its_predictor_forecasts_in_one_pass_and_chains_beyond_its_horizon():
    model = _trained_like(_model())
    predictor = ForecastPredictor(model, {"model": "echowarp"}, GRID, precision="fp32")
    frames, commands = _window(b=2, k=6)
    out = predictor.rollout(frames.numpy(), commands.numpy(), 6)
    assert out.shape == (2, 6, *GRID.shape) and np.all((out >= 0) & (out <= 1))
    with torch.no_grad():
        first = model.forecast(frames, commands[:, :7], 4).clamp(0, 1).numpy()
    np.testing.assert_allclose(out[:, :4], first, atol=1e-5)


def test_it_forecasts_chosen_horizons_alone_with_the_images_of_its_whole_forecast():
    from sonarset.models.echopt.predictor import DirectForecastPredictor
    from sonarset.models.predictor import as_predictor

    model = _trained_like(_model())  # tiny: max_horizon 4
    frames, commands = _window(b=3, k=6)
    with torch.no_grad():  # the same images, to the rounding of a batch of another size
        whole = model.forecast(frames, commands[:, :7], 4)
        torch.testing.assert_close(model.forecast_at(frames, commands[:, :7], (1, 3, 4)), whole[:, [0, 2, 3]],
                                   rtol=0, atol=1e-5)
        torch.testing.assert_close(model.forecast_at(frames, commands[:, :5], (2,)), whole[:, [1]], rtol=0, atol=1e-5)
        for bad in ((3, 1), (0, 2), (2, 2), (5,)):
            with pytest.raises(ValueError):
                model.forecast_at(frames, commands, bad)
    checked = as_predictor(DirectForecastPredictor(model, {"model": "echowarp"}, GRID, precision="fp32"))
    assert checked.forecasts_directly
    f, c = frames.numpy(), commands.numpy()
    np.testing.assert_allclose(checked.forecast_at(f, c, (1, 4)), checked.rollout(f, c, 4)[:, [0, 3]], atol=1e-5)
    # beyond its horizon a forecast chains blocks: those steps come from the rollout
    np.testing.assert_array_equal(checked.forecast_at(f, c, (2, 6)), checked.rollout(f, c, 6)[:, [1, 5]])


@pytest.mark.parametrize("outside,patch", [("zeros", 1), ("border", 2)])  # each setting once
def test_it_exports_to_onnx_and_runs_in_onnxruntime(tmp_path, outside, patch):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    import onnx

    from sonarset import SonarSetError
    from sonarset.models.echopt.checkpoint import save_checkpoint
    from sonarset.models.echopt.onnx_export import PARITY_TOLERANCE, export_onnx, random_windows
    from sonarset.models.echopt.onnx_runtime import OnnxEchoPTPredictor
    from sonarset.models.predictor import chain_rollout
    from sonarset.models.registry import make_predictor

    model = _trained_like(_model(outside=outside, patch=patch))
    for p in model.parameters():
        p.data *= 0.1
    card = {"preset": "tiny", "grid": GRID.model_dump(), "rig": RIG.model_dump(mode="json")}
    ckpt = save_checkpoint(tmp_path / "run" / "model.safetensors", model, card)
    e = export_onnx(f"echowarp:{tmp_path / 'run'}", tmp_path / "warp.onnx")
    assert e.kind == "echowarp" and e.max_abs_diff is not None and e.max_abs_diff <= PARITY_TOLERANCE
    # the warp's grid is stacked in the graph: written into slices it is ScatterElements, 1.37x slower
    assert "ScatterElements" not in {node.op_type for node in onnx.load(e.path).graph.node}
    torch_pred = make_predictor(f"echowarp:{ckpt}", GRID, RIG, precision="fp32")
    assert torch_pred.predictor.model.cfg.outside == outside
    onnx_pred = make_predictor(f"echowarp:{e.path}", GRID, RIG)
    assert onnx_pred.name == "echowarp"
    most = model.max_horizon
    frames, commands = (t.numpy() for t in random_windows(model, 5, seed=3, steps=most + 2))
    one = commands[:, :model.cfg.n_in + 1]
    np.testing.assert_allclose(onnx_pred.predict(frames, one), torch_pred.predict(frames, one), atol=1e-4)
    # the graph forecasts each horizon from the measured frames, as torch does: not chained next frames
    assert onnx_pred.forecasts_directly and not onnx_pred.chains
    for horizon in (most, most + 2):  # beyond max_horizon both chain blocks
        direct = onnx_pred.rollout(frames, commands, horizon)
        np.testing.assert_allclose(direct, torch_pred.rollout(frames, commands, horizon), atol=PARITY_TOLERANCE)
    chained = chain_rollout(onnx_pred.predict, frames, commands, most)
    assert np.abs(chained - direct[:, :most]).max() > 1e-2
    np.testing.assert_allclose(onnx_pred.forecast_at(frames, commands, (2, most)), direct[:, [1, most - 1]],
                               atol=PARITY_TOLERANCE)
    np.testing.assert_array_equal(onnx_pred.forecast_at(frames, commands, (1, most + 2)), direct[:, [0, most + 1]])
    with pytest.raises(SonarSetError, match="horizons must be increasing"):
        onnx_pred.forecast_at(frames, commands, (3, 1))
    with pytest.raises(SonarSetError, match="need 5 commands for horizon 2"):
        onnx_pred.forecast_at(frames, commands[:, :4], (2,))
    with pytest.raises(SonarSetError, match="an ONNX export of echowarp, not of echopt"):
        make_predictor(f"echopt:{e.path}", GRID, RIG)
    with pytest.raises(SonarSetError, match="load it with load_onnx_predictor"):
        OnnxEchoPTPredictor(e.path)


def test_a_next_frame_graph_of_echowarp_loads_and_says_it_chains(tmp_path, monkeypatch):
    """An EchoWarp exported as a next frame's graph (before its graph took the horizons, or the
    ablation's max_horizon 1, whose rollout chains anyway) runs as one, and a multi-horizon one's
    label says its forecasts chain."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    import sonarset.models.echopt.onnx_export as onnx_export
    from sonarset.models.echopt.checkpoint import save_checkpoint
    from sonarset.models.echopt.onnx_runtime import OnnxEchoPTPredictor
    from sonarset.models.registry import make_predictor

    assert not onnx_export.exports_a_forecast(_model(max_horizon=1))
    model = _trained_like(_model())
    ckpt = save_checkpoint(tmp_path / "run" / "model.safetensors", model, {"preset": "tiny", "grid": GRID.model_dump()})
    monkeypatch.setattr(onnx_export, "exports_a_forecast", lambda m: False)  # as exported before
    e = onnx_export.export_onnx(f"echowarp:{ckpt}", tmp_path / "old.onnx")
    old = make_predictor(f"echowarp:{e.path}", GRID, RIG)
    assert isinstance(old.predictor, OnnxEchoPTPredictor) and old.chains and "chained: export it again" in old.label
    frames, commands = (t.numpy() for t in onnx_export.random_windows(model, 3, seed=4))
    torch_pred = make_predictor(f"echowarp:{ckpt}", GRID, RIG, precision="fp32")
    np.testing.assert_allclose(old.predict(frames, commands), torch_pred.predict(frames, commands),
                               atol=onnx_export.PARITY_TOLERANCE)


@pytest.mark.parametrize("switch", ["max_shift", "older_frames"])
def test_each_part_switches_off_for_the_ablation(switch):
    full, ablated = _model(), _model(**{switch: 0})
    frames, commands = _window(k=2)
    with torch.no_grad():
        torch.testing.assert_close(ablated.forecast(frames, commands, 2), full.forecast(frames, commands, 2))
        _trained_like(ablated)
        out = ablated.forecast(frames, commands, 2)
        channel = 0 if switch == "max_shift" else 2  # the warp's correction, or the first older frame's gate
        ablated.head.weight[channel] += 1.0
        torch.testing.assert_close(ablated.forecast(frames, commands, 2), out)  # that output is unused


def test_outside_the_view_it_reads_the_edge_or_nothing():
    """``outside``: where a pixel's source lies outside the view, the warp reads the edge's value
    (border, legs 1-9) or nothing (zeros), for the last frame and the registered older ones alike;
    inside the view both read the same. A card without the setting is a border model."""
    from types import SimpleNamespace

    from sonarset.models.echopt.card_images import card_processing
    from sonarset.models.echopt.train_model import init_from
    from sonarset.models.echowarp.model import EchoWarpConfig

    border, zeros = _model(), _model(outside="zeros")
    frames = torch.zeros(1, 3, *GRID.shape)
    frames[0, :, 10:20, [0, -1]] = 1.0  # echoes along both edges of the view
    commands = torch.tensor([[[0.0, 0.0]] * 3 + [[0.0, 1.0]] * 4])  # a turn: new azimuths enter at an edge
    with torch.no_grad():
        a, b = border.forecast(frames, commands, 4)[0].numpy(), zeros.forecast(frames, commands, 4)[0].numpy()
    ir, ia = border.sources(commands, 3, (1, 2, 3, 4))[:2]
    ir, ia = ir[0, :, -1].numpy(), ia[0, :, -1].numpy()  # (4, R, A): each pixel's source in the last frame
    outside = (ia < 0) | (ia > GRID.shape[1] - 1)
    along = outside & (ir > 11) & (ir < 18)  # sourced beyond the edge, beside the echo
    assert along[-1].sum() >= 8
    beyond = (ia <= -1) | (ia >= GRID.shape[1])  # past the bilinear blend with the edge's pixel
    assert (a[along] > 0.99).all() and (b[beyond] == 0).all() and (along & beyond).any()
    inside = (ia > 1) & (ia < GRID.shape[1] - 2) & (ir > 1) & (ir < GRID.shape[0] - 2)
    np.testing.assert_allclose(a[inside], b[inside], atol=1e-6)
    with pytest.raises(ConfigError, match="outside must be one of"):
        _model(outside="reflect")
    old = {k: v for k, v in zeros.cfg.to_dict().items() if k != "outside"}
    assert EchoWarpConfig.from_dict(old).outside == "border"
    # a fine-tune may change it: the same weights, read through the other sampling
    trained = _trained_like(_model())
    card = {"processing": None}
    init_from(zeros, "leg", trained, card, SimpleNamespace(processing=card_processing(card)))
    assert all(torch.equal(p, q) for p, q in zip(zeros.parameters(), trained.parameters()))


def test_its_inputs_are_cast_once_to_autocasts_dtype_with_the_same_values():
    model = _trained_like(_model())
    frames, commands = _window(k=2)
    captured = {}
    features = model.features

    def spy(*args):
        captured["x"] = features(*args)
        return captured["x"]

    model.features = spy
    with torch.no_grad():
        plain = model.forecast(frames, commands, 2)
        x32 = captured["x"]
        with torch.autocast("cpu", dtype=torch.bfloat16):
            model.forecast(frames, commands, 2)
    assert x32.dtype == torch.float32 and captured["x"].dtype == torch.bfloat16
    assert captured["x"].is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(captured["x"], x32.to(torch.bfloat16))  # the cast every convolution made of it before
    assert plain.dtype == torch.float32


def test_its_forecast_is_the_sum_of_its_parts():
    model = _trained_like(_model())
    frames, commands = _window(b=2, k=3)
    with torch.no_grad():
        parts = model.parts(frames, commands, 3)
        assert set(parts) == {"source", "warp", "older", "composite", "shift"}
        assert parts["shift"].shape == (2, 3, 2, *GRID.shape)
        assert torch.equal(model.forecast(frames, commands, 3), parts["source"] + parts["warp"] + parts["older"])
        # each window's and horizon's terms in their place: the first horizon's are the one-step pass's
        one = model.parts(frames, commands[:, :4], 1)
        for name, v in parts.items():
            torch.testing.assert_close(v[:, :1], one[name], atol=1e-5, rtol=1e-5)
        # the corrected warp is the last frame sampled where the correction moves each source pixel
        ir, ia, _ = model.sources(commands, 3, (1, 2, 3))
        shift = parts["shift"]
        for h in range(3):
            expected = model.sample(frames[:, -1:], ir[:, h, -1:] + shift[:, h, :1], ia[:, h, -1:] + shift[:, h, 1:2])[:, 0]
            torch.testing.assert_close(parts["warp"][:, h], expected, atol=1e-6, rtol=0)
        # the composite part is the untrained model's whole forecast: the last frame warped once
        plain = _model().forecast(frames, commands, 3)
        torch.testing.assert_close(parts["composite"], plain, atol=1e-6, rtol=0)
        # without the correction the warp is the composite one, and the terms still sum to the forecast
        bare = _trained_like(_model(max_shift=0, older_frames=0))
        p0 = bare.parts(frames, commands, 3)
        assert set(p0) == {"source", "warp", "composite"} and torch.equal(p0["warp"], p0["composite"])
        assert torch.equal(bare.forecast(frames, commands, 3), p0["source"] + p0["warp"])


def test_a_fine_tune_grows_it_wider_with_the_same_function():
    """``init`` of a narrower EchoWarp than the run's preset widens its U-Net (Net2WiderNet): the
    wider model forecasts what the narrow one did; the copied channels part ways in training (their
    gradients differ); a narrower or differently deep U-Net is refused."""
    from types import SimpleNamespace

    from sonarset.errors import SonarSetError
    from sonarset.models.echopt.card_images import card_processing
    from sonarset.models.echopt.train_model import init_from

    narrow = _trained_like(_model())
    wide = _model(channels=(7, 13))
    card = {"processing": None}
    store = SimpleNamespace(processing=card_processing(card))
    init_from(wide, "leg", narrow, card, store)
    frames, commands = _window(k=4)
    with torch.no_grad():
        a, b = narrow.forecast(frames, commands, 4), wide.forecast(frames, commands, 4)
    assert a.abs().max() > 0.1 and (a - b).abs().max() < 1e-5 * a.abs().max()
    # channel 4 of the first layer is a copy of one of its first 4, which it no longer follows once trained
    first = wide.down[0][0][0].weight
    twin = next(c for c in range(4) if torch.equal(first[4], first[c]))
    wide.forecast(frames, commands, 4).square().sum().backward()
    assert not torch.allclose(first.grad[4], first.grad[twin])
    for channels in ((3, 8), (4, 8, 16)):
        with pytest.raises(SonarSetError, match="another network"):
            init_from(_model(channels=channels), "leg", narrow, card, store)
    # three levels: each Up reads its own level's skip
    deep = _trained_like(_model(channels=(4, 8, 16)))
    deeper = _model(channels=(6, 11, 20))
    init_from(deeper, "leg", deep, card, store)
    with torch.no_grad():
        a, b = deep.forecast(frames, commands, 4), deeper.forecast(frames, commands, 4)
    assert a.abs().max() > 0.1 and (a - b).abs().max() < 1e-5 * a.abs().max()


def test_its_sampling_grid_is_the_stacked_grid_values_and_gradients(monkeypatch):
    import sonarset.models.echowarp.model as echowarp_model
    from sonarset.models.flow import sampling_grid

    g = torch.Generator().manual_seed(3)
    x, y = torch.rand((4, 5, 6), generator=g), torch.rand((1, 5, 6), generator=g).expand(4, 5, 6)
    assert torch.equal(sampling_grid(x, y), torch.stack([x, y], -1))
    model = _trained_like(_model())
    frames, commands = _window(k=3)
    runs = []
    for grid in (sampling_grid, lambda a, b: torch.stack([a, b], -1)):
        monkeypatch.setattr(echowarp_model, "sampling_grid", grid)
        model.zero_grad()
        pred = model.forecast(frames, commands, 3)
        (pred * torch.linspace(0, 1, pred.numel()).view_as(pred)).sum().backward()
        runs.append([pred.detach(), *(p.grad.clone() for p in model.parameters())])
    assert all(torch.equal(a, b) for a, b in zip(*runs))


def test_a_narrow_grid_trains_in_bf16_as_in_fp32():
    """Its U-Net levels 1 or 2 pixels wide: strided convolutions of such inputs are fp32 under bf16
    autocast (oneDNN's bf16 kernel returned up to 1e34 there on an AMX CPU, in some passes)."""
    torch.manual_seed(0)
    narrow = GRID.model_copy(update={"n_range": 64, "n_azimuth": 3})
    model = build("echowarp", "tiny", 64, 3, **grid_and_rig(narrow, RIG)).to(memory_format=torch.channels_last)
    for p in model.parameters():
        torch.nn.init.normal_(p, std=0.1)
    g = torch.Generator().manual_seed(1)
    frames = torch.rand((4, 3, 64, 3), generator=g).contiguous(memory_format=torch.channels_last)
    commands = (torch.rand((4, 7, 2), generator=g) * 2 - 1) * torch.tensor([0.3, 1.0])
    with torch.no_grad():
        exact = model.forecast(frames, commands, 4)
    for _ in range(10):  # the kernel read memory it had not written: some passes were right
        with torch.autocast("cpu", dtype=torch.bfloat16):
            half = model.forecast(frames, commands, 4)
        assert torch.isfinite(half).all() and (half.float() - exact).abs().max() < 0.05
