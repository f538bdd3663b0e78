"""The demo (``sonarset demo``): the shipped EchoPT against the baselines, the noise ceiling and
the observable ceiling, on a test run simulated afresh from a seed the model never saw."""

from __future__ import annotations

import os
from typing import Callable

from sonarset.report.numbers import format_p, horizon_name
from sonarset.format.attrs import SensorGrid
from sonarset.sim import generate
from sonarset.store.store import SonarStore, open_store

from sonarset.models.echopt.cards import card_processing, describe_images, read_card
from sonarset.models.echopt.checkpoint import load_checkpoint
from sonarset.models.eval.evaluate import evaluate
from sonarset.models.eval.result import EvalResult
from sonarset.models.registry import BASELINES


def check_model(model: str) -> None:
    """Load the checkpoint (or ONNX export) ``model`` on the default grid: a bad one fails before
    the simulation."""
    if str(model).endswith(".onnx"):
        from sonarset.models.echopt.onnx_runtime import load_onnx_predictor

        load_onnx_predictor(model, SensorGrid.default())
    else:
        load_checkpoint(model, SensorGrid.default())


def runs_in(model: str, precision: str, device: str) -> str:
    """How EchoPT will compute: "EchoPT runs in bf16 (CPU flags avx512_bf16)"."""
    if str(model).endswith(".onnx"):
        return "EchoPT runs in fp32 (onnxruntime)"
    from sonarset.models.echopt.precision import describe_precision, resolve_device

    return f"EchoPT runs in {describe_precision(precision, resolve_device(device))}"


def simulate_fresh_run(path: str | os.PathLike, *, minutes: float, seed: int,
                       progress: Callable[[str, int, int], None] | None = None) -> SonarStore:
    """One test run of ``minutes`` on the default grid, simulated from ``seed`` into a new store."""
    generate(path, runs=0, test_runs=1, minutes=minutes, seed=seed, grid=SensorGrid.default(),
             progress=progress)
    return open_store(path)


def images_note(model: str, store: SonarStore) -> str:
    """Which images the model was trained on and which the fresh run holds."""
    return (f"EchoPT ({model}) was trained on {describe_images(card_processing(read_card(model)))}; "
            f"the fresh run has {describe_images(store.processing)}")


def evaluate_fresh_run(store: SonarStore, model: str, *, samples: int, device: str, precision: str = "auto",
                       progress: Callable[[str, int, int], None] | None = None) -> EvalResult:
    """The baselines and EchoPT on ``samples`` windows of the default horizons, with both ceilings."""
    return evaluate(store, [*BASELINES, f"echopt:{model}"], samples=samples, device=device, precision=precision,
                    progress=progress, ceiling=True)


def echopt_against_flow(res: EvalResult) -> list[str]:
    """One line per metric: EchoPT's one-shot gain over the acoustic-flow warp and its p-values."""
    one = {c.metric: c for c in res.comparisons if c.horizon == 1 and {c.a, c.b} == {"flow", "echopt"}
           and c.metric in ("cc", "nrmsd")}
    lines = [f"one-shot {k}: EchoPT - flow = {(-c.mean_diff if c.a == 'flow' else c.mean_diff):+.4f}, "
             f"paired t-test p {format_p(c.t_paired_p)} (Holm {format_p(c.p_holm)})" for k, c in one.items()]
    gap = res.gap_closed().get("echopt", {})
    longest = str(max(res.horizons))
    if gap.get(longest, {}).get("cc") is not None:
        s = res.summary()
        f1 = {m: s[m][longest]["echo_f1"]["mean"] for m in ("flow", "echopt")}
        lines.append(f"{horizon_name(int(longest))}: EchoPT closes {gap[longest]['cc']:.0%} of the CC gap between flow and the "
                     f"observable ceiling; echo F1 {f1['echopt']:.3f} vs flow {f1['flow']:.3f}")
    return lines
