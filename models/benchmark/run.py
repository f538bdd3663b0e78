"""A benchmark run: every model, with flow and the ceilings, on every dataset of a protocol, into
one results file (``run_benchmark``).

Each dataset is one ``evaluate`` call with every model together, so the models share its windows
and its paired tests. The paired t-tests of every model against the reference (flow) over the
whole file, every dataset, horizon and metric, are one family, Holm-corrected together: a claim
"beats flow on the benchmark" is tested once, however many cells it rests on.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from sonarset.report.numbers import finite_or_none, horizon_name
from sonarset.scoring.ceiling import CEILINGS
from sonarset.scoring.stats import HAC_SPANS, holm
from sonarset.store.atomic import atomic_text, publish_files

from sonarset.models.benchmark.machine import machine
from sonarset.models.benchmark.protocol import PROTOCOL_V1, PROTOCOL_V1_QUICK, Dataset, Protocol
from sonarset.models.benchmark.stores import cache_dir, ensure_store
from sonarset.models.eval.result import EvalResult

Progress = Callable[[str, int, int], None]
#: What the Holm correction of a results file covers, in words (its ``statistics`` entry).
HOLM_FAMILY = ("the tests of every model against {reference} on every dataset, horizon and metric of "
               "this results file ({n} tests), corrected together (Holm), the paired t-tests as p_holm and the "
               "serial-robust ones as p_hac_holm; each evaluation's own all-pairs "
               "correction is not used")


def run_benchmark(specs: list[str], out: str | os.PathLike, quick: bool = False, *, cache: str | os.PathLike | None = None,
                  device: str = "auto", precision: str = "auto", protocol: Protocol | None = None,
                  progress: Progress | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Score the models ``specs`` (the model specs the registry resolves, as eval takes them) on the protocol (v1, or
    v1-quick with ``quick``) and write ``out``/results.json and results.md; returns the results.

    The protocol's stores are generated on first use into ``cache`` (``cache_dir``) and reused
    after. Every model is loaded once first, so a bad spec fails before any simulation.
    ``progress(name, done, total)`` follows the simulation and the rollouts; ``log`` gets a line
    per store simulated and per dataset done.
    """
    from sonarset.models.echopt.precision import resolve_device

    protocol = protocol or (PROTOCOL_V1_QUICK if quick else PROTOCOL_V1)
    specs = method_specs(specs, protocol.reference)
    device = resolve_device(device)
    models = describe_models(specs, protocol, device, precision)
    folder = cache_dir(protocol, cache)
    t_start = time.perf_counter()
    stores: dict[str, tuple] = {}
    datasets: dict[str, dict] = {}
    for ds in protocol.datasets:
        if ds.store.name not in stores:
            stores[ds.store.name] = ensure_store(ds.store, protocol, folder, progress=_prefixed(progress, ds.store.name),
                                                 log=log)
        store, _ = stores[ds.store.name]
        res, seconds = evaluate_dataset(store, ds, specs, protocol, device, precision, progress)
        methods = dict(zip(specs, res.predictors, strict=True))  # evaluate keeps the specs' order
        for m in models:
            m["method"] = methods[m["spec"]]
        datasets[ds.name] = dataset_entry(res, ds, protocol, seconds)
        if log:
            log(dataset_line(ds.name, datasets[ds.name], protocol))
    results = {
        "protocol": {"name": protocol.name, "version": protocol.version, "definition": protocol.to_dict()},
        "models": models,
        "datasets": datasets,
        "stores": {name: info for name, (_, info) in stores.items()},
        "statistics": correct_over_file(datasets, protocol),
        "timings": timings(datasets, stores, time.perf_counter() - t_start),
        "machine": machine(device),
        "precision_requested": precision,
    }
    results = finite_or_none(results)
    write_results(results, out)
    return results


def method_specs(specs: list[str], reference: str) -> list[str]:
    """The specs to evaluate: the reference first, then the others in their order, each once."""
    out = [reference]
    for s in (s.strip() for s in specs):
        if s and s not in out:
            out.append(s)
    return out


def describe_models(specs: list[str], protocol: Protocol, device: str, precision: str) -> list[dict]:
    """Each model's spec, label, card and precision, from loading it once on the protocol's grid:
    an unknown spec or a checkpoint for another grid fails here, before any simulation."""
    from sonarset.sim.runs import simulator_rig
    from sonarset.models.registry import make_predictor

    models = []
    for spec in specs:
        p = make_predictor(spec, protocol.sensor_grid(), simulator_rig(), device=device, precision=precision)
        models.append({"method": p.name, "spec": spec, "label": p.label, "card": p.card, "precision": p.precision})
    return models


def evaluate_dataset(store, ds: Dataset, specs: list[str], protocol: Protocol, device: str, precision: str,
                     progress: Progress | None) -> tuple[EvalResult, float]:
    from sonarset.models.eval.evaluate import evaluate

    t0 = time.perf_counter()
    res = evaluate(store, specs, horizons=protocol.horizons, samples=protocol.samples, seed=protocol.eval_seed,
                   device=device, precision=precision, progress=_prefixed(progress, ds.name), ceiling=protocol.ceiling,
                   worlds=[ds.world] if ds.world else None)
    return res, time.perf_counter() - t0


def _prefixed(progress: Progress | None, prefix: str) -> Progress | None:
    if progress is None:
        return None
    return lambda name, done, total: progress(f"{prefix} {name}", done, total)


def metric_stats(x: np.ndarray) -> dict:
    """Mean, std (ddof 1) and n over the windows where the metric is defined."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return {"mean": float(x.mean()) if len(x) else None, "std": float(x.std(ddof=1)) if len(x) > 1 else None,
            "n": int(len(x))}


def dataset_entry(res: EvalResult, ds: Dataset, protocol: Protocol, seconds: float) -> dict:
    """One dataset of results.json: per horizon, each method's metrics, gap share and comparison
    to the reference, and the ceilings."""
    ref = protocol.reference
    gap = res.gap_closed(reference=ref)
    order = {m: i for i, m in enumerate(res.predictors)}
    vs, head_to_head = {}, {}
    for c in res.comparisons:
        if c.a == c.b:
            continue
        if ref in (c.a, c.b):
            model, other = (c.b, c.a) if c.a == ref else (c.a, c.b)
        else:  # two models: the later one in the file's order against the earlier
            model, other = (c.a, c.b) if order[c.a] > order[c.b] else (c.b, c.a)
        sign = 1.0 if c.a == model else -1.0  # as model - other
        lo, hi = (c.ci_low, c.ci_high) if sign > 0 else (-c.ci_high, -c.ci_low)
        test = {"n": c.n, "mean_diff": sign * c.mean_diff, "ci_low": lo, "ci_high": hi, "t_paired_p": c.t_paired_p,
                "p_holm": None, "wilcoxon_p": c.wilcoxon_p, "t_two_sample_p": c.t_two_sample_p,
                "t_hac_p": c.t_hac_p, "p_hac_holm": None}
        if other == ref:
            vs[(model, c.horizon, c.metric)] = test
        else:
            head_to_head.setdefault((model, c.horizon), {}).setdefault(other, {})[c.metric] = test
    horizons = {}
    for h in res.horizons:
        methods = {}
        for m in res.predictors:
            entry = {k: metric_stats(res.per_window[m][h][k]) for k in protocol.metrics}
            if m != ref:
                entry["gap_share"] = gap.get(m, {}).get(str(h))
                entry["vs_reference"] = {k: vs.get((m, h, k)) for k in protocol.metrics}
                if (m, h) in head_to_head:  # each earlier model of the file, as m - it
                    entry["vs_models"] = head_to_head[(m, h)]
            methods[m] = entry
        ceilings = {c: {k: metric_stats(res.per_window[c][h][k]) for k in protocol.metrics}
                    for c in CEILINGS if c in res.methods}
        horizons[str(h)] = {"methods": methods, "ceilings": ceilings}
    # n_in: the windows have room for that many input frames (the models'), which decides which
    # windows the seed draws: files of other contexts score other windows
    return {"about": ds.about, "store": ds.store.name, "world": ds.world, "runs": res.runs,
            "windows": len(res.window_ids), "n_in": res.n_in, "notes": res.notes, "ceiling_skipped": res.ceiling_skipped,
            "precision": res.precision, "seconds": {"evaluate": seconds, "methods": res.seconds},
            "horizons": horizons}


def correct_over_file(datasets: dict, protocol: Protocol) -> dict:
    """Holm over every comparison with the reference in the file, and apart over every comparison
    between two models; fills each one's ``p_holm`` (paired t-test) and ``p_hac_holm`` (serial-robust)."""
    tests = [c for d in datasets.values() for per_h in d["horizons"].values() for m in per_h["methods"].values()
             for c in (m.get("vs_reference") or {}).values() if c is not None]
    # the models against each other: a family of its own, so adding a model never weakens the
    # tests against the reference
    pairs = [c for d in datasets.values() for per_h in d["horizons"].values() for m in per_h["methods"].values()
             for per_other in (m.get("vs_models") or {}).values() for c in per_other.values() if c is not None]
    for family in (tests, pairs):
        for test, adjusted in (("t_paired_p", "p_holm"), ("t_hac_p", "p_hac_holm")):
            for c, p in zip(family, holm([np.nan if c.get(test) is None else c[test] for c in family])):
                c[adjusted] = p
    return {"reference": protocol.reference, "tests": len(tests),
            "holm_family": HOLM_FAMILY.format(reference=protocol.reference, n=len(tests)),
            "head_to_head_tests": len(pairs),
            "head_to_head_family": f"the tests of each model against every model before it in the file "
                                   f"(vs_models) on every dataset, horizon and metric of this file: {len(pairs)} tests",
            "meaning": "per dataset, horizon and metric, model - reference on the same windows: the mean "
                       "difference with a bootstrap 95% CI (BCa, 2000 resamples), the paired t-test, the "
                       "Wilcoxon signed-rank test, the paper's two-sample (Welch) t-test, and the paired test with "
                       "the windows' serial correlation in its variance (t_hac_p: Newey-West, Bartlett kernel "
                       f"reaching {HAC_SPANS} window spans within a run; Holm-corrected over the same family: "
                       "p_hac_holm)"}


def timings(datasets: dict, stores: dict, total: float) -> dict:
    per_method: dict[str, float] = {}
    for d in datasets.values():
        for m, s in d["seconds"]["methods"].items():
            per_method[m] = per_method.get(m, 0.0) + s
    return {"total": total, "generate": sum(info["seconds"] for _, info in stores.values()),
            "evaluate": sum(d["seconds"]["evaluate"] for d in datasets.values()), "per_method": per_method}


def dataset_line(name: str, entry: dict, protocol: Protocol) -> str:
    """'lab: 1000 windows in 61 s; CC AR-10 flow 0.561, echopt 0.690'."""
    h = str(max(protocol.horizons))
    cc = ", ".join(f"{m} {v['cc']['mean']:.3f}" if v["cc"]["mean"] is not None else f"{m} undefined"
                   for m, v in entry["horizons"][h]["methods"].items())
    return f"{name}: {entry['windows']} windows in {entry['seconds']['evaluate']:.0f} s; CC {horizon_name(int(h))} {cc}"


def write_results(results: dict, out: str | os.PathLike) -> Path:
    """results.json and results.md in ``out``, as one unit: a reader, or a kill, never finds a
    results.json beside the Markdown of another run, nor half a file."""
    from sonarset.models.benchmark.tables import results_markdown

    def write(folder: Path) -> None:
        atomic_text(folder / "results.md", results_markdown(results))
        atomic_text(folder / "results.json", json.dumps(results, indent=2) + "\n")

    return publish_files(out, write, last="results.json")
