"""EchoPT: architecture, training, resume, checkpoints."""

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from sonarset import GridMismatchError, SonarSetError, open_store
from sonarset.cli.app import app
from sonarset.models.echopt.checkpoint import load_checkpoint, save_checkpoint
from sonarset.models.echopt.config import make_config
from sonarset.models.echopt.model import EchoPT
from sonarset.models.eval.evaluate import evaluate
from sonarset.models.echopt.train import train
from sonarset.models.echopt.train_config import TrainConfig
from sonarset.format.attrs import SensorGrid
from sonarset.sim import generate

TINY_GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                       azimuth_max_rad=math.pi / 2, n_azimuth=30)


@pytest.fixture(scope="module")
def tiny_store(tmp_path_factory):
    path = tmp_path_factory.mktemp("echopt") / "tiny.zarr"
    generate(path, runs=2, test_runs=1, minutes=0.5, seed=3, workers=1, grid=TINY_GRID)
    return open_store(path)


def test_paper_preset_matches_the_paper():
    m = EchoPT(make_config("paper"))
    assert m.n_params() == pytest.approx(9.0e6, rel=0.10)
    assert m.n_params("blocks") == pytest.approx(7.8e6, rel=0.10)
    cfg = m.cfg
    assert (cfg.d_embed, cfg.d_model, cfg.n_heads, cfg.d_ff, cfg.n_layers) == (376, 384, 6, 500, 8)
    assert cfg.grid_tokens == (8, 18)
    with torch.no_grad():
        y = m(torch.rand(2, 3, 200, 90), torch.rand(2, 4, 2))
    assert y.shape == (2, 200, 90)


def test_small_preset_shapes():
    m = EchoPT(make_config("small"))
    assert 0.3e6 < m.n_params() < 2e6
    with torch.no_grad():
        assert m(torch.rand(3, 3, 200, 90), torch.rand(3, 4, 2)).shape == (3, 200, 90)


def test_grid_must_divide_into_patches():
    with pytest.raises(GridMismatchError, match="not divisible by the 25x5 patch"):
        make_config("small", n_range=210, n_azimuth=90)
    make_config("small", n_range=100, n_azimuth=45)  # any multiple works


def test_tiny_model_overfits_a_handful_of_windows(tiny_store):
    from sonarset.windows import FrameBank, WindowIndex, gather

    torch.manual_seed(0)
    bank = FrameBank.from_store(tiny_store, split="train", image_dtype=np.float32)
    b = gather(bank, WindowIndex.build(bank, 3, 1), np.arange(0, 80, 10))
    f, c, t = (torch.from_numpy(np.ascontiguousarray(x)) for x in (b.frames, b.commands, b.targets[:, 0]))
    model = EchoPT(make_config("tiny", *TINY_GRID.shape))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(300):  # 10x lower by about step 170 (Xeon VM, 2026-12-07); 39x by 300
        loss = torch.nn.functional.mse_loss(model(f, c), t)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


def _cfg(**kw):
    base = dict(preset="tiny", epochs=3, batch_size=16, lr=1e-3, n_val=20, eval_every=3, device="cpu",
                test_samples=0, command="test")
    return TrainConfig(**{**base, **kw})


def test_resume_equals_uninterrupted(tiny_store, tmp_path):
    full = train(tiny_store, tmp_path / "full", _cfg(max_steps=9))
    part = train(tiny_store, tmp_path / "part", _cfg(max_steps=9, max_minutes=1e-9))  # stops at once
    assert part.steps == 1
    resumed = train(tiny_store, tmp_path / "part", _cfg(max_steps=9), resume=True)
    assert resumed.steps == 9
    a = [(r["step"], r["val_loss"]) for r in full.history if r["step"] % 3 == 0]
    b = [(r["step"], r["val_loss"]) for r in resumed.history if r["step"] % 3 == 0]
    assert a == b  # same losses, bit for bit, on CPU
    wa, _ = load_checkpoint(tmp_path / "full", TINY_GRID)
    wb, _ = load_checkpoint(tmp_path / "part", TINY_GRID)
    for (ka, va), (kb, vb) in zip(wa.state_dict().items(), wb.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)
    with pytest.raises(SonarSetError, match="exists and is not empty"):
        train(tiny_store, tmp_path / "full", _cfg(max_steps=9))
    with pytest.raises(SonarSetError, match="resume with lr") as refused:
        train(tiny_store, tmp_path / "full", _cfg(max_steps=9, lr=5e-4), resume=True)
    assert refused.value.parameter == "lr"


def test_checkpoint_is_safetensors_with_a_card(tmp_path):
    from safetensors import safe_open

    model = EchoPT(make_config("tiny", *TINY_GRID.shape))
    path = save_checkpoint(tmp_path / "m", model, {"grid": TINY_GRID.model_dump(), "preset": "tiny"})
    assert path.suffix == ".safetensors" and sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "m.safetensors"]
    with safe_open(str(path), framework="pt") as f:  # a plain safetensors file: no pickle inside
        assert "pos" in f.keys()
    card = json.loads((tmp_path / "m.json").read_text())
    assert card["config"]["d_embed"] == 24 and card["n_params"] == model.n_params()
    loaded, _ = load_checkpoint(path, TINY_GRID)
    for a, b in zip(model.state_dict().values(), loaded.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(GridMismatchError, match="trained on grid 50x30"):
        load_checkpoint(path, SensorGrid.default())
    (tmp_path / "bad.safetensors").write_bytes(b"\x80\x04not safetensors")
    (tmp_path / "bad.json").write_text((tmp_path / "m.json").read_text())
    with pytest.raises(SonarSetError, match="cannot load weights"):
        load_checkpoint(tmp_path / "bad", TINY_GRID)
    for v in model.state_dict().values():  # a diverged training: weights that are NaN
        if v.is_floating_point():
            v.fill_(float("nan"))
    nan = save_checkpoint(tmp_path / "nan", model, {"grid": TINY_GRID.model_dump(), "preset": "tiny"})
    with pytest.raises(SonarSetError, match="weight tensors hold NaN or infinite values"):
        load_checkpoint(nan, TINY_GRID)


@pytest.mark.parametrize("field,value,message", [
    ("dt", 0, "dt"), ("dt", float("nan"), "dt"), ("n_heads", 0, "n_heads"), ("patch", [0, 5], "patch"),
    ("n_range", 0, "n_range"), ("d_embed", -8, "d_embed"), ("d_embed", 10 ** 9, "d_embed"),
    ("n_layers", 10 ** 6, "n_layers"), ("prior", "magic", "prior"), ("kernel", [3], "kernel"),
    ("range_edges", [5.0, 0.5], "range_edges"), ("n_heads", 7, "heads")])
def test_impossible_model_cards_are_refused_with_the_card_named(tiny_store, tmp_path, field, value, message):
    """A card is data from a file: settings no network can have fail at load, in one line, before
    torch builds anything (1e6 layers took 98 s and ended in a traceback)."""
    model = EchoPT(make_config("tiny", *TINY_GRID.shape))
    path = save_checkpoint(tmp_path / "m", model, {"grid": TINY_GRID.model_dump(), "preset": "tiny"})
    card = json.loads((tmp_path / "m.json").read_text())
    card["config"][field] = value
    (tmp_path / "m.json").write_text(json.dumps(card))
    with pytest.raises(SonarSetError, match=message) as err:
        load_checkpoint(path, TINY_GRID)
    assert "m.json" in str(err.value) and "\n" not in str(err.value)
    if field == "dt":  # and the command line says the same, in one line, exit 1
        r = CliRunner().invoke(app, ["eval", tiny_store.location, "--models", f"echopt:{path}", "--horizons", "1",
                                     "--samples", "2", "--no-figures", "--out", str(tmp_path / "ev")])
        assert r.exit_code == 1 and "m.json" in r.output and "Traceback" not in r.output, r.output


def test_train_and_eval_cli(tiny_store, tmp_path):
    r = CliRunner().invoke(app, ["train", tiny_store.location, "--preset", "tiny", "--out", str(tmp_path / "run"),
                                 "--max-steps", "4", "--eval-every", "2", "--n-val", "20", "--batch-size", "8",
                                 "--device", "cpu", "--test-samples", "30"])
    assert r.exit_code == 0, r.output
    card = json.loads((tmp_path / "run" / "model.json").read_text())
    assert card["test"]["results"]["echopt"]["1"]["n"] == 30 and card["training"]["runs"] == ["run_000", "run_001"]
    # the card records what the model knows: the training store's images and robot
    assert card["processing"] == tiny_store.processing.model_dump(mode="json")
    assert card["rig"] == (tiny_store.rig.model_dump(mode="json") if tiny_store.rig else None)
    r = CliRunner().invoke(app, ["eval", tiny_store.location, "--models", f"flow,echopt:{tmp_path / 'run'}",
                                 "--samples", "20", "--horizons", "1,3", "--out", str(tmp_path / "ev"), "--no-figures"])
    assert r.exit_code == 0, r.output
    assert "echopt" in json.loads((tmp_path / "ev" / "metrics.json").read_text())["results"]
    # a model trained on another grid is refused, in one line
    r = CliRunner().invoke(app, ["eval", tiny_store.location, "--models", "echopt:pretrained", "--samples", "5",
                                 "--out", str(tmp_path / "ev2")])
    assert r.exit_code == 1 and "EchoPT was trained on grid 200x90" in r.output and "retrain on this grid" in r.output


class _Killed(Exception):
    pass


def _final_weights(path):
    from safetensors.torch import load_file

    return load_file(str(path / "state.safetensors"))  # weights and optimizer moments


def test_killed_at_any_write_phase_resumes_to_the_uninterrupted_result(tiny_store, tmp_path):
    """A kill after each write of a checkpoint (between the best weights and their card, after the
    card, after the state, after the metrics), the first and the last time it happens: --resume
    ends with the weights, optimizer state, best model and metrics of an uninterrupted run."""
    import sonarset.models.echopt.train as tr

    cfg = _cfg(max_steps=6, eval_every=2, curriculum="0:1,2:2", context_noise=0.02, step_weights="harmonic")
    phases: list[str] = []
    tr._AFTER_WRITE = phases.append
    try:
        full = train(tiny_store, tmp_path / "full", cfg)
    finally:
        tr._AFTER_WRITE = None
    ref = _final_weights(tmp_path / "full")
    best_ref = load_checkpoint(tmp_path / "full", TINY_GRID)
    for phase in ("best-weights", "best", "state", "metrics"):
        assert phases.count(phase) >= 1, phases
        for nth in sorted({1, phases.count(phase)}):  # the first and the last time it happens
            run = tmp_path / f"{phase}-{nth}"
            seen: list[str] = []

            def kill(p, phase=phase, nth=nth, seen=seen):
                seen.append(p)
                if seen.count(phase) == nth:
                    raise _Killed(p)

            tr._AFTER_WRITE = kill
            try:
                with pytest.raises(_Killed):
                    train(tiny_store, run, cfg)
            finally:
                tr._AFTER_WRITE = None
            with pytest.raises(SonarSetError, match="exists and is not empty"):
                train(tiny_store, run, cfg)  # a restart without --resume never overwrites it
            assert train(tiny_store, run, cfg, resume=True).steps == 6
            got = _final_weights(run)
            assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref), (phase, nth)
            best = load_checkpoint(run, TINY_GRID)
            assert (best[1]["steps"], best[1]["val_loss"]) == (best_ref[1]["steps"], best_ref[1]["val_loss"])
            assert all(torch.equal(x, y) for x, y in zip(best_ref[0].state_dict().values(), best[0].state_dict().values()))
            steps = [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()]
            assert steps == [r["step"] for r in full.history], (phase, nth)  # no step repeated or lost


def test_rollout_training_options_and_priors(tiny_store, tmp_path):
    from sonarset.models.baselines import AcousticFlow
    from sonarset.models.echopt.config import grid_and_rig

    # an untrained flow-prior model is exactly the flow baseline, with the store's rig
    model = EchoPT(make_config("tiny", *TINY_GRID.shape, **grid_and_rig(TINY_GRID, tiny_store.rig))).eval()
    rng = np.random.default_rng(0)
    f = rng.random((4, 3, *TINY_GRID.shape)).astype(np.float32)
    c = np.stack([rng.uniform(-0.3, 0.3, (4, 4)), rng.uniform(-1, 1, (4, 4))], -1).astype(np.float32)
    flow = AcousticFlow(TINY_GRID, tiny_store.rig)
    with torch.no_grad():
        np.testing.assert_allclose(model(torch.from_numpy(f), torch.from_numpy(c)).numpy(), flow.predict(f, c), atol=1e-6)
    # rollout, pushforward and a weighted loss train and record what they did
    res = train(tiny_store, tmp_path / "ro", _cfg(max_steps=4, curriculum="0:1,2:3", pushforward=True,
                                                 loss="mse=1,gdl=0.5,cc=0.1,w1=1,energy=0.5", prior="last",
                                                 val_horizon=2))
    assert [r["rollout_k"] for r in res.history] == [1, 3, 3, 3][: len(res.history)] or res.history[-1]["rollout_k"] == 3
    _, card = load_checkpoint(tmp_path / "ro", TINY_GRID)
    assert card["config"]["prior"] == "last" and card["val_horizon"] == 2
    assert card["training"]["config"]["curriculum"] == "0:1,2:3"
    assert card["training"]["config"]["loss"] == "mse=1,gdl=0.5,cc=0.1,w1=1,energy=0.5"
    assert all(np.isfinite(r["train_loss"]) for r in res.history)
    # the capped NRMSD term compares each step with the flow baseline's own rollout, whatever the prior
    from sonarset.models.baselines import rollout
    from sonarset.models.echopt.losses import rollout_losses
    c5 = np.concatenate([c, c[:, -1:]], 1)
    drawn = []
    rollout_losses(model, torch.from_numpy(f), torch.from_numpy(c5), torch.rand(4, 2, *TINY_GRID.shape),
                   {"nrmsd_capped": 1.0}, flow=lambda last, cmd: drawn.append(model.flow_prior(last, cmd)) or drawn[-1])
    np.testing.assert_allclose(torch.stack(drawn, 1).detach().numpy(), rollout(flow, f, c5, 2), atol=1e-5)
    res = train(tiny_store, tmp_path / "capped", _cfg(max_steps=2, curriculum="2", loss="cc=1,nrmsd_capped=1,echo=1",
                                                     prior="last", val_horizon=2))
    assert all(np.isfinite(r["train_loss"]) and np.isfinite(r["val_loss"]) for r in res.history)
    for bad, msg in ((dict(curriculum="2:3"), "start at step 0"), (dict(loss="mse,fancy"), "unknown term"),
                     (dict(prior="magic"), "prior must be one of"),
                     (dict(step_weights="cubic"), "step_weights must be one of")):
        with pytest.raises(SonarSetError, match=msg) as refused:
            train(tiny_store, tmp_path / "bad", _cfg(max_steps=2, **bad))
        assert refused.value.parameter == next(iter(bad))


def test_init_fine_tunes_from_a_checkpoint_and_refuses_another_network(tiny_store, tmp_path):
    base = train(tiny_store, tmp_path / "base", _cfg(max_steps=3))
    assert base.steps == 3
    start, _ = load_checkpoint(tmp_path / "base", TINY_GRID)
    # zero steps of fine-tuning leave the weights as they were: --init loads them all
    tuned = train(tiny_store, tmp_path / "tuned", _cfg(max_steps=1, lr=1e-12, init=str(tmp_path / "base")))
    assert tuned.steps == 1
    after, card = load_checkpoint(tmp_path / "tuned", TINY_GRID)
    for (k, a), (_, b) in zip(start.state_dict().items(), after.state_dict().items(), strict=True):
        assert torch.allclose(a, b, atol=1e-6), k
    # the card names no path of this machine: init relative to the run directory
    assert card["training"]["config"]["init"] == "../base"
    # init may name its checkpoint as --models does (kind:RUN); the kind must be the one trained
    named = train(tiny_store, tmp_path / "named", _cfg(max_steps=1, lr=1e-12, init=f"echopt:{tmp_path / 'base'}"))
    assert load_checkpoint(named.out_dir, TINY_GRID)[1]["training"]["config"]["init"] == "echopt:../base"
    with pytest.raises(SonarSetError, match="a unet checkpoint, but this run trains model echopt; set model unet") as e:
        train(tiny_store, tmp_path / "kind", _cfg(max_steps=1, init=f"unet:{tmp_path / 'base'}"))
    assert e.value.parameter == "init"
    with pytest.raises(SonarSetError, match="another network.*prior"):
        train(tiny_store, tmp_path / "other", _cfg(max_steps=1, prior="last", init=str(tmp_path / "base")))
    with pytest.raises(SonarSetError, match="no EchoPT checkpoint"):
        train(tiny_store, tmp_path / "missing", _cfg(max_steps=1, init=str(tmp_path / "nowhere")))


def test_bf16_training_records_its_precision_and_tracks_fp32(tiny_store, tmp_path):
    """The same steps in fp32 and in bf16 autocast: both train, the card says which, and the bf16
    run's validation loss stays close to the fp32 run's (BENCHMARKS.md: within 2% on the paper's data)."""
    runs = {p: train(tiny_store, tmp_path / p, _cfg(max_steps=12, precision=p, optimizer="adamw"))
            for p in ("fp32", "bf16")}
    for p, res in runs.items():
        card = load_checkpoint(res.out_dir, TINY_GRID)[1]
        assert card["training"]["precision"] == p and card["training"]["config"]["precision"] == p
        assert res.history[-1]["val_loss"] < res.history[0]["val_loss"]  # it learnt something
    fp32, bf16 = (runs[p].best_val_loss for p in ("fp32", "bf16"))
    assert abs(bf16 - fp32) / fp32 < 0.05
    with pytest.raises(SonarSetError, match="precision must be one of"):
        train(tiny_store, tmp_path / "bad", _cfg(max_steps=1, precision="fp8"))


def test_train_on_chosen_worlds_with_a_longer_context(tiny_store, tmp_path):
    """--worlds picks the runs and the card names their families; --n-in 5 builds a 5-frame
    model that eval runs beside the baselines on 5-frame windows."""
    res = train(tiny_store, tmp_path / "ctx", _cfg(max_steps=3, worlds="lab", n_in=5))
    card = json.loads((res.out_dir / "model.json").read_text())
    assert card["training"]["worlds"] == {"lab": 2} and card["config"]["n_in"] == 5
    ev = evaluate(tiny_store, ["flow", f"echopt:{res.out_dir / 'model.safetensors'}"], horizons=(1, 2), samples=20)
    assert ev.n_in == 5 and np.isfinite(ev.per_window["echopt"][2]["cc"]).all()
    with pytest.raises(SonarSetError, match="no complete runs of world orchard in split 'train'"):
        train(tiny_store, tmp_path / "none", _cfg(max_steps=3, worlds="orchard"))


def test_aligned_inputs_register_a_reflector_at_the_predicted_pose():
    """A reflector seen from three poses along the window's commands: aligned, each frame shows it
    where the frame to predict will (within a bin), with the sensor ahead of the axle; the last
    aligned frame is the flow prior, and an untrained aligned model is exactly that prior."""
    from sonarset.models.flow import arc_motion

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=100, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=45)
    cfg = make_config("tiny", *grid.shape, range_edges=(0.5, 5.0), azimuth_edges=(-math.pi / 2, math.pi / 2),
                      dt=0.2, sensor_offset=0.15, inputs="aligned")
    model = EchoPT(cfg).eval()
    commands = np.array([[0.0, 0.0], [0.3, 0.8], [0.25, 0.6], [0.3, -0.4]])  # command k: frame k-1 -> k
    # robot poses (x, y, yaw) of frames 0..3 (3: the frame to predict), integrated along each arc
    poses = [np.zeros(3)]
    for v, w in commands[1:]:
        c, s, dx, dy = (float(a[0]) for a in arc_motion(np, np.array([v]), np.array([w]), cfg.dt))
        x, y, yaw = poses[-1]
        poses.append(np.array([x + dx * math.cos(yaw) - dy * math.sin(yaw),
                               y + dx * math.sin(yaw) + dy * math.cos(yaw), yaw + math.atan2(s, c)]))
    reflector = np.array([2.4, 0.9])

    def seen_from(pose):
        x, y, yaw = pose
        sx, sy = x + cfg.sensor_offset * math.cos(yaw), y + cfg.sensor_offset * math.sin(yaw)
        dx, dy = reflector[0] - sx, reflector[1] - sy
        return math.hypot(dx, dy), math.atan2(dy, dx) - yaw

    rr, tt = np.meshgrid(grid.range_centres(), grid.azimuth_centres(), indexing="ij")
    frames = np.stack([np.exp(-(((rr - r) / 0.06) ** 2 + ((tt - th) / math.radians(4)) ** 2) / 2)
                       for r, th in map(seen_from, poses[:3])])[None].astype(np.float32)
    r_target, th_target = seen_from(poses[3])
    f, c = torch.from_numpy(frames), torch.from_numpy(commands[None].astype(np.float32))
    with torch.no_grad():
        aligned = model.align(f, c)[0].numpy()
        np.testing.assert_allclose(model(f, c)[0].numpy(), aligned[-1], atol=1e-6)
    np.testing.assert_allclose(aligned[-1], model.flow_prior(f[:, -1], c[:, -1])[0].numpy(), atol=1e-6)
    for k in range(3):
        i, j = np.unravel_index(np.argmax(aligned[k]), aligned[k].shape)
        assert abs(grid.range_centres()[i] - r_target) <= grid.range_step, k
        assert abs(grid.azimuth_centres()[j] - th_target) <= grid.azimuth_step, k
    # the raw frames do not: the reflector moved by several bins over the window
    i, j = np.unravel_index(np.argmax(frames[0, 0]), frames[0, 0].shape)
    assert abs(grid.azimuth_centres()[j] - th_target) > 2 * grid.azimuth_step


def test_a_fine_tune_may_align_its_inputs_and_keeps_them(tiny_store, tmp_path):
    """--init with --inputs aligned warm-starts an aligned model from a raw one (the same weights);
    a fine-tune of that one without --inputs stays aligned; a bad value is refused."""
    train(tiny_store, tmp_path / "raw", _cfg(max_steps=2))
    train(tiny_store, tmp_path / "al", _cfg(max_steps=2, init=str(tmp_path / "raw"), inputs="aligned"))
    _, card = load_checkpoint(tmp_path / "al", TINY_GRID)
    assert card["config"]["inputs"] == "aligned" and card["training"]["config"]["inputs"] == "aligned"
    train(tiny_store, tmp_path / "al2", _cfg(max_steps=1, init=str(tmp_path / "al")))
    assert load_checkpoint(tmp_path / "al2", TINY_GRID)[0].cfg.inputs == "aligned"
    ev = evaluate(tiny_store, ["flow", f"echopt:{tmp_path / 'al2' / 'model.safetensors'}"], horizons=(1, 2), samples=10)
    assert np.isfinite(ev.per_window["echopt"][2]["cc"]).all()
    with pytest.raises(SonarSetError, match="inputs must be one of") as refused:
        train(tiny_store, tmp_path / "bad", _cfg(max_steps=1, inputs="warped"))
    assert refused.value.parameter == "inputs"


def test_geometry_branch_starts_at_zero_and_sees_where_a_pixel_lies():
    """The geometry branch (config.geometry_channels) added to a model leaves its forecasts exactly
    as they were until it learns; its inputs are the pixel's position and the command's warp."""
    torch.manual_seed(0)
    cfg = make_config("tiny", *TINY_GRID.shape)
    base = EchoPT(cfg)
    torch.nn.init.normal_(base.head[-1].weight, std=0.1)  # a "trained" base: not just its prior
    geo = EchoPT(make_config("tiny", *TINY_GRID.shape, geometry_channels=4))
    missing, unexpected = geo.load_state_dict(base.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("geo_") for k in missing)
    frames, commands = torch.rand(3, 3, *TINY_GRID.shape), torch.tensor([[0.2, 0.5]] * 4).expand(3, 4, 2).clone()
    assert torch.equal(base(frames, commands), geo(frames, commands))
    g = geo.geometry(commands[:, -1])
    assert g.shape == (3, 7, *TINY_GRID.shape)
    # sin(azimuth) rises across the grid, the range channel runs -1 .. 1 down it, the command is scaled
    assert (g[0, 0, 0].diff() > 0).all() and g[0, 2, 0, 0] < -0.9 and g[0, 2, -1, 0] > 0.9
    assert torch.allclose(g[0, 3:5, 5, 5], torch.tensor([0.2 / 0.3, 0.5]))
    # turning left (omega > 0) moves the scene to the right: each pixel's source lies at a larger azimuth
    assert (g[0, 6, 10:, 5:-5] > 0).all()
    with pytest.raises(ValueError, match="geometry_channels"):
        make_config("tiny", *TINY_GRID.shape, geometry_channels=-1)


def test_a_fine_tune_may_add_the_geometry_branch_and_train_only_it(tiny_store, tmp_path):
    """--init with --geometry-channels adds the branch to a model without one; --trainable geometry
    updates only it, so the rest of the network stays as trained; neither can take a branch away."""
    train(tiny_store, tmp_path / "base", _cfg(max_steps=2))
    start, _ = load_checkpoint(tmp_path / "base", TINY_GRID)
    train(tiny_store, tmp_path / "geo", _cfg(max_steps=4, init=str(tmp_path / "base"), geometry_channels=4,
                                             trainable="geometry"))
    tuned, card = load_checkpoint(tmp_path / "geo", TINY_GRID)
    assert card["config"]["geometry_channels"] == 4 and card["training"]["config"]["trainable"] == "geometry"
    after = tuned.state_dict()
    for k, a in start.state_dict().items():
        assert torch.equal(a, after[k]), k
    assert tuned.geo_weights[-1].weight.abs().sum() > 0  # the branch learned (it starts at zero)
    # a fine-tune of it keeps the branch; one that would drop it, or train a branch that is not there, is refused
    train(tiny_store, tmp_path / "geo2", _cfg(max_steps=1, init=str(tmp_path / "geo")))
    assert load_checkpoint(tmp_path / "geo2", TINY_GRID)[0].cfg.geometry_channels == 4
    with pytest.raises(SonarSetError, match="another network.*geometry_channels"):
        train(tiny_store, tmp_path / "drop", _cfg(max_steps=1, init=str(tmp_path / "geo"), geometry_channels=0))
    with pytest.raises(SonarSetError, match="no geometry branch") as refused:
        train(tiny_store, tmp_path / "none", _cfg(max_steps=1, trainable="geometry"))
    assert refused.value.parameter == "trainable"
    with pytest.raises(SonarSetError, match="geometry_channels must be an integer") as refused:
        train(tiny_store, tmp_path / "huge", _cfg(max_steps=1, geometry_channels=5000))
    assert refused.value.parameter == "geometry_channels"
    ev = evaluate(tiny_store, ["flow", f"echopt:{tmp_path / 'geo' / 'model.safetensors'}"], horizons=(1, 2), samples=10)
    assert np.isfinite(ev.per_window["echopt"][2]["cc"]).all()
