"""The losses of training: per-pixel image terms, their weighted sums (the ``loss`` setting), and the
unrolled loss over a rollout that training minimises and validation reports."""

from __future__ import annotations

import sys

import numpy as np
import torch
import torch.nn.functional as F

from sonarset.errors import SonarSetError
from sonarset.perf import release_free_memory
from sonarset.windows import WindowBatcher, WindowIndex

from sonarset.models.echopt.distributed import Dist
from sonarset.models.echopt.precision import autocast
from sonarset.models.echopt.train_config import STEP_WEIGHTS
from sonarset.models.eval.result import ECHO_FLOOR
from sonarset.scoring.echoes import EchoMatching

LOSSES = ("mse", "l1", "gdl", "cc", "nrmsd", "nrmsd_pooled", "nrmsd_floored", "nrmsd_capped", "w1", "energy", "echo")
# terms that compare the forecast with the flow baseline's forecast of the same target
REFERENCE_TERMS = ("nrmsd_capped",)


def parse_loss(spec: str) -> dict[str, float]:
    """``"mse"`` -> {"mse": 1}; ``"mse=1,gdl=0.5"`` -> {"mse": 1.0, "gdl": 0.5}."""
    terms: dict[str, float] = {}
    for part in spec.split(","):
        name, _, w = part.strip().partition("=")
        if name not in LOSSES:
            raise SonarSetError(f"loss {spec!r}: unknown term {name!r}; choose from {', '.join(LOSSES)}",
                                parameter="loss")
        try:
            terms[name] = float(w) if w else 1.0
        except ValueError:
            raise SonarSetError(f"loss {spec!r}: weight of {name!r} is not a number", parameter="loss") from None
    return terms


def value_distribution_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """1-D Wasserstein distance between each forecast's and its target's pixel values (mean absolute
    difference of the sorted values), averaged over the batch.

    Blind to where the energy is (MSE's job), it sees only how it is distributed: the conditional
    mean of an uncertain echo position, which MSE converges to, spreads a bright echo into a wider,
    dimmer one, and so has too many middling pixels and too few bright ones. Penalising that keeps a
    rollout's peak and echo energy, which is what fades otherwise.
    """
    return (sorted_rows(pred.flatten(1)) - sorted_rows(target.flatten(1))).abs().mean()


def sorted_rows(x: torch.Tensor) -> torch.Tensor:
    """Each row of ``x`` (N, n) sorted ascending; differentiable (the gradient reaches each value where
    it came from), as ``x.sort(dim=1).values``.

    On a CPU, NumPy sorts: its vectorised sort (x86-simd-sort) is 10x faster than torch's on rows
    of an image's 18,000 pixels. A row that needs a gradient is sorted by a 64-bit key, the value's
    order-preserving bits above its index, so that one sort gives the permutation to gather the
    values with (ties in index order): 1.6x faster than ``torch.sort`` on two threads, 5x on one.
    NaNs (which the keys would order by their sign bit) and big-endian machines (where the key would
    not be the high half) go to ``torch.sort``."""
    if (x.device.type != "cpu" or x.dtype != torch.float32 or x.dim() != 2 or x.shape[1] >= 2 ** 32
            or sys.byteorder != "little"):
        return x.sort(dim=1).values
    values = x.detach().contiguous().numpy()
    if not x.requires_grad:
        return torch.from_numpy(np.sort(values, axis=1))
    if np.isnan(values).any():
        return x.sort(dim=1).values
    bits = values.view(np.int32)
    keys = np.empty((*values.shape, 2), np.uint32)  # (index, key) pairs: one little-endian uint64 each
    # unsigned integers compare as the floats do once a positive float's sign bit is set and a
    # negative one's every bit is flipped (larger magnitudes are then smaller keys)
    np.bitwise_xor(bits, (bits >> 31) | np.int32(-2 ** 31), out=keys[..., 1].view(np.int32))
    keys[..., 0] = np.arange(values.shape[1], dtype=np.uint32)
    keys.view(np.uint64)[..., 0].sort(axis=1)
    return x.gather(1, torch.from_numpy(keys[..., 0].astype(np.int64)))


def echo_energy_loss(pred: torch.Tensor, target: torch.Tensor, floor: float = ECHO_FLOOR) -> torch.Tensor:
    """The batch's relative echo-energy deficit or excess: |sum E(pred) - sum E(target)| / sum E(target),
    with E an image's echo energy, the sum of its pixels above ``floor`` (the quantity of the "no
    fade" check, ``models.eval.result.peak_and_energy``).

    A forecast cannot know which echoes will enter the field of view during a rollout; any loss
    that scores each pixel draws such an echo as faint as its probability, so a deterministic model
    loses a little energy at every step. This term calibrates the total over the batch, not any
    one image or pixel. Its gradient reaches only pixels above the floor, so it brightens echoes the
    model already draws and never lifts the background into new ones.
    """
    e_pred = (pred * (pred > floor)).sum()
    e_target = (target * (target > floor)).sum()
    return (e_pred - e_target).abs() / e_target.clamp_min(1e-6)


def _error_and_target_norms(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image: ||p - m||_2 and ||m||_2, the two halves of every NRMSD term."""
    return (pred - target).flatten(1).norm(dim=1), target.flatten(1).norm(dim=1)


def nrmsd_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The evaluation's NRMSD, ||p - m||_2 / ||m||_2 per image, averaged over the batch.

    MSE weights every image by its own energy, so a near-blank target (a robot facing open space)
    hardly counts in it, while NRMSD divides by that energy: a faint echo drawn where the target has
    none costs little MSE and a large NRMSD. The mean NRMSD of a test run is dominated by such
    windows (docs/metrics.md), and this term trains on them with the weight the metric gives them.
    """
    diff, norms = _error_and_target_norms(pred, target)
    return (diff / norms.clamp_min(1e-6)).mean()


def pooled_nrmsd_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The batch's summed error norms over its summed target norms, sum ||p - m||_2 / sum ||m||_2.

    On ordinary images it has the scale of ``nrmsd_loss``, but every image's gradient has the same
    norm (1 / sum ||m||), where ``nrmsd_loss`` gives each image 1 / ||m||: a near-blank target, at
    1/100 of an ordinary target's norm, pulls 100 times harder there. With 1 % of the windows near
    blank, those take about half of that term's push, and the model learns to win them by wide
    margins while the ordinary windows, most of a test run, gain less (BENCHMARKS, "Where NRMSD's
    t-test gets its variance"). This term spends the push on all windows alike.
    """
    diff, norms = _error_and_target_norms(pred, target)
    return diff.sum() / norms.sum().clamp_min(1e-6)


NRMSD_FLOOR_SHARE = 0.25  # of the batch's median target norm


def floored_nrmsd_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image NRMSD whose denominator is at least ``NRMSD_FLOOR_SHARE`` of the batch's median
    target norm: ||p - m||_2 / max(||m||_2, share x median ||m||_2), averaged over the batch.

    Between ``nrmsd_loss`` and ``pooled_nrmsd_loss``: an ordinary image keeps the weight the metric
    gives it (1 / ||m||, so sparse families such as the corridor and the orchard, whose targets hold
    less energy, keep their larger share, which the pooled term takes from them), while a near-blank
    target pulls at most 4 times harder than a typical one instead of 100 times.
    """
    diff, norms = _error_and_target_norms(pred, target)
    floor = NRMSD_FLOOR_SHARE * norms.median()
    return (diff / torch.maximum(norms, floor).clamp_min(1e-6)).mean()


NEAR_BLANK_NRMSD = 2.0  # flow's NRMSD above which a target counts as near blank (BENCHMARKS' split)


def capped_nrmsd_loss(pred: torch.Tensor, target: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Per-image NRMSD whose weight is capped where the target is near blank for the flow baseline:
    ||p - m||_2 / max(||m||_2, ||f - m||_2 / ``NEAR_BLANK_NRMSD``), ``reference`` f being flow's
    forecast of the same target, averaged over the batch.

    Every image on which flow's NRMSD is at most 2 keeps the metric's own weight, 1 / ||m||, in every
    world family whatever else is in the batch (``floored_nrmsd_loss`` floors at a share of the
    batch's median norm, which in a lab-heavy batch cut the corridor's faint but ordinary targets:
    BENCHMARKS). A target so faint that flow's error is more than twice its norm pulls as if flow's
    NRMSD there were 2: these are the windows that the per-image term trains hardest on and that
    make a paired test's variance.
    """
    diff, norms = _error_and_target_norms(pred, target)
    cap = (reference.detach() - target).flatten(1).norm(dim=1) / NEAR_BLANK_NRMSD
    return (diff / torch.maximum(norms, cap).clamp_min(1e-6)).mean()


ECHO_MARGIN = 0.05  # how far past the detection level a hinge of echo_match_loss reaches


def window_max(x: torch.Tensor, window: tuple[int, int]) -> torch.Tensor:
    """Each pixel's maximum within +-``window`` (range, azimuth) bins of (..., R, A) images, the
    window clipped to the image (``max_pool2d`` with stride 1 padded with -inf): in range, then in
    azimuth, as elementwise maxima of shifted views, 30x faster than ``max_pool2d`` on the CPU. A
    run of w pixels takes about log2(w) maxima, not w - 1: the maximum over a run of 2s is that
    of two overlapping runs of s (van Herk 1992; Gil & Werman 1993), and a run of w that of two runs
    of the largest such s below w, offset by w - s."""
    for dim, h in ((-2, window[0]), (-1, window[1])):
        n, width = x.shape[dim], 2 * h + 1
        padded = F.pad(x, (0, 0, h, h) if dim == -2 else (h, h), value=float("-inf"))
        run, size = padded, 1  # run[i]: the maximum of padded[i : i + size]
        while 2 * size <= width:
            m = run.shape[dim] - size
            run, size = torch.maximum(run.narrow(dim, 0, m), run.narrow(dim, size, m)), 2 * size
        x = torch.maximum(run.narrow(dim, 0, n), run.narrow(dim, width - size, n)) if size < width else run.narrow(dim, 0, n)
    return x


def brightest_near(x: torch.Tensor, at: torch.Tensor, window: tuple[int, int]) -> torch.Tensor:
    """The largest pixel of (B, R, A) images ``x`` within +-``window`` bins of each pixel ``at`` (K, 3)
    (image, range, azimuth indices), (K,), differentiable: it is that pixel itself, found without
    gradient, so its gradient reaches that pixel alone."""
    _, R, A = x.shape
    with torch.no_grad():
        dr, da = torch.meshgrid(torch.arange(-window[0], window[0] + 1, device=x.device),
                                torch.arange(-window[1], window[1] + 1, device=x.device), indexing="ij")
        r, a = at[:, 1:2] + dr.reshape(1, -1), at[:, 2:3] + da.reshape(1, -1)  # (K, window pixels)
        inside = (r >= 0) & (r < R) & (a >= 0) & (a < A)
        r, a = r.clamp(0, R - 1), a.clamp(0, A - 1)
        best = x[at[:, :1], r, a].masked_fill(~inside, float("-inf")).argmax(1, keepdim=True)
    return x[at[:, 0], r.gather(1, best)[:, 0], a.gather(1, best)[:, 0]]


def echo_match_loss(pred: torch.Tensor, target: torch.Tensor, window: tuple[int, int],
                    level: float = EchoMatching.level, margin: float = ECHO_MARGIN) -> torch.Tensor:
    """A differentiable stand-in for the echo metrics' matching (sonarset/scoring/echoes.py), over
    (B, R, A) images, ``window`` the tolerance in bins (``tolerance_bins``):

    - a target echo (a local maximum >= ``level``) whose forecast holds no pixel as bright as the
      echo, or as ``level + margin``, within the tolerance costs the shortfall of the brightest one
      there (a miss: its gradient raises the forecast where the echo is, not a smear around it);
    - a forecast echo with no target echo within the tolerance costs its excess over
      ``level - margin`` (a false echo: lowered until it is no echo).

    The sum over both kinds, divided by the number of target and forecast echoes, is 0 when every
    echo is matched with margin to spare, as F1's denominator counts them. CC and NRMSD score the
    pixels; an echo a pixel term draws as a smear below the level, or as two maxima, they barely
    see, and the echo F1 counts in full. Unlike F1 it ignores the one-to-one pairing.
    """
    with torch.no_grad():
        t_echo = (target >= level) & (target >= window_max(target, window))
        p_echo = (pred >= level) & (pred >= window_max(pred, window))
        false = p_echo & (window_max(t_echo.float(), window) == 0)
    # a miss costs the shortfall of the forecast's brightest pixel near the echo, and moves it alone
    near = brightest_near(pred, t_echo.nonzero(), window)
    missed = F.relu(target[t_echo].clamp(max=level + margin) - near).sum()
    extra = F.relu(pred - (level - margin))[false].sum()
    return (missed + extra) / (t_echo.sum() + p_echo.sum()).clamp_min(1)


def image_loss(pred: torch.Tensor, target: torch.Tensor, terms: dict[str, float],
               reference: torch.Tensor | None = None, echo_window: tuple[int, int] | None = None) -> torch.Tensor:
    """Weighted sum of per-pixel losses over (B, R, A) images; ``reference``, the flow baseline's
    forecasts of the same targets, is needed by the ``REFERENCE_TERMS`` only, ``echo_window``
    (the echo tolerance in bins) by ``echo``."""
    total = pred.new_zeros(())
    for name, w in terms.items():
        if name == "mse":
            v = F.mse_loss(pred, target)
        elif name == "l1":
            v = F.l1_loss(pred, target)
        elif name == "gdl":  # image-gradient difference (Mathieu et al. 2016): keeps edges sharp
            v = (F.l1_loss(pred.diff(dim=-1), target.diff(dim=-1)) + F.l1_loss(pred.diff(dim=-2), target.diff(dim=-2))) / 2
        elif name == "nrmsd":
            v = nrmsd_loss(pred, target)
        elif name == "nrmsd_pooled":
            v = pooled_nrmsd_loss(pred, target)
        elif name == "nrmsd_floored":
            v = floored_nrmsd_loss(pred, target)
        elif name == "nrmsd_capped":
            if reference is None:
                raise ValueError("the nrmsd_capped term needs the flow baseline's forecasts")
            v = capped_nrmsd_loss(pred, target, reference)
        elif name == "w1":
            v = value_distribution_loss(pred, target)
        elif name == "energy":
            v = echo_energy_loss(pred, target)
        elif name == "echo":
            if echo_window is None:
                raise ValueError("the echo term needs the echo tolerance in bins (tolerance_bins of the grid)")
            v = echo_match_loss(pred, target, echo_window)
        else:  # 1 - CC (the paper's metric) per image
            p = pred.flatten(1) - pred.flatten(1).mean(1, keepdim=True)
            t = target.flatten(1) - target.flatten(1).mean(1, keepdim=True)
            v = 1 - ((p * t).sum(1) / (p.norm(dim=1) * t.norm(dim=1) + 1e-8)).mean()
        total = total + w * v
    return total


def step_weights(kind: str, k: int, horizons: tuple[int, ...] | None = None) -> list[float]:
    """The shares of a ``k``-step rollout's losses in the training loss, summing to 1: ``uniform``
    (1/k each) or ``harmonic`` (step h in proportion to 1/h; k = 10: the one-step forecast 34 %, the
    tenth 3 %); with ``horizons``, of the losses at those steps alone (k of them)."""
    if kind not in STEP_WEIGHTS:
        raise SonarSetError(f"step_weights must be one of {', '.join(STEP_WEIGHTS)}, got {kind!r}",
                            parameter="step_weights")
    steps = horizons or range(1, k + 1)
    w = [1.0] * k if kind == "uniform" else [1.0 / h for h in steps]
    return [x / sum(w) for x in w]


def weighted_loss(losses: list[torch.Tensor], kind: str = "uniform",
                  horizons: tuple[int, ...] | None = None) -> torch.Tensor:
    """The rollout's loss: its steps' losses (at ``horizons``, when given) by their ``step_weights``
    (one loss, as pushforward's, is itself)."""
    if horizons is not None and len(losses) != len(horizons):
        raise ValueError(f"{len(losses)} losses for the {len(horizons)} horizons {horizons}")
    return sum(w * v for w, v in zip(step_weights(kind, len(losses), horizons), losses))


def forecaster(fwd) -> torch.nn.Module | None:
    """The network behind ``fwd`` (itself, or under DistributedDataParallel or torch.compile) when it
    forecasts several steps in one pass (a ``forecast`` method, such as SimVP's), else None."""
    module = fwd
    while isinstance(getattr(module, "module", None) or getattr(module, "_orig_mod", None), torch.nn.Module):
        module = getattr(module, "module", None) or module._orig_mod
    return module if callable(getattr(module, "forecast", None)) else None


def rollout_losses(fwd, frames: torch.Tensor, cmds: torch.Tensor, targets: torch.Tensor, terms: dict[str, float],
                   pushforward: bool = False, precision: str = "fp32", flow=None,
                   echo_window: tuple[int, int] | None = None,
                   horizons: tuple[int, ...] | None = None) -> list[torch.Tensor]:
    """One loss per rollout step: step h predicts target h from the last n_in frames, measured or
    the model's own (clamped to [0, 1], as in evaluation) predictions. With ``pushforward`` all
    steps but the last run without gradient, and only the last step's loss is returned. A
    ``REFERENCE_TERMS`` term compares step h with the flow baseline's own h-step rollout from the
    measured frames, the forecast an evaluation compares it with: ``flow`` (last frame, command ->
    next frame, as ``EchoPT.flow_prior``) draws it.

    A model that forecasts several steps in one pass (:func:`forecaster`) is called once per block
    of up to its ``max_horizon`` steps (once, for every protocol horizon), through ``fwd`` with the
    block's length as a third argument, each block's context the measured frames or the previous
    block's predictions; with ``pushforward`` only the last block carries gradient, and its steps'
    losses are returned (one block: the same as without). ``echo_window`` is the ``echo`` term's.

    With ``horizons`` (increasing steps up to k) only the losses at those steps are returned; a
    model whose forward takes ``horizons`` (EchoWarp: each horizon its own slot) forecasts those
    alone when they fit one block."""
    n_in, k = frames.shape[1], targets.shape[1]
    if horizons is not None and pushforward:
        raise ValueError("horizons and pushforward do not go together: pushforward trains the last step alone")
    if horizons is not None and forecaster(fwd) is not None \
            and horizons[-1] <= forecaster(fwd).max_horizon and hasattr(forecaster(fwd), "forecast_at"):
        return _direct_losses(fwd, frames, cmds, targets, terms, precision, flow, echo_window, horizons)
    buf = list(frames.unbind(1))
    if not any(t in REFERENCE_TERMS for t in terms):
        flow = None
    elif flow is None:
        raise ValueError(f"the loss terms {', '.join(REFERENCE_TERMS)} need the flow baseline's warp")
    reference = frames[:, -1] if flow is not None else None
    many = forecaster(fwd)
    block = many.max_horizon if many is not None else 1
    losses = []
    h = 0
    while h < k:
        m = min(block, k - h)
        grad = torch.is_grad_enabled() and (not pushforward or h + m == k)
        ctx = torch.stack(buf[h:h + n_in], 1).contiguous(memory_format=torch.channels_last)
        with torch.set_grad_enabled(grad), autocast(ctx.device, precision):
            if many is None:
                preds = fwd(ctx, cmds[:, h:h + n_in + 1]).float()[:, None]  # the losses in fp32
            else:
                preds = fwd(ctx, cmds[:, h:h + n_in + m], m).float()
        for j, pred in enumerate(preds.unbind(1)):
            if flow is not None:
                with torch.no_grad():
                    reference = flow(reference.float(), cmds[:, h + j + n_in])
            if grad or not pushforward:
                losses.append(image_loss(pred, targets[:, h + j], terms, reference, echo_window))
            buf.append(pred.clamp(0, 1))
        h += m
    return losses if horizons is None else [losses[h - 1] for h in horizons]


def _direct_losses(fwd, frames, cmds, targets, terms, precision, flow, echo_window, horizons) -> list[torch.Tensor]:
    """rollout_losses at ``horizons`` from one pass that forecasts those alone (through ``fwd``, so
    that DistributedDataParallel sees the pass)."""
    n_in = frames.shape[1]
    ctx = frames.contiguous(memory_format=torch.channels_last)
    with autocast(ctx.device, precision):
        preds = fwd(ctx, cmds[:, :n_in + horizons[-1]], horizons=horizons).float()
    references = {}
    if any(t in REFERENCE_TERMS for t in terms):
        if flow is None:
            raise ValueError(f"the loss terms {', '.join(REFERENCE_TERMS)} need the flow baseline's warp")
        reference = frames[:, -1]
        with torch.no_grad():
            for j in range(horizons[-1]):
                reference = flow(reference.float(), cmds[:, j + n_in])
                references[j + 1] = reference
    return [image_loss(preds[:, i], targets[:, h - 1], terms, references.get(h), echo_window)
            for i, h in enumerate(horizons)]


@torch.no_grad()
def validation_loss(model: torch.nn.Module, batcher: WindowBatcher, index: WindowIndex, horizon: int = 1,
                    batch_size: int = 128, dist: Dist = Dist(), terms: dict[str, float] | None = None,
                    precision: str = "fp32", weights: str = "uniform",
                    echo_window: tuple[int, int] | None = None, horizons: tuple[int, ...] | None = None) -> float:
    """The training loss (``terms``, default MSE) per pixel over ``index``, over a rollout of
    ``horizon`` steps (the losses at ``horizons`` alone, where given) shared by ``weights``
    (``step_weights``); each process takes every world-th
    batch. The kept model is the best by the objective it was trained for: with a sharpness term,
    the MSE alone would prefer the blurrier weights. The training steps' freed memory goes back to
    the OS first, and validation's after (``release_free_memory``): its batches are twice a training
    batch, and would otherwise be laid out beside the steps' free blocks, not in them."""
    release_free_memory()
    model.eval()
    total, n = 0.0, 0
    starts = range(0, len(index), batch_size)
    for lo in list(starts)[dist.rank::dist.world]:
        b = batcher.gather(index, np.arange(lo, min(len(index), lo + batch_size)), horizon)
        losses = rollout_losses(model, b.frames, b.commands, b.targets, terms or {"mse": 1.0}, precision=precision,
                                flow=model.flow_prior, echo_window=echo_window, horizons=horizons)
        total += float(weighted_loss(losses, weights, horizons)) * len(b)
        n += len(b)
        del b, losses
        release_free_memory()
    model.train()
    total, n = dist.all_sum(total, n)
    return total / n
