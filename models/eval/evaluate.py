"""The evaluation engine: every method on the same seeded windows, the paper's metrics, statistics.

``evaluate`` is the library API behind ``sonarset eval``; it returns an :class:`EvalResult`
(models/eval/result.py), which models/eval/report.py renders (metrics.json, per_window.csv,
report.md and the figures). The rollouts and their scores are models/eval/scores.py's.
"""

from __future__ import annotations

import concurrent.futures as cf
import os
from itertools import combinations
from typing import Callable

import numpy as np

from sonarset.errors import FormatError, SonarSetError
from sonarset.format.arrays import FRAME_INTERVAL_TOLERANCE
from sonarset.format.attrs import RobotRig
from sonarset.scoring.ceiling import CEILINGS
from sonarset.scoring.echoes import EchoMatching
from sonarset.scoring.stats import Comparison, WindowPlaces, compare, holm
from sonarset.store.store import SonarStore
from sonarset.stream import window_bank
from sonarset.windows import N_IN, FrameBank, RunLayout, WindowBatcher, WindowIndex

from sonarset.models.predictor import CheckedPredictor, Predictor, as_predictor
from sonarset.models.registry import HORIZONS
from sonarset.models.eval.result import METRICS, EvalResult, undefined_notes
from sonarset.models.eval.scores import Scores, score_ceilings


def baseline_rig(store: SonarStore, bank: FrameBank | RunLayout) -> tuple[RobotRig, str | None]:
    """The robot the baselines turn commands into image motion with, and a note when it is assumed.

    Its frame interval is the median spacing of the evaluated runs' time stamps, which the spec
    makes normative; the declared interval (the rig's, else 1 / frame rate) must agree with it
    within FRAME_INTERVAL_TOLERANCE, or the store is refused: naive and flow would warp every frame
    by the wrong step, silently. Without a rig the sensor is assumed on the wheel axle, with a note.
    """
    rig = store.rig
    declared = rig.frame_interval_s if rig is not None else 1.0 / store.attrs.frame_rate_hz
    measured = bank.frame_interval_s
    if measured is not None and abs(measured - declared) > FRAME_INTERVAL_TOLERANCE * declared:
        what = "rig.frame_interval_s" if rig is not None else f"frame_rate_hz {store.attrs.frame_rate_hz:g}"
        raise FormatError(f"{store.location}: the time stamps of runs {', '.join(bank.run_names)} are "
                          f"{measured:.6g} s apart (median), but the store declares {declared:g} s frames "
                          f"({what}); fix the store's frame rate or its time stamps")
    dt = measured if measured is not None else declared
    if rig is not None:
        return rig.model_copy(update={"frame_interval_s": dt}), None
    return RobotRig(frame_interval_s=dt, sensor_offset_m=0.0), (
        f"note: the store records no robot rig: naive and flow use the time stamps' {dt:.6g} s "
        "frames and assume the sensor on the wheel axle")


def evaluate(
    store: SonarStore,
    model_specs: list[str],
    *,
    horizons: tuple[int, ...] = HORIZONS,
    samples: int = 1000,
    split: str = "test",
    seed: int = 0,
    batch_size: int = 64,
    device: str = "cpu",
    precision: str = "auto",
    predictors: dict[str, Predictor] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    ceiling: bool = False,
    worlds: list[str] | None = None,
    echo_matching: EchoMatching | None = None,
    stream: bool = False,
) -> EvalResult:
    """Evaluate every model on the same ``samples`` windows of ``split``, for every horizon.

    ``model_specs`` are names the registry resolves (models/registry.py: persistence, naive, flow,
    pretrained, ``KIND:PATH``, a plugin's name, ``package.module:factory``); ``predictors`` adds
    predictor objects (anything that answers models/predictor.py's protocol) under their keys.

    Windows are drawn once (seeded) among those with room for the longest horizon, so every
    method and horizon sees the same starting points; each method is rolled out once to the
    longest horizon and scored at every requested one (a method that forecasts each horizon
    directly, ``forecast_at``, forecasts the requested ones alone). ``worlds`` keeps only the runs of those
    world families (``source.world``).

    With ``ceiling``, the target frames of simulated runs are also re-rendered from their recorded
    world and poses with an independent noise draw (seeded by ``seed``) and scored as the method
    ``"ceiling"``: the noise ceiling, how much of a frame is predictable at all; and re-rendered
    from only the reflectors each window's context frames heard, as ``"observable"``: how much
    of it the context could know (``sonarset.scoring.ceiling``). Runs they cannot re-render get NaN there,
    a reason in ``ceiling_skipped`` and a line in ``notes``; with none, the rows are omitted.

    Every method is also scored on the echoes it draws (``echo_matching``, default
    ``EchoMatching()``): detection precision, recall and F1, and the position error of matched echoes.

    With ``stream``, only the frames of the drawn windows are read (``sonarset.stream.window_bank``)
    instead of every frame of the split: the same windows and numbers, in memory bounded by
    ``samples``, not by the store.
    """
    horizons = tuple(sorted(set(int(h) for h in horizons)))
    if not horizons or horizons[0] < 1:
        raise SonarSetError("horizons must be positive integers", parameter="horizons")
    echo_matching = echo_matching or EchoMatching()
    # images as float32 (the metrics' precision): every frame of the split, or (stream) only the
    # frames of the windows drawn below
    bank = (RunLayout.of(store, split=split, worlds=worlds) if stream
            else FrameBank.from_store(store, split=split, image_dtype=np.float32, worlds=worlds))
    rig, note = baseline_rig(store, bank)
    notes = [note] if note else []
    preds, model_notes = _predictors(store, model_specs, rig, device, precision, predictors)
    notes += model_notes
    index = _windows(store, bank, split, window_frames(preds), horizons[-1], samples, seed)
    if stream:
        bank = window_bank(store, bank, index, np.float32)
    ids = [(bank.run_names[j], k) for j, k in (index.locate(i) for i in range(len(index)))]
    scores = Scores.of(preds, len(index), horizons, store.grid, echo_matching)
    skipped: dict[str, str] = {}
    with cf.ThreadPoolExecutor(1) as helper:
        # The ceiling renders (compiled, GIL released) beside the rollouts: it shares nothing with
        # them, and it fills the cycles a learned model's threads leave idle.
        ceiling_job = helper.submit(score_ceilings, store, bank, index, ids, horizons, seed, batch_size,
                                    echo_matching, progress) if ceiling else None
        examples = scores.roll_out(WindowBatcher.of(bank), index, preds, batch_size, progress)
        examples["window"] = ids[0]
    if ceiling_job is not None:
        ceiling_scores, ceiling_seconds, skipped = ceiling_job.result()
        notes += [f"ceiling: run {r} not re-rendered: {why}" for r, why in skipped.items()]
        if ceiling_scores is None:
            notes.append(f"ceiling: no run of split {split!r} can be re-rendered; the ceiling rows are omitted")
        else:
            for name, rows in ceiling_scores.items():
                scores.per_window[name] = rows
                scores.seconds[name] = ceiling_seconds[name]
    result = EvalResult(store.location, split, bank.run_names, list(horizons), list(scores.per_window),
                        index.starts, ids, scores.per_window, seconds=scores.seconds, examples=examples, notes=notes,
                        ceiling_skipped=skipped, step_peak=scores.step_peak, step_energy=scores.step_energy,
                        target_peak=scores.target_peak, target_energy=scores.target_energy, n_in=index.n_in,
                        precision={m: p.precision for m, p in preds.items() if p.precision is not None},
                        echo_matching=echo_matching, worlds=list(worlds) if worlds else None,
                        direct=[m for m, p in preds.items() if p.forecasts_directly])
    result.notes += undefined_notes(result)
    n_images = len(index) * len(horizons)
    result.notes += [f"{m}: {k} of its {n_images} forecast images hold values outside [0, 1], the "
                     "energyscapes' range; they are scored as they are" for m, k in scores.outside_unit.items() if k]
    result.comparisons = _compare_all(result, seed)
    return result


def _predictors(store: SonarStore, model_specs: list[str], rig: RobotRig, device: str, precision: str,
                given: dict[str, Predictor] | None) -> tuple[dict[str, CheckedPredictor], list[str]]:
    """The predictors by name (``given`` first, under their keys, then ``model_specs``), checked
    against the protocol, and notes on learned models meeting other images than they were trained
    on and on plugins a built-in name shadows."""
    from sonarset.models.echopt.card_images import training_notices
    from sonarset.models.registry import make_predictor, shadowed_plugins

    preds: dict[str, CheckedPredictor] = {}
    for name, p in (given or {}).items():
        if name in CEILINGS:
            raise SonarSetError(f"predictor {name!r}: that name is the {name} row's (not a predictor); "
                                "pass the model under another name")
        preds[name] = as_predictor(p, name)
        preds[name].name = name
    for spec in dict.fromkeys(model_specs):
        p = make_predictor(spec, store.grid, rig, device=device, precision=precision)
        taken = preds.keys() | set(CEILINGS)  # the ceilings' rows are named so too
        if p.name in taken:  # several checkpoints: each under its own label (echopt RUN/model), else its spec
            p.name = p.label if p.label not in taken else spec
            if p.name in taken:
                raise SonarSetError(f"model {spec!r}: another model is named {p.name!r}; evaluate them apart",
                                    parameter="model_specs")
        preds[p.name] = p
    shadowed = shadowed_plugins()
    notes = [shadowed[s.partition(":")[0]] for s in dict.fromkeys(model_specs) if s.partition(":")[0] in shadowed]
    for p in preds.values():
        if p.card is not None:
            notes += training_notices(p.label, p.card, store.processing, store.rig, rig.frame_interval_s)
    if not preds:
        raise SonarSetError("no models to evaluate")
    return preds, notes


def window_frames(preds: dict[str, CheckedPredictor]) -> int:
    """Input frames per window: the one count all predictors were built for (a learned model's is
    in its config); predictors that read only the last frame take any."""
    counts = {p.n_in for p in preds.values() if not p.any_context}
    if not counts:
        return N_IN
    if len(counts) != 1:
        raise SonarSetError("the models take different numbers of input frames ("
                            + ", ".join(f"{name} {p.n_in}" for name, p in preds.items() if not p.any_context)
                            + "); evaluate them apart")
    return counts.pop()


def _windows(store: SonarStore, bank: FrameBank | RunLayout, split: str, n_in: int, horizon: int, samples: int,
             seed: int) -> WindowIndex:
    """``samples`` windows (seeded) among those with room for ``horizon`` targets."""
    index = WindowIndex.build(bank, n_in, horizon)
    if len(index) == 0:
        raise SonarSetError(f"{store.location}: split {split!r} has no run long enough for horizon {horizon} "
                            f"(needs {index.span} frames)")
    return index.sample(samples, seed)


def _compare_all(res: EvalResult, seed: int) -> list[Comparison]:
    pairs = [(h, a, b, k) for h in res.horizons for a, b in combinations(res.predictors, 2)  # ceilings: no predictors
             for k in METRICS]
    # one reach for every horizon: what correlates windows beyond their shared frames is the scene
    # the robot drives through, the same at every horizon
    places = WindowPlaces.of(res.window_ids, res.n_in + max(res.horizons))

    def one(pair: tuple) -> Comparison:
        h, a, b, k = pair
        return compare(res.per_window[a][h][k], res.per_window[b][h][k], metric=k, horizon=h, names=(a, b), seed=seed,
                       windows=places)

    # the bootstraps (168 in the demo) spend their time in NumPy, which releases the GIL; each is
    # seeded on its own, so the threads change no value
    with cf.ThreadPoolExecutor(min(4, os.cpu_count() or 1)) as pool:
        comps = list(pool.map(one, pairs))
    for c, p, p_hac in zip(comps, holm([c.t_paired_p for c in comps]), holm([c.t_hac_p for c in comps])):
        c.p_holm, c.p_hac_holm = p, p_hac
    return comps
