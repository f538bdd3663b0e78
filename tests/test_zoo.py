"""The reference methods (models/zoo/): each starts as its prior, SimVP forecasts every horizon in one
causal pass, and EchoPT's trainer trains, checkpoints, evaluates and resumes every kind."""

import json

import numpy as np
import pytest
import torch

from sonarset import SonarSetError
from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.store.store import create_store

from sonarset.models.baselines import AcousticFlow
from sonarset.models.echopt.cards import add_test_metrics
from sonarset.models.echopt.checkpoint import load_checkpoint
from sonarset.models.echopt.config import grid_and_rig
from sonarset.models.echopt.networks import build
from sonarset.models.echopt.predictor import ForecastPredictor, load_learned_predictor
from sonarset.models.echopt.train import train
from sonarset.models.echopt.train_config import TrainConfig
from sonarset.models.eval.evaluate import evaluate
from sonarset.models.zoo import REFERENCE_METHODS, ZOO
from tests.conftest import make_run

GRID = SensorGrid(range_min_m=0.5, range_max_m=3.0, n_range=40, azimuth_min_rad=-1.4, azimuth_max_rad=1.4, n_azimuth=18)
RIG = RobotRig()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    s = create_store(tmp_path_factory.mktemp("zoo") / "s.zarr", GRID)
    for i, (name, split, frames) in enumerate((("run_000", "train", 40), ("run_001", "train", 40),
                                               ("test_000", "test", 30))):
        s.write_run(name, **make_run(frames, i, grid=GRID), split=split, chunk_frames=16)
    return s


def _model(kind: str, **overrides):
    torch.manual_seed(0)
    return build(kind, "tiny", *GRID.shape, **{**grid_and_rig(GRID, RIG), **overrides}).eval()


def _window(b: int = 3, k: int = 1, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    frames = torch.rand((b, 3, *GRID.shape), generator=g)
    commands = (torch.rand((b, 3 + k, 2), generator=g) * 2 - 1) * torch.tensor([0.3, 1.0])
    return frames, commands


@pytest.mark.parametrize("kind", REFERENCE_METHODS)
@pytest.mark.parametrize("prior,inputs", [("flow", "raw"), ("flow", "aligned"), ("last", "raw")])
def test_an_untrained_model_is_its_prior(kind, prior, inputs):
    model = _model(kind, prior=prior, inputs=inputs)
    frames, commands = _window()
    with torch.no_grad():
        out = model(frames, commands)
    assert out.shape == (3, *GRID.shape)
    if prior == "last":
        assert torch.equal(out, frames[:, -1])
    else:  # the flow baseline's warp, through EchoPT's own plumbing
        flow = AcousticFlow(GRID, RIG).predict(frames.numpy(), commands.numpy())
        np.testing.assert_allclose(out.numpy(), flow, atol=1e-5)
    with pytest.raises(SonarSetError, match="built for 3 frames of 40x18"):
        model(frames[:, :, :20], commands)


@pytest.mark.parametrize("kind", REFERENCE_METHODS)
def test_without_a_prior_the_network_draws_the_image(kind):
    model = _model(kind, prior="none")
    frames, commands = _window()
    with torch.no_grad():
        out = model(frames, commands)
    assert out.shape == (3, *GRID.shape) and out.abs().sum() > 0 and not torch.allclose(out, frames[:, -1])


def test_simvp_forecasts_every_horizon_in_one_causal_pass():
    model = _model("simvp")
    assert model.max_horizon == 10
    frames, commands = _window(k=10)
    with torch.no_grad():
        # untrained: the flow baseline's own rollout
        flow = AcousticFlow(GRID, RIG)
        expected = flow.rollout(frames.numpy(), commands.numpy(), 10)
        np.testing.assert_allclose(model.forecast(frames, commands, 10).numpy(), expected, atol=1e-5)
        for p in model.parameters():  # trained-like weights: the network's own part shows
            torch.nn.init.normal_(p, std=0.3)
        one = model(frames, commands[:, :4])
        for k in (1, 3, 10):
            out = model.forecast(frames, commands[:, :3 + k], k)
            assert out.shape == (3, k, *GRID.shape)
            torch.testing.assert_close(out[:, 0], one, atol=1e-5, rtol=1e-5)
        # step j sees no later command
        later = commands.clone()
        later[:, 6:] = -later[:, 6:]
        a, b = model.forecast(frames, commands, 10), model.forecast(frames, later, 10)
        torch.testing.assert_close(a[:, :3], b[:, :3], atol=1e-5, rtol=1e-5)
        assert not torch.allclose(a[:, 3:], b[:, 3:])
    with pytest.raises(ValueError, match="1..10 steps"):
        model.forecast(frames, torch.zeros(3, 14, 2), 11)


def _cfg(kind: str, **kw) -> TrainConfig:
    base = dict(model=kind, preset="tiny", epochs=5, batch_size=8, lr=1e-3, n_val=8, eval_every=1, device="cpu",
                test_samples=0, curriculum="2", optimizer="adamw", command="test")
    return TrainConfig(**{**base, **kw})


@pytest.mark.parametrize("kind", list(ZOO))
def test_the_trainer_trains_checkpoints_evaluates_and_resumes_each_kind(store, tmp_path, kind):
    full = train(store, tmp_path / "full", _cfg(kind, max_steps=3))
    part = train(store, tmp_path / "part", _cfg(kind, max_steps=3, max_minutes=1e-9))
    assert part.steps == 1
    resumed = train(store, tmp_path / "part", _cfg(kind, max_steps=3), resume=True)
    assert [r["val_loss"] for r in resumed.history] == [r["val_loss"] for r in full.history]
    model, card = load_checkpoint(tmp_path / "full", GRID)
    assert type(model).__name__ == {"convlstm": "ConvLSTM", "simvp": "SimVP", "unet": "UNet", "echowarp": "EchoWarp"}[kind]
    assert card["model"] == kind and card["n_params"] == model.n_params()
    assert type(model.cfg).from_dict(card["config"]) == model.cfg
    # the registry's KIND:PATH, and the card's test metrics
    res = evaluate(store, ["flow", f"{kind}:{tmp_path / 'full'}"], samples=6, horizons=(1, 3))
    assert kind in res.per_window and res.precision[kind] in ("fp32", "bf16")
    test = add_test_metrics(tmp_path / "full", store, _cfg(kind, test_samples=6))
    assert test["model"] == kind and test["results"][kind]["1"]["n"] == 6 and test[f"{kind}_vs_flow"]
    assert json.loads((tmp_path / "full" / "model.json").read_text())["test"]["model"] == kind
    # --init continues a model of the same kind
    tuned = train(store, tmp_path / "tuned", _cfg(kind, max_steps=1, lr=1e-12, init=str(tmp_path / "full")))
    assert tuned.steps == 1
    after, _ = load_checkpoint(tmp_path / "tuned", GRID)
    for (name, a), b in zip(model.state_dict().items(), after.state_dict().values(), strict=True):
        assert torch.allclose(a, b, atol=1e-6), name


def test_simvp_predictor_rolls_out_in_one_pass_and_chains_beyond_its_horizon(store, tmp_path):
    train(store, tmp_path / "run", _cfg("simvp", max_steps=2))
    p = load_learned_predictor(str(tmp_path / "run"), GRID)
    assert isinstance(p, ForecastPredictor) and p.name == "simvp" and p.label == "simvp run/model"
    frames, commands = (x.numpy() for x in _window(b=5, k=12))
    out = p.rollout(frames, commands, 12)
    assert out.shape == (5, 12, *GRID.shape) and out.min() >= 0 and out.max() <= 1
    np.testing.assert_allclose(out[:, 0], p.predict(frames, commands[:, :4]), atol=1e-5)
    first = p.rollout(frames, commands[:, :13], 10)
    np.testing.assert_allclose(out[:, :10], first, atol=1e-5)
    # the last two steps: a new pass, from the first pass's last three predictions
    np.testing.assert_allclose(out[:, 10:], p.rollout(first[:, 7:], commands[:, 10:], 2), atol=1e-5)


@pytest.mark.parametrize("setting,value,message", [
    ("preset", "paper", "preset paper: EchoPT's only"),
    ("geometry_channels", 4, "geometry_channels 4: an EchoPT option"),
    ("trainable", "geometry", "trainable geometry: an EchoPT option")])
def test_echopt_options_are_refused_for_the_reference_methods(store, tmp_path, setting, value, message):
    with pytest.raises(SonarSetError, match=message) as err:
        train(store, tmp_path / "run", _cfg("unet", max_steps=1, **{setting: value}))
    assert err.value.parameter == setting and "\n" not in str(err.value)
    assert not (tmp_path / "run").exists()


def test_a_checkpoint_answers_to_its_own_kind_only(store, tmp_path):
    train(store, tmp_path / "u", _cfg("unet", max_steps=1))
    with pytest.raises(SonarSetError, match="a U-Net checkpoint, not SimVP's; name it unet:"):
        train(store, tmp_path / "s", _cfg("simvp", max_steps=1, init=str(tmp_path / "u")))
    with pytest.raises(SonarSetError, match="a U-Net checkpoint, not EchoPT's"):
        evaluate(store, [f"echopt:{tmp_path / 'u'}"], samples=2, horizons=(1,))
    # KIND:pretrained is the shipped checkpoint of that kind (trained on the default grid, not this one)
    with pytest.raises(SonarSetError, match=r"simvp-small\.safetensors: SimVP was trained on grid 200x90"):
        evaluate(store, ["simvp:pretrained"], samples=2, horizons=(1,))
    pytest.importorskip("onnxscript")
    from sonarset.models.echopt.onnx_export import export_onnx

    with pytest.raises(SonarSetError, match="a U-Net checkpoint; ONNX export is for EchoPT and EchoWarp only"):
        export_onnx(tmp_path / "u", tmp_path / "u.onnx")
    # the shipped EchoPT loads as it always has, from a card that names no kind
    shipped = load_learned_predictor("pretrained", SensorGrid.default())
    assert shipped.name == "echopt" and shipped.label == "echopt-small" and "model" not in shipped.card


def test_cat_channels_is_torch_cat_and_keeps_channels_last():
    from sonarset.models.zoo.common import cat_channels

    g = torch.Generator().manual_seed(2)
    a, b = (torch.rand((2, c, 5, 3), generator=g, dtype=torch.bfloat16) for c in (3, 4))
    last = [t.contiguous(memory_format=torch.channels_last) for t in (a, b)]
    out = cat_channels(last)
    assert torch.equal(out, torch.cat([a, b], 1)) and out.is_contiguous(memory_format=torch.channels_last)
    # any other layout: torch.cat as it is
    mixed = cat_channels([last[0], b])
    assert torch.equal(mixed, torch.cat([a, b], 1))
    # the gradient reaches each part as through torch.cat
    x = last[0].float().requires_grad_()
    cat_channels([x, last[1].float()]).sum(1).square().sum().backward()
    y = a.float().requires_grad_()
    torch.cat([y, b.float()], 1).sum(1).square().sum().backward()
    assert torch.equal(x.grad, y.grad)


def test_up_hands_its_resize_a_dense_gradient_of_the_same_values(monkeypatch):
    from sonarset.models.zoo.common import Up

    torch.manual_seed(0)
    up = Up(6, 4, 5).to(memory_format=torch.channels_last)
    g = torch.Generator().manual_seed(1)
    deep = torch.rand((2, 6, 5, 4), generator=g).contiguous(memory_format=torch.channels_last).requires_grad_()
    skip = torch.rand((2, 4, 9, 7), generator=g).contiguous(memory_format=torch.channels_last).requires_grad_()
    seen = []
    resize = torch.nn.functional.interpolate

    def spy(x, **kw):  # the resize's output, to see the gradient that reaches it
        y = resize(x, **kw)
        y.register_hook(lambda grad: seen.append(grad))
        return y

    monkeypatch.setattr(torch.nn.functional, "interpolate", spy)
    up(deep, skip).square().sum().backward()
    monkeypatch.undo()
    # the function and its gradient are those of the plain resize-concatenate-convolve
    d2, s2 = deep.detach().clone().requires_grad_(), skip.detach().clone().requires_grad_()
    conv = up.convs(torch.cat([resize(d2, size=(9, 7), mode="bilinear", align_corners=False), s2], 1))
    conv.square().sum().backward()
    assert torch.allclose(deep.grad, d2.grad, atol=1e-6) and torch.allclose(skip.grad, s2.grad, atol=1e-6)
    # and the resize's backward reads a dense channels-last gradient, not a strided slice of the concatenation's
    assert len(seen) == 1 and seen[0].is_contiguous(memory_format=torch.channels_last)


def test_a_run_trained_on_chosen_horizons_resumes_with_them_only(store, tmp_path):
    """``horizons``: EchoWarp trains on those steps of its rollout alone; the card records the
    setting and a resume with another is refused in one line."""
    cfg = _cfg("echowarp", max_steps=2, curriculum="4", horizons="1,3,5")  # 5 is beyond k: left out
    res = train(store, tmp_path / "run", cfg)
    assert res.steps == 2 and all(np.isfinite(r["val_loss"]) for r in res.history)
    _, card = load_checkpoint(tmp_path / "run", GRID)
    assert card["training"]["config"]["horizons"] == "1,3,5"
    with pytest.raises(SonarSetError, match="horizons"):
        train(store, tmp_path / "run", _cfg("echowarp", max_steps=2, curriculum="4"), resume=True)
