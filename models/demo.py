"""The demo (``sonarset demo``): a model (by default the recommended shipped one, EchoWarp) against
the baselines, the noise ceiling and the observable ceiling, on a test run simulated afresh from a
seed the model never saw."""

from __future__ import annotations

import os
from typing import Callable

from sonarset.report.numbers import format_p, horizon_name
from sonarset.format.attrs import SensorGrid
from sonarset.sim import generate
from sonarset.sim.runs import simulator_rig
from sonarset.store.store import SonarStore, open_store

from sonarset.models.echopt.cards import card_processing, describe_images
from sonarset.models.eval.evaluate import evaluate
from sonarset.models.eval.result import EvalResult
from sonarset.models.predictor import CheckedPredictor
from sonarset.models.registry import BASELINES, make_predictor

#: How the demo's sentences name a model (its name otherwise).
TITLES = {"echopt": "EchoPT", "echowarp": "EchoWarp"}


def title(name: str) -> str:
    return TITLES.get(name, name)


def check_model(spec: str, device: str = "cpu", precision: str = "auto") -> CheckedPredictor:
    """The model ``spec`` names, made for the default grid and the simulated robot: a bad one fails
    before the simulation."""
    return make_predictor(spec, SensorGrid.default(), simulator_rig(), device=device, precision=precision)


def runs_in(model: CheckedPredictor, precision: str, device: str) -> str | None:
    """How the model computes, where it says (its ``precision``): "EchoPT runs in bf16 (CPU flags
    avx512_bf16)"; None for a model without that choice."""
    if model.precision is None:
        return None
    from sonarset.models.echopt.precision import describe_precision, resolve_device

    why = describe_precision(precision, resolve_device(device))  # what auto chose for a torch model, and why
    return f"{title(model.name)} runs in {why if why.split()[0] == model.precision else model.precision}"


def simulate_fresh_run(path: str | os.PathLike, *, minutes: float, seed: int,
                       progress: Callable[[str, int, int], None] | None = None) -> SonarStore:
    """One test run of ``minutes`` on the default grid, simulated from ``seed`` into a new store."""
    generate(path, runs=0, test_runs=1, minutes=minutes, seed=seed, grid=SensorGrid.default(),
             progress=progress)
    return open_store(path)


def images_note(model: CheckedPredictor, store: SonarStore) -> str | None:
    """Which images a learned model (one with a card) was trained on and which the fresh run holds."""
    if model.card is None:
        return None
    return (f"{title(model.name)} ({model.label}) was trained on {describe_images(card_processing(model.card))}; "
            f"the fresh run has {describe_images(store.processing)}")


def evaluate_fresh_run(store: SonarStore, spec: str, *, samples: int, device: str, precision: str = "auto",
                       progress: Callable[[str, int, int], None] | None = None) -> EvalResult:
    """The baselines and the model ``spec`` (the result's last predictor) on ``samples`` windows of
    the default horizons, with both ceilings."""
    return evaluate(store, list(dict.fromkeys([*BASELINES, spec])), samples=samples, device=device,
                    precision=precision, progress=progress, ceiling=True)


def model_against_flow(res: EvalResult) -> list[str]:
    """One line per metric: the model's (the result's last predictor) one-shot gain over the
    acoustic-flow warp and its p-values; nothing when the model is flow."""
    model = res.predictors[-1]
    if model == "flow":
        return []
    name = title(model)
    one = {c.metric: c for c in res.comparisons if c.horizon == 1 and {c.a, c.b} == {"flow", model}
           and c.metric in ("cc", "nrmsd")}
    lines = [f"one-shot {k}: {name} - flow = {(-c.mean_diff if c.a == 'flow' else c.mean_diff):+.4f}, "
             f"paired t-test p {format_p(c.t_paired_p)} (Holm {format_p(c.p_holm)}; with the windows' serial "
             f"correlation {format_p(c.t_hac_p)})" for k, c in one.items()]
    gap = res.gap_closed().get(model, {})
    longest = str(max(res.horizons))
    if gap.get(longest, {}).get("cc") is not None:
        s = res.summary()
        f1 = {m: s[m][longest]["echo_f1"]["mean"] for m in ("flow", model)}
        share = round(gap[longest]["cc"], 2) + 0.0  # + 0.0: one that rounds to zero is 0 %, not -0 %
        lines.append(f"{horizon_name(int(longest))}: {name} closes {share:.0%} of the CC gap between flow "
                     f"and the observable ceiling; echo F1 {f1[model]:.3f} vs flow {f1['flow']:.3f}")
    return lines
