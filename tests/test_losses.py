"""The training loss terms: what each one sees and what it is blind to."""

import numpy as np
import pytest
import torch

from sonarset.errors import SonarSetError
from sonarset.models.echopt.losses import (ECHO_MARGIN, LOSSES, brightest_near, echo_energy_loss, echo_match_loss,
                                         image_loss, nrmsd_loss, parse_loss, window_max,
                                         capped_nrmsd_loss, floored_nrmsd_loss, pooled_nrmsd_loss,
                                         rollout_losses, sorted_rows, step_weights, value_distribution_loss,
                                         weighted_loss)
from sonarset.format.attrs import SensorGrid
from sonarset.scoring.echoes import find_echoes, tolerance_bins
from sonarset.scoring.metrics import nrmsd


def _echo(centre: int, width: float, amplitude: float = 1.0) -> torch.Tensor:
    """One echo on a (1, 40, 12) image: a Gaussian bump in range at azimuth bin 6."""
    r = torch.arange(40.0)[:, None]
    img = torch.zeros(40, 12)
    img[:, 6:7] = amplitude * torch.exp(-0.5 * ((r - centre) / width) ** 2)
    return img[None]


def test_parse_loss_terms_and_errors():
    assert parse_loss("mse") == {"mse": 1.0}
    assert parse_loss("mse=1,w1=0.3") == {"mse": 1.0, "w1": 0.3}
    assert set(LOSSES) == {"mse", "l1", "gdl", "cc", "nrmsd", "nrmsd_pooled", "nrmsd_floored", "nrmsd_capped",
                           "w1", "energy", "echo"}
    with pytest.raises(SonarSetError, match="unknown term 'wasserstein'"):
        parse_loss("mse,wasserstein")
    with pytest.raises(SonarSetError, match="weight of 'w1' is not a number"):
        parse_loss("w1=x")


def test_value_distribution_loss_sees_blur_not_position():
    target = _echo(20, 1.5)
    moved = _echo(26, 1.5)  # the same echo elsewhere: the same pixel values
    # The energy-preserving blur MSE prefers: the average of the echo at three possible ranges.
    blurred = (_echo(17, 1.5) + _echo(20, 1.5) + _echo(23, 1.5)) / 3
    assert value_distribution_loss(moved, target).item() == pytest.approx(0.0, abs=1e-7)
    assert value_distribution_loss(blurred, target).item() > 1e-3
    # MSE prefers the blur to the moved echo; the value-distribution term penalises only the blur.
    assert image_loss(blurred, target, {"mse": 1}) < image_loss(moved, target, {"mse": 1})
    assert image_loss(blurred, target, {"w1": 1}) > image_loss(moved, target, {"w1": 1})


def test_value_distribution_loss_is_a_distance_per_image():
    a, b = _echo(10, 2.0), _echo(30, 1.0, 0.5)
    batch = value_distribution_loss(torch.cat([a, b]), torch.cat([b, a]))
    assert batch.item() == pytest.approx(value_distribution_loss(a, b).item())  # symmetric, averaged
    assert value_distribution_loss(a, a).item() == 0.0


def test_sorted_rows_are_torch_sort_values_with_their_gradient():
    g = torch.Generator().manual_seed(3)
    # negative values, exact ties (zeros, repeated values) and a signed zero, as forecasts hold them
    x = (torch.rand((6, 500), generator=g) - 0.3) * (torch.rand((6, 500), generator=g) > 0.4)
    x[0, :40] = 0.25
    x[1, 7] = -0.0
    target = torch.rand((6, 500), generator=g) * (torch.rand((6, 500), generator=g) > 0.7)
    assert torch.equal(sorted_rows(target), target.sort(dim=1).values)
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    sa, sb = sorted_rows(a), b.sort(dim=1).values
    assert torch.equal(sa, sb)
    (sa - sorted_rows(target)).abs().mean().backward()
    (sb - target.sort(dim=1).values).abs().mean().backward()
    # a tie's members may trade places, not the gradient each value receives in all
    assert torch.equal(a.grad.sort(dim=1).values, b.grad.sort(dim=1).values)
    assert torch.allclose(a.grad.sum(1), b.grad.sum(1))
    # where NumPy cannot sort it (another dtype), torch does
    assert torch.equal(sorted_rows(x.double()), x.double().sort(dim=1).values)
    # a NaN sorts last, whatever its sign bit (arithmetic's NaN, inf - inf, has it set on x86)
    nan = torch.tensor([[1.0, float("inf") - float("inf"), -1.0]], requires_grad=True)
    assert torch.equal(sorted_rows(nan)[:, :2], torch.tensor([[-1.0, 1.0]])) and sorted_rows(nan)[0, 2].isnan()
    # a strided view sorts as its values do
    view = x.t().contiguous().t()
    assert torch.equal(sorted_rows(view.requires_grad_()), x.sort(dim=1).values)


def test_echo_energy_loss_sees_fading_not_position_and_never_lifts_the_background():
    target = _echo(20, 1.5)
    assert echo_energy_loss(_echo(26, 1.5), target).item() == pytest.approx(0.0, abs=1e-6)  # moved: same energy
    faded = _echo(20, 1.5, amplitude=0.7)
    assert echo_energy_loss(faded, target).item() == pytest.approx(0.3, rel=0.05)  # 30% of the energy gone
    # A haze below the echo floor is no echo energy: the term neither counts it nor pushes it up.
    haze = faded + 0.04 * (faded < 0.04)
    pred = haze.clone().requires_grad_(True)
    echo_energy_loss(pred, target).backward()
    below = haze <= 0.05
    assert torch.all(pred.grad[below] == 0)
    assert torch.all(pred.grad[~below] < 0)  # descending the loss brightens the drawn echo


def test_echo_energy_loss_calibrates_the_batch_not_each_image():
    a, b = _echo(10, 2.0), _echo(30, 2.0)
    # One echo too bright, the other as much too dim: the batch keeps its energy.
    pred = torch.cat([1.2 * a, 0.8 * b])
    assert echo_energy_loss(1.2 * a, a).item() > 0.19 and echo_energy_loss(0.8 * b, b).item() > 0.19
    # ~0, but for the echo tails that the scaling moves across the floor.
    assert echo_energy_loss(pred, torch.cat([a, b])).item() < 0.02


def test_echo_match_loss_costs_missed_and_false_echoes_not_offsets_within_the_tolerance():
    window = (3, 1)  # range, azimuth bins
    target = _echo(20, 1.5)
    assert echo_match_loss(target, target, window).item() == 0.0
    assert echo_match_loss(_echo(22, 1.5), target, window).item() == 0.0  # 2 bins off: a match
    # 8 bins off: the target's echo is missed (the brightest forecast pixel within 3 bins of it is
    # the moved echo's tail, 5 bins from its peak) and the forecast's is false; 2 echoes counted.
    moved = echo_match_loss(_echo(28, 1.5), target, window).item()
    tail = np.exp(-0.5 * (5 / 1.5) ** 2)
    assert moved == pytest.approx(((0.3 + ECHO_MARGIN - tail) + (1.0 - 0.3 + ECHO_MARGIN)) / 2, rel=1e-5)
    # A faded echo in the right place is a miss only while it is below the level (and its margin).
    assert echo_match_loss(_echo(20, 1.5, 0.25), target, window).item() == pytest.approx(0.1, rel=1e-3)
    assert echo_match_loss(_echo(20, 1.5, 0.4), target, window).item() == 0.0


def test_echo_match_loss_pushes_only_the_pixels_that_decide_a_match():
    window = (3, 1)
    target = _echo(20, 1.5)
    # A faint echo near the target's and a false one far from it.
    pred = (_echo(21, 1.5, 0.2) + _echo(34, 1.0, 0.6)).requires_grad_(True)
    echo_match_loss(pred, target, window).backward()
    pushed = pred.grad.nonzero().tolist()
    assert sorted(pushed) == [[0, 21, 6], [0, 34, 6]]
    assert pred.grad[0, 21, 6] < 0 < pred.grad[0, 34, 6]  # descent raises the near one, lowers the false one
    with pytest.raises(ValueError, match="echo tolerance"):
        image_loss(pred, target, {"echo": 1})
    assert image_loss(pred, target, {"echo": 2}, echo_window=window).item() == pytest.approx(
        2 * echo_match_loss(pred, target, window).item())


def test_echo_match_loss_finds_the_echoes_the_metric_finds():
    grid = SensorGrid(range_min_m=0.5, range_max_m=2.5, n_range=40, azimuth_min_rad=-1.2, azimuth_max_rad=1.2,
                      n_azimuth=16)
    rng = np.random.default_rng(3)
    images = rng.random((4, 40, 16), dtype=np.float32) ** 8  # sparse bright pixels
    window = tolerance_bins(grid)
    x = torch.from_numpy(images)
    # Against a blank forecast every echo the metric finds is missed by its value (at most level +
    # margin), and their count is the denominator.
    echoes = find_echoes(images, grid)
    r = np.rint((echoes.range_m - grid.range_min_m) / grid.range_step - 0.5).astype(int)
    a = np.rint((np.radians(echoes.azimuth_deg) - grid.azimuth_min_rad) / grid.azimuth_step - 0.5).astype(int)
    shortfalls = np.minimum(images[echoes.image, r, a], 0.3 + ECHO_MARGIN)
    assert len(shortfalls) > 4 and shortfalls.min() < 0.3 + ECHO_MARGIN  # some echoes below level + margin
    assert echo_match_loss(torch.zeros_like(x), x, window).item() == pytest.approx(shortfalls.mean(), rel=1e-5)
    # And a forecast equal to the target matches each.
    assert echo_match_loss(x, x, window).item() == 0.0


@pytest.mark.parametrize("window", [(1, 1), (3, 2), (2, 0), (0, 3), (5, 3), (4, 2), (8, 5), (6, 7)])
def test_window_max_is_a_clipped_max_pool_and_brightest_near_picks_its_pixel(window):
    x = torch.rand(3, 13, 9, generator=torch.Generator().manual_seed(1))
    pooled = torch.nn.functional.max_pool2d(x[:, None], (2 * window[0] + 1, 2 * window[1] + 1), stride=1,
                                            padding=window)[:, 0]
    assert torch.equal(window_max(x, window), pooled)
    at = torch.tensor([[0, 0, 0], [1, 6, 4], [2, 12, 8], [2, 3, 0]])  # corners, middle, an edge
    pick = brightest_near(x.requires_grad_(True), at, window)
    assert torch.equal(pick.detach(), pooled[at[:, 0], at[:, 1], at[:, 2]])
    pick.sum().backward()
    assert (x.grad > 0).sum() <= len(at) and x.grad.sum() == len(at)  # one pixel each (two picks may share one)


def test_nrmsd_loss_is_the_metric_and_weights_a_faint_target_as_it_does():
    bright, faint = _echo(20, 1.5), _echo(20, 1.5, amplitude=0.05)
    stray = 0.02 * _echo(30, 1.0)  # the same faint echo drawn where neither target has one
    pred, target = torch.cat([bright + stray, faint + stray]), torch.cat([bright, faint])
    expected = nrmsd(pred.numpy(), target.numpy()).mean()
    assert nrmsd_loss(pred, target).item() == pytest.approx(float(expected), rel=1e-5)
    # MSE charges the stray echo the same on both images; NRMSD 20 times more on the faint one.
    per_image = [nrmsd_loss(p[None], t[None]).item() for p, t in zip(pred, target)]
    assert per_image[1] == pytest.approx(20 * per_image[0], rel=1e-4)
    mse = [image_loss(p[None], t[None], {"mse": 1}).item() for p, t in zip(pred, target)]
    assert mse[0] == pytest.approx(mse[1])
    assert nrmsd_loss(target, target).item() == 0.0
    assert np.isfinite(nrmsd_loss(stray, torch.zeros_like(stray)).item())  # a blank target stays finite


def test_pooled_nrmsd_loss_pulls_every_image_alike():
    bright, faint = _echo(20, 1.5), _echo(20, 1.5, amplitude=0.01)
    stray = 0.02 * _echo(30, 1.0)
    target = torch.cat([bright, faint])
    # On one image it is that image's NRMSD; over a batch, summed error norms over summed target norms.
    assert pooled_nrmsd_loss(bright + stray, bright).item() == pytest.approx(nrmsd_loss(bright + stray, bright).item())
    pred = torch.cat([bright + stray, faint + stray])
    expected = 2 * stray.norm() / (bright.norm() + faint.norm())
    assert image_loss(pred, target, {"nrmsd_pooled": 1}).item() == pytest.approx(expected.item(), rel=1e-5)
    assert pooled_nrmsd_loss(target, target).item() == 0.0
    # Gradient per image: the same norm for the bright and the near-blank target under the pooled term,
    # 100 times larger on the near-blank one under the per-image NRMSD.
    for loss, ratio in ((pooled_nrmsd_loss, 1.0), (nrmsd_loss, 100.0)):
        p = pred.clone().requires_grad_(True)
        loss(p, target).backward()
        norms = p.grad.flatten(1).norm(dim=1)
        assert (norms[1] / norms[0]).item() == pytest.approx(ratio, rel=1e-3)


def test_floored_nrmsd_loss_caps_only_near_blank_targets():
    stray = 0.02 * _echo(30, 1.0)
    ordinary = torch.cat([_echo(20, 1.5), _echo(20, 1.5, 0.8), _echo(20, 1.5, 0.5)])
    # No target below a quarter of the batch's median norm: exactly the per-image NRMSD.
    assert floored_nrmsd_loss(ordinary + stray, ordinary).item() == pytest.approx(
        nrmsd_loss(ordinary + stray, ordinary).item(), rel=1e-6)
    # A near-blank target at 1/100 of the norm: its gradient capped at 4x a median image's, not 100x.
    target = torch.cat([ordinary, _echo(20, 1.5, 0.01)])
    p = (target + stray).requires_grad_(True)
    floored_nrmsd_loss(p, target).backward()
    norms = p.grad.flatten(1).norm(dim=1)
    assert (norms[3] / norms[2]).item() == pytest.approx(4.0, rel=1e-3)  # torch: the lower middle value
    assert floored_nrmsd_loss(target, target).item() == 0.0


def test_capped_nrmsd_loss_caps_only_where_flow_calls_the_target_near_blank():
    stray = 0.02 * _echo(30, 1.0)
    bright, faint = _echo(20, 1.5), _echo(20, 1.5, 0.1)  # the faint one an ordinary target of a sparse world
    target = torch.cat([bright, faint])
    # flow's NRMSD at most 2 on both: exactly the per-image NRMSD, the faint target's 10x pull kept
    flow_ok = target + 1.5 * stray
    assert capped_nrmsd_loss(target + stray, target, flow_ok).item() == pytest.approx(
        nrmsd_loss(target + stray, target).item(), rel=1e-6)
    # a near-blank target on which flow's error is 8x its norm: its weight is that of flow's NRMSD 2
    blank = _echo(20, 1.5, 0.001)
    flow_far = blank + 8 * blank.norm() * stray / stray.norm()
    p = (blank + stray).requires_grad_(True)
    capped_nrmsd_loss(p, blank, flow_far).backward()
    assert p.grad.norm().item() == pytest.approx(2 / (flow_far - blank).norm().item(), rel=1e-4)
    assert p.grad.norm().item() == pytest.approx(1 / (4 * blank.norm().item()), rel=1e-4)  # 1/4 of the metric's
    assert capped_nrmsd_loss(target, target, flow_far.expand(2, -1, -1)).item() == 0.0
    with pytest.raises(ValueError, match="flow baseline"):
        image_loss(target, target, {"nrmsd_capped": 1})


def test_rollout_losses_compare_each_step_with_flows_own_rollout():
    """The reference of step h is flow's h-step rollout from the measured frames (what evaluation
    compares the model with), driven by step h's newest command, not flow of the model's forecasts."""
    n_in, k = 3, 3
    frames = torch.rand(2, n_in, 8, 6)
    cmds = torch.arange(2 * (n_in + k) * 2, dtype=torch.float32).view(2, n_in + k, 2)
    calls = []

    def flow(last, command):
        calls.append((last.clone(), command.clone()))
        return last + 1.0

    def fwd(ctx, c):
        return torch.zeros_like(ctx[:, -1])  # the model's own forecasts differ from flow's

    rollout_losses(fwd, frames, cmds, torch.rand(2, k, 8, 6), {"nrmsd_capped": 1.0}, flow=flow)
    assert len(calls) == k
    for h, (last, command) in enumerate(calls):
        torch.testing.assert_close(last, frames[:, -1] + h)  # chained on flow's own forecasts
        torch.testing.assert_close(command, cmds[:, h + n_in])
    calls.clear()
    rollout_losses(fwd, frames, cmds, torch.rand(2, k, 8, 6), {"nrmsd": 1.0}, flow=flow)
    assert not calls  # no reference term: no warp
    with pytest.raises(ValueError, match="flow baseline's warp"):
        rollout_losses(fwd, frames, cmds, torch.rand(2, k, 8, 6), {"nrmsd_capped": 1.0})


def test_step_weights_share_a_rollout_loss():
    assert step_weights("uniform", 4) == [0.25] * 4
    harmonic = np.array(step_weights("harmonic", 4))
    np.testing.assert_allclose(harmonic, np.array([1, 1 / 2, 1 / 3, 1 / 4]) / (25 / 12))
    assert harmonic.sum() == pytest.approx(1)
    # losses growing with the step, as a rollout's do: uniform is their mean, harmonic leans to the first
    losses = [torch.tensor(x) for x in (1.0, 2.0, 3.0, 4.0)]
    assert float(weighted_loss(losses)) == pytest.approx(2.5)
    assert float(weighted_loss(losses, "harmonic")) == pytest.approx(4 / (25 / 12))
    assert float(weighted_loss([torch.tensor(3.0)], "harmonic")) == pytest.approx(3.0)  # pushforward's one loss
    # the first step's share of the gradient
    steps = [torch.tensor(1.0, requires_grad=True) for _ in range(10)]
    weighted_loss([s * s for s in steps], "harmonic").backward()
    assert steps[0].grad / sum(s.grad for s in steps) == pytest.approx(1 / sum(1 / h for h in range(1, 11)))
    with pytest.raises(SonarSetError, match="step_weights must be one of"):
        step_weights("cubic", 3)


def test_a_rollout_trained_on_chosen_horizons_has_the_losses_and_weights_of_those_steps():
    """``horizons`` keeps the losses at those steps: a chained model's as its whole rollout's, and a
    model that forecasts each horizon directly (EchoWarp) from one pass of those alone, through the
    forward that DistributedDataParallel wraps; harmonic weights go by the step, 1/h."""
    from sonarset.models.echopt.config import grid_and_rig
    from sonarset.models.echopt.networks import build
    from sonarset.models.echopt.train_config import TrainConfig
    from sonarset.format.attrs import RobotRig

    grid = SensorGrid(range_min_m=0.5, range_max_m=3.0, n_range=40, azimuth_min_rad=-1.4, azimuth_max_rad=1.4,
                      n_azimuth=18)
    torch.manual_seed(0)
    warp = build("echowarp", "tiny", *grid.shape, **grid_and_rig(grid, RobotRig()))  # max_horizon 4
    for p in warp.parameters():
        torch.nn.init.normal_(p, std=0.3)
    frames, targets = torch.rand(3, 3, *grid.shape), torch.rand(3, 4, *grid.shape)
    cmds = (torch.rand(3, 7, 2) * 2 - 1) * torch.tensor([0.3, 1.0])
    terms = {"cc": 1.0, "nrmsd_capped": 1.0}
    calls = []
    forward = warp.forward
    warp.forward = lambda *a, **kw: calls.append(kw) or forward(*a, **kw)
    whole = rollout_losses(warp, frames, cmds, targets, terms, flow=warp.flow_prior)
    some = rollout_losses(warp, frames, cmds, targets, terms, flow=warp.flow_prior, horizons=(2, 4))
    assert calls[-1] == {"horizons": (2, 4)} and len(some) == 2
    torch.testing.assert_close(torch.stack(some), torch.stack([whole[1], whole[3]]), rtol=0, atol=1e-5)

    def chained(ctx, c):
        return ctx[:, -1] * 0.9

    every = rollout_losses(chained, frames, cmds, targets, terms, flow=warp.flow_prior)
    assert rollout_losses(chained, frames, cmds, targets, terms, flow=warp.flow_prior, horizons=(1, 3)) == \
        [every[0], every[2]]
    losses = [torch.tensor(1.0), torch.tensor(4.0)]
    assert float(weighted_loss(losses, "harmonic", (1, 4))) == pytest.approx((1 + 4 / 4) / (1 + 1 / 4))
    assert float(weighted_loss(losses, "uniform", (1, 4))) == pytest.approx(2.5)
    # the setting: steps up to the curriculum's k; refused in one line where no run can have it
    assert TrainConfig(horizons="1,3,5,10").loss_horizons(4) == (1, 3)
    assert TrainConfig().loss_horizons(10) is None
    for bad, message in (("3,1", "increasing"), ("0,2", "increasing"), ("a", "increasing"), ("5", "none within")):
        with pytest.raises(SonarSetError, match=message):
            TrainConfig(horizons=bad, curriculum="4").check()
    with pytest.raises(SonarSetError, match="pushforward"):
        TrainConfig(horizons="1,2", pushforward=True).check()
    with pytest.raises(SonarSetError, match="none within a 1-step rollout"):  # refused before training, not at validation
        TrainConfig(horizons="3,5", curriculum="10", val_horizon=1).check()
    with pytest.raises(ValueError, match="2 losses for the 3 horizons"):
        weighted_loss(losses, "harmonic", (1, 2, 4))
