"""Are protocol v1's unresolved cells a question of its power? A projection, and a replication on fresh runs.

    python bench/bench_replicate.py --models flow,echopt:pretrained,pretrained
                                    [--results docs/results/benchmark-v1.json] [--seed-offsets 1,2] [--samples 1000]

A cell (dataset x horizon x CC, NRMSD, echo F1) is unresolved where a model is not better than an
earlier one at Holm p < 0.001. Two questions tell a real tie from a sample too small:

1. **Projection** (from the results file alone): at the observed mean difference and its spread,
   how many windows would the paired t-test (and the serial-robust one, with its variance
   inflation at the file's windows, more runs of the same length) need to pass the Bonferroni
   bound of the cell's Holm family, p < 0.001 / m (which passes Holm whatever the cell's rank: a
   sufficient, conservative target)? The observed effect is itself uncertain: a fresh sample decides.
2. **Replication**: the protocol's datasets simulated afresh from other master seeds (the same
   worlds, minutes, images, windows and horizons; each seed + each of ``--seed-offsets``, one
   replication per offset), every model evaluated as ``sonarset benchmark`` does (ceilings
   aside), and the cells counted in v1, in each replication and with every sample's windows
   pooled (independent runs: as many times the windows per dataset as there are samples), each
   with the file's Holm families, by the paired and by the serial-robust test.

Protocol v1 is not changed: its verdicts are its own; this measures how far each unresolved cell
is from resolving, and whether a fresh sample agrees.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from pathlib import Path

import numpy as np

from bench_serial import METRICS, passes

from sonarset.models.benchmark.protocol import PROTOCOL_V1, Protocol
from sonarset.report.numbers import finite_or_none, format_p, format_value
from sonarset.models.benchmark.tables import unresolved_table
from sonarset.models.benchmark.run import correct_over_file, dataset_entry, evaluate_dataset, method_specs
from sonarset.models.benchmark.stores import cache_dir, ensure_store
from sonarset.scoring.stats import WindowPlaces, compare

BAR = 1e-3


def replication(protocol: Protocol, offset: int) -> Protocol:
    """The protocol with every store simulated from its master seed + ``offset`` (a new cache folder)."""
    stores = {name: dataclasses.replace(r, name=f"{r.name}-seed{r.seed + offset}", seed=r.seed + offset)
              for name, r in protocol.stores().items()}
    datasets = tuple(dataclasses.replace(d, store=stores[d.store.name],
                                         about=f"{d.about}, replicated from master seed {d.store.seed + offset}")
                     for d in protocol.datasets)
    return dataclasses.replace(protocol, version=f"{protocol.version}-replication", datasets=datasets, ceiling=False)


def sample_name(offset: int) -> str:
    return f"replication +{offset}"


def evaluate_all(protocol: Protocol, specs: list[str], precision: str) -> dict:
    folder, stores, results = cache_dir(protocol), {}, {}
    for ds in protocol.datasets:
        if ds.store.name not in stores:
            stores[ds.store.name] = ensure_store(ds.store, protocol, folder)[0]
        results[ds.name] = evaluate_dataset(stores[ds.store.name], ds, specs, protocol, "cpu", precision, None)
    return results


def pooled_entry(parts: list, protocol: Protocol) -> dict:
    """A dataset entry (``vs_reference``, ``vs_models``, as results.json has them) from the windows of
    several evaluations of the same models pooled; each evaluation's runs kept apart."""
    first = parts[0]
    order = {m: i for i, m in enumerate(first.predictors)}
    ids = [(f"{i}:{run}", k) for i, res in enumerate(parts) for run, k in res.window_ids]
    places = WindowPlaces.of(ids, first.n_in + max(first.horizons))
    horizons = {}
    for h in first.horizons:
        methods = {}
        for model in first.predictors:
            if order[model] == 0:
                continue
            entry = {"vs_reference": {}, "vs_models": {}}
            for other in first.predictors[:order[model]]:
                tests = {}
                for k in protocol.metrics:
                    a, b = (np.concatenate([res.per_window[m][h][k] for res in parts]) for m in (model, other))
                    # the CIs are not reported here: a short bootstrap
                    c = compare(a, b, metric=k, horizon=h, names=(model, other), n_resamples=200, windows=places)
                    tests[k] = {**{f: getattr(c, f) for f in ("n", "mean_diff", "t_paired_p", "t_hac_p")},
                                "p_holm": None, "p_hac_holm": None}
                if other == protocol.reference:
                    entry["vs_reference"] = tests
                else:
                    entry["vs_models"][other] = tests
            methods[model] = entry
        horizons[str(h)] = {"methods": methods}
    return {"horizons": horizons}


def cell_test(datasets: dict, reference: str, model: str, other: str, cell: str) -> dict:
    """The test of ``model`` against ``other`` in ``cell`` (dataset/horizon/metric) of a file's datasets."""
    ds, h, k = cell.split("/")
    v = datasets[ds]["horizons"][h]["methods"][model]
    return (v["vs_reference"] if other == reference else v["vs_models"][other])[k]


def projection(results: dict) -> None:
    st = results["statistics"]
    print(f"\n## Projection from the results file (Bonferroni bound {BAR:g} / {st['tests']} against "
          f"{st['reference']}, / {st.get('head_to_head_tests', st['tests'])} head to head)\n")
    print(unresolved_table(results, BAR))


def counts(datasets: dict, protocol: Protocol, key: str) -> dict:
    cells = len(protocol.datasets) * len(protocol.horizons) * len(METRICS)
    return {pair: (cells - len(fails), fails) for pair, fails in passes(datasets, protocol.reference, key).items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="flow,echopt:pretrained,pretrained")
    ap.add_argument("--results", default="docs/results/benchmark-v1.json", help="protocol v1 results file to project from")
    ap.add_argument("--seed-offsets", default="1", help="one replication per offset of the master seeds")
    ap.add_argument("--precision", default="auto")
    ap.add_argument("--samples", type=int, default=PROTOCOL_V1.samples, help="windows per dataset (fewer: a quick look)")
    ap.add_argument("--projection-only", action="store_true")
    ap.add_argument("--out", help="a JSON file for every sample's tests (v1, each replication, pooled)")
    args = ap.parse_args()
    offsets = [int(x) for x in args.seed_offsets.split(",")]
    if 0 in offsets or len(set(offsets)) != len(offsets):  # v1's own runs, or one run twice, are no fresh sample
        ap.error(f"--seed-offsets {args.seed_offsets}: distinct offsets other than 0")
    t0 = time.perf_counter()
    projection(json.loads(Path(args.results).read_text()))
    if args.projection_only:
        return
    v1 = dataclasses.replace(PROTOCOL_V1, samples=args.samples, ceiling=False)
    specs = method_specs(args.models.split(","), v1.reference)
    runs = {"v1": evaluate_all(v1, specs, args.precision)}
    for offset in offsets:
        runs[sample_name(offset)] = evaluate_all(replication(v1, offset), specs, args.precision)
    files, statistics = {}, {}
    for name, results in runs.items():
        files[name] = {ds: dataset_entry(res, d, v1, seconds)
                       for d, (ds, (res, seconds)) in zip(v1.datasets, results.items())}
        statistics[name] = correct_over_file(files[name], v1)
    files["pooled"] = {ds: pooled_entry([results[ds][0] for results in runs.values()], v1) for ds in runs["v1"]}
    statistics["pooled"] = correct_over_file(files["pooled"], v1)
    if args.out:  # first: what follows only prints
        Path(args.out).write_text(json.dumps({"seed_offsets": offsets, "samples": args.samples, "models": specs,
                                              "statistics": statistics, "files": finite_or_none(files)}, indent=1))
    print(f"\n# bench_replicate  {platform.node()}  {time.strftime('%Y-%m-%d')}  {time.perf_counter() - t0:.0f} s  "
          f"{args.samples} windows per dataset and sample; replications at master seeds "
          f"{', '.join(f'+{o}' for o in offsets)}")
    table = {(name, key): counts(datasets, v1, key) for name, datasets in files.items()
             for key in ("p_holm", "p_hac_holm")}
    pairs = list(next(iter(table.values())))
    labels = {"v1": "protocol v1's", **{sample_name(o): f"the replication at seeds +{o}" for o in offsets},
              "pooled": f"all {len(runs)}, pooled"}
    cells = len(v1.datasets) * len(v1.horizons) * len(METRICS)
    print(f"\n## Cells (of {cells}) in which the model is better at Holm p < {BAR:g}\n")
    print("| windows | test | " + " | ".join(f"{m} vs {o}" for m, o in pairs) + " |")
    print("|---|---|" + "---|" * len(pairs))
    for (name, key), per_pair in table.items():
        print(f"| {labels[name]} | {'paired' if key == 'p_holm' else 'serial-robust'} | "
              + " | ".join(str(per_pair[p][0]) for p in pairs) + " |")
    print("\n## The cells protocol v1 leaves unresolved, in each sample (mean difference, Holm p paired / "
          "serial-robust)\n")
    print("| model vs other | cell | " + " | ".join(labels.values()) + " |")
    print("|---|---|" + "---|" * len(labels))
    for (model, other), open_cells in passes(files["v1"], v1.reference, "p_holm").items():
        for cell in open_cells:
            tests = [cell_test(files[name], v1.reference, model, other, cell) or {} for name in labels]
            print(f"| {model} vs {other} | {cell} | " + " | ".join(
                f"{format_value(t.get('mean_diff'), '+.4f', 'untested')} (n {t.get('n', 0)}), "
                f"{format_p(t.get('p_holm'))} / {format_p(t.get('p_hac_holm'))}" for t in tests) + " |")
    print("\n## The cells not passed\n")
    for (name, key), per_pair in table.items():
        for pair, (_, fails) in per_pair.items():
            print(f"- {name}, {'paired' if key == 'p_holm' else 'serial-robust'}, {pair[0]} vs {pair[1]}: "
                  f"{', '.join(fails) or 'none'}")


if __name__ == "__main__":
    main()
