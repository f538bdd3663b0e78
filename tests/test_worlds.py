"""World families (lab, corridor, orchard, warehouse, rooms), fences, and stores that mix them."""

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from sonarset import SonarSetError, open_store
from sonarset.cli.app import app
from sonarset.format.attrs import SensorGrid
from sonarset.sim import (
    FAMILIES, ExplorationPolicy, GenerationSpec, SonarModel, generate, integrate, load_world, plan_runs,
)
from sonarset.sim.families import corridor_world
from sonarset.sim.spec import world_mix
from sonarset.sim.world import FenceSpec, World, WorldSpec
from sonarset.windows import FrameBank

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=60, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)


def _geometry(w: World) -> tuple:
    return (w.seg_a.tolist(), w.seg_b.tolist(), w.seg_refl.tolist(), w.circ_c.tolist(), w.circ_r.tolist(),
            w.circ_refl.tolist(), w.fence_a.tolist())


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_family_varies_with_seed_and_repeats_with_it(family):
    a, b, a2 = load_world(family, 11), load_world(family, 12), load_world(family, 11)
    assert _geometry(a) == _geometry(a2)
    assert _geometry(a) != _geometry(b)
    assert len(a.seg_a) + len(a.circ_c) >= 10  # a scene, not a few reflectors


@pytest.mark.parametrize("family", sorted(FAMILIES))
@pytest.mark.parametrize("seed", [3, 404])
def test_exploration_stays_clear_and_inside(family, seed):
    """The policy spawns in a box and drives 2 minutes without touching a wall, circle or fence;
    the robot sees echoes most of the time (it does not wander into empty space)."""
    world = load_world(family, seed)
    rng = np.random.default_rng(seed)
    policy = ExplorationPolicy(world, rng, dt=0.2)
    pose = world.sample_spawn(rng)
    poses = [pose]
    for _ in range(600):
        pose = integrate(pose, *policy(pose), 0.2)
        poses.append(pose)
    poses = np.array(poses)
    assert world.clearance(poses[:, :2]).min() > 0.2  # the robot's radius
    if len(world.fence_a):
        lo, hi = np.minimum(world.fence_a, world.fence_b).min(0), np.maximum(world.fence_a, world.fence_b).max(0)
        assert (poses[:, :2] > lo).all() and (poses[:, :2] < hi).all()
    images, _ = SonarModel(GRID).render_batch(world, poses[::20], None)
    assert (images.reshape(len(images), -1).max(1) > 0.3).mean() > 0.5


def test_corridor_seed_zero_is_the_control_experiments():
    assert _geometry(load_world("corridor", 0)) == _geometry(corridor_world())
    assert load_world("corridor", 0).waypoint == corridor_world().waypoint
    assert len(load_world("corridor", 5).fence_a) == 4 and load_world("corridor", 5).waypoint is not None


def test_fences_block_the_robot_but_not_the_sonar():
    spec = WorldSpec(circles=[{"centre": (2.0, 0.0), "radius": 0.1}], spawn=[{"x": (0, 0.1), "y": (0, 0.1)}])
    fenced = spec.model_copy(update={"fences": [FenceSpec(start=(1.0, -3), end=(1.0, 3))]})
    open_w, fenced_w = World.from_spec(spec), World.from_spec(fenced)
    model = SonarModel(GRID)
    pose = np.array([[0.0, 0.0, 0.0]])
    assert np.array_equal(model.render_batch(open_w, pose, None)[0], model.render_batch(fenced_w, pose, None)[0])
    assert fenced_w.clearance(np.array([[0.9, 0.0]]))[0] == pytest.approx(0.1)
    assert World.from_spec(fenced_w.to_spec()).fence_a.tolist() == [[1.0, -3.0]]
    policy = ExplorationPolicy(fenced_w, np.random.default_rng(0), dt=0.2)
    p = np.array([0.2, 0.0, 0.0])
    for _ in range(300):
        p = integrate(p, *policy(p), 0.2)
        assert p[0] < 1.0 - 0.2


def test_world_mix_syntax():
    assert world_mix("lab") == [("lab", 10)] and world_mix("lab", 3) == [("lab", 3)]
    assert world_mix("lab:4, orchard:2") == [("lab", 4), ("orchard", 2)]
    assert world_mix("worlds/a.json:2") == [("worlds/a.json", 2)]
    for bad, runs, why in [("lab:4,orchard", None, "give every world a run count"),
                           ("lab,orchard", None, "several worlds need a run count"),
                           ("lab:4", 3, "gives the run counts; leave runs unset"), ("lab:1,lab:2", None, "named twice"),
                           (" , ", None, "empty")]:
        with pytest.raises(SonarSetError, match=why):
            world_mix(bad, runs)


def test_mixed_plans_keep_single_world_plans_and_give_each_world_test_runs():
    def plans_of(runs, test_runs, world):
        return plan_runs(GenerationSpec(runs=runs, test_runs=test_runs, minutes=1.0, seed=7, world=world))

    assert plans_of(3, 1, "lab") == plans_of(None, 1, "lab:3")
    plans = plans_of(None, 1, "lab:2,orchard:1,rooms:1")
    assert [(p.name, p.split, p.world) for p in plans] == [
        ("run_000", "train", "lab"), ("run_001", "train", "lab"), ("run_002", "train", "orchard"),
        ("run_003", "train", "rooms"), ("test_000", "test", "lab"), ("test_001", "test", "orchard"),
        ("test_002", "test", "rooms")]
    assert len({p.seed for p in plans}) == len(plans) and len({p.world_seed for p in plans}) == len(plans)
    # the first runs of a mix are those of the first world's own store
    assert plans[:2] == plans_of(None, 0, "lab:2,orchard:1,rooms:1")[:2]


@pytest.fixture(scope="module")
def mixed_store(tmp_path_factory):
    path = tmp_path_factory.mktemp("worlds") / "mix.zarr"
    generate(path, world="orchard:1,warehouse:1", test_runs=1, minutes=0.4, seed=2, workers=1, grid=GRID)
    return open_store(path)


def test_store_records_each_runs_world_and_filters_by_it(mixed_store):
    s = mixed_store
    assert s.worlds() == {"orchard": ["run_000", "test_000"], "warehouse": ["run_001", "test_001"]}
    assert s.worlds("test") == {"orchard": ["test_000"], "warehouse": ["test_001"]}
    src = s.run("run_001").attrs.source
    assert src["world"] == "warehouse" and isinstance(src["world_seed"], int)
    assert s.runs("train", worlds=["orchard"]) == ["run_000"]
    bank = FrameBank.from_store(s, split="test", worlds=["warehouse"])
    assert bank.run_names == ["test_001"]
    with pytest.raises(SonarSetError, match=r"no complete runs of world rooms in split 'test' \(worlds: orchard, warehouse\)"):
        FrameBank.from_store(s, split="test", worlds=["rooms"])


def test_generate_and_eval_cli_take_worlds(mixed_store, tmp_path):
    r = CliRunner().invoke(app, ["generate", str(tmp_path / "m.zarr"), "--world", "lab:1,orchard", "--minutes", "0.1"])
    assert r.exit_code == 1 and "give every world a run count" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "m.zarr").exists()
    r = CliRunner().invoke(app, ["eval", mixed_store.location, "--worlds", "orchard", "--samples", "20",
                                 "--horizons", "1,3", "--models", "naive,flow", "--out", str(tmp_path / "o"),
                                 "--no-figures"])
    assert r.exit_code == 0, r.output
    report = (tmp_path / "o" / "report.md").read_text()
    assert "(test_000), worlds orchard;" in report


def test_info_names_each_runs_world(mixed_store):
    r = CliRunner().invoke(app, ["info", mixed_store.location, "--json"])
    assert r.exit_code == 0, r.output
    import json

    worlds = {run["name"]: run["world"] for run in json.loads(r.output)["runs"]}
    seed = mixed_store.run("run_001").attrs.source["world_seed"]
    assert worlds["run_000"].startswith("orchard #") and worlds["run_001"] == f"warehouse #{seed}"


@pytest.mark.parametrize("name, text, says", [
    ("deep.json", lambda: '{"walls": ' + "[" * 100_000 + "]" * 100_000 + "}", "nested too deeply"),
    ("deep.toml", lambda: "walls = " + "[" * 5_000 + "]" * 5_000 + "\n", "nested too deeply"),
    ("big.json", lambda: " " * (17 * 2**20) + "{}", "17 MiB is not a world file"),
], ids=["deep-json", "deep-toml", "17-MiB"])
def test_world_files_too_deep_or_too_large_are_refused_in_one_line(tmp_path, name, text, says):
    path = tmp_path / name
    path.write_text(text())
    with pytest.raises(SonarSetError, match=says) as exc:
        load_world(str(path))
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)
