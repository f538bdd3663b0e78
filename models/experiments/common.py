"""What both experiments share: predictors built once per worker process, a deterministic parallel
map over seeded tasks, bootstrap confidence intervals, and how their outputs are written."""

from __future__ import annotations

import concurrent.futures as cf
import json
import os
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np
from sonarset.store.atomic import atomic_text, publish_files, save_figure
from sonarset.perf import keep_freed_memory
from sonarset.pool import WorkerPool
from sonarset.errors import SonarSetError
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.report.numbers import finite_or_none
from sonarset.scoring.stats import bootstrap_ci
from sonarset.sim.runs import simulator_rig

from sonarset.models.predictor import CheckedPredictor

_PREDICTORS: dict = {}
#: The robot the experiments simulate, at its frame interval; the baselines warp by its frame
#: interval and sensor offset.
RIG = simulator_rig()


def predictor(spec: str, grid: SensorGrid, device: str = "cpu", precision: str = "auto") -> CheckedPredictor:
    """The predictor for a model spec (any the registry resolves: ``flow``, ``pretrained``,
    ``echopt:PATH``, a plugin's name, ``package.module:factory``), built once per process."""
    key = (spec, grid.model_dump_json(), device, precision)
    if key not in _PREDICTORS:
        from sonarset.models.registry import make_predictor

        _PREDICTORS[key] = make_predictor(spec, grid, RIG, device=device, precision=precision)
    return _PREDICTORS[key]


def learned_precision(preds: Iterable[CheckedPredictor]) -> dict[str, str]:
    """{predictor name: fp32 | bf16} of the learned predictors among ``preds``, as they compute."""
    return {p.name: p.precision for p in preds if p.precision is not None}


def experiment_processing(preds: Iterable[CheckedPredictor], requested: Processing | str | None = None) -> Processing:
    """The images an experiment simulates: those its learned models were trained on (their cards).

    ``requested`` (a profile name or settings) is checked against the cards: a model is never fed
    images unlike its training images, so a mismatch is refused, as are models trained on different
    images in one experiment. Without a learned model, the request or the simulator's default
    (``ertis``); the controller and the burst detector work on both profiles (``sonarset.sim.control``).
    """
    from sonarset.models.echopt.cards import card_processing

    if isinstance(requested, str):
        try:
            requested = Processing.named(requested)
        except ValueError as e:
            raise SonarSetError(f"processing: {e}", parameter="processing") from None
    found = {p.label: card_processing(p.card) for p in preds if p.card is not None}
    trained = next(iter(found.values()), None)
    if any(not p.same_images(trained) for p in found.values()):
        listed = ", ".join(f"{k}: {p.profile}" for k, p in found.items())
        raise SonarSetError(f"the models were trained on different images ({listed}); run them in separate experiments")
    if trained is None:
        return requested or Processing.ertis()
    if requested is not None and not requested.same_images(trained):
        raise SonarSetError(f"{', '.join(found)} was trained on {trained.profile} images, not {requested.profile}; "
                            f"leave processing to the model, or pass a model trained on {requested.profile} images",
                            parameter="processing")
    return trained


def _init_worker() -> None:
    keep_freed_memory()
    # Each process gets one core: the pool already fills the machine.
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass


def parallel_map(fn: Callable, tasks: Sequence, workers: int | None = None,
                 progress: Callable[[int, int], None] | None = None) -> list:
    """[fn(t) for t in tasks] in worker processes, results in task order whatever the scheduling.

    Every task carries its own seed, so the results do not depend on ``workers``. ``fn`` must be a
    module-level function (the pool spawns fresh interpreters).
    """
    workers = max(1, min(workers or os.cpu_count() or 1, len(tasks)))
    results: list = [None] * len(tasks)
    if workers == 1:
        for i, t in enumerate(tasks):
            results[i] = fn(t)
            if progress:
                progress(i + 1, len(tasks))
        return results
    with WorkerPool(workers, _init_worker) as pool:
        futures = {pool.submit(fn, t): i for i, t in enumerate(tasks)}
        for n, f in enumerate(cf.as_completed(futures), 1):
            results[futures[f]] = f.result()
            if progress:
                progress(n, len(tasks))
    return results


def mean_ci(x: np.ndarray, seed: int = 0) -> tuple[float, float, float]:
    """Mean and its bootstrap 95% CI (``sonarset.scoring.stats.bootstrap_ci``); NaNs dropped."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan"), float("nan")
    return (float(x.mean()), *bootstrap_ci(x, seed=seed))


def write_outputs(out: str | os.PathLike, metrics: dict, figure, figure_name: str, report: list[str],
                  extra: Callable[[Path], object] | None = None) -> Path:
    """An experiment's outputs in ``out`` (created): metrics.json (NaNs as null), the figure,
    whatever ``extra(folder)`` writes (an animation), and report.md from the report's lines."""
    def write(folder: Path) -> None:
        atomic_text(folder / "metrics.json", json.dumps(finite_or_none(metrics), indent=2) + "\n")
        save_figure(figure, folder / figure_name)
        if extra is not None:
            extra(folder)
        atomic_text(folder / "report.md", "\n".join(report) + "\n")

    return publish_files(out, write, last="report.md")
