"""Do protocol v1's significance claims hold when neighbouring windows are correlated?

    python bench/bench_serial.py --models flow,echopt:pretrained,pretrained

Windows drawn from one run share frames and scene, so their paired differences are not
independent. This evaluates the models on protocol v1's datasets (the benchmark's stores, windows
and Holm families), then counts, per model, the cells (dataset x horizon x CC, NRMSD, echo F1) in
which it is better than each earlier model at Holm p < 0.001: by the paired t-test (the protocol's
test) and by the serial-correlation-robust test (``sonarset.scoring.stats.hac_t_p``) with its kernel
reaching 1, 2, 4 (the default, ``HAC_SPANS``) and 8 window spans. It also prints the lag-one
autocorrelation of the CC differences per horizon, and the cells the default robust test no
longer passes.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import numpy as np

from sonarset.models.benchmark.protocol import PROTOCOL_V1
from sonarset.models.benchmark.run import correct_over_file, dataset_entry, evaluate_dataset, method_specs
from sonarset.models.benchmark.stores import cache_dir, ensure_store
from sonarset.scoring.stats import HAC_SPANS, WindowPlaces, hac_t_p, hac_variance

METRICS = ("cc", "nrmsd", "echo_f1")
SPANS = (1, 2, HAC_SPANS, 8)
BLOCKS = 30


def in_order(res) -> np.ndarray:
    """The windows' indices sorted by run, then start frame."""
    return np.lexsort(([k for _, k in res.window_ids], [r for r, _ in res.window_ids]))


def lag_one(res, a: str, b: str, h: int) -> float:
    """The lag-one autocorrelation of a - b's CC differences, windows in order of their start (the
    next window drawn, about 3 frames on in protocol v1); pairs with an undefined value left out."""
    d = (res.per_window[a][h]["cc"] - res.per_window[b][h]["cc"])[in_order(res)]
    dc = d - np.nanmean(d)
    both = np.isfinite(dc[1:]) & np.isfinite(dc[:-1])
    return float((dc[1:] * dc[:-1])[both].sum() / np.nansum(dc * dc))


def differences(res, c) -> tuple[np.ndarray, np.ndarray]:
    """c.a - c.b per window where both are defined, and the mask of those windows."""
    a, b = res.per_window[c.a][c.horizon][c.metric], res.per_window[c.b][c.horizon][c.metric]
    ok = np.isfinite(a) & np.isfinite(b)
    return (a - b)[ok], ok


def robust_p(res, places: WindowPlaces) -> None:
    """Each comparison's ``t_hac_p`` again, with ``places``' reach."""
    for c in res.comparisons:
        d, ok = differences(res, c)
        c.t_hac_p = hac_t_p(d, places.frames[ok], places.runs[ok], places.bandwidth)


def t_statistics(res, a: str, b: str, h: int, span: int) -> list[float]:
    """a - b's CC t statistic at horizon h: paired, robust at each of SPANS, and by batch means
    over BLOCKS contiguous stretches of the windows (a check that needs no kernel)."""
    c = next(c for c in res.comparisons if c.metric == "cc" and c.horizon == h and {c.a, c.b} == {a, b})
    d, ok = differences(res, c)
    d = d if c.a == a else -d
    places = WindowPlaces.of(res.window_ids, span)
    out = [d.mean() / np.sqrt(d.var(ddof=1) / len(d))]
    out += [d.mean() / np.sqrt(hac_variance(d, places.frames[ok], places.runs[ok], k * span)) for k in SPANS]
    stretch = d[np.lexsort((places.frames[ok], places.runs[ok]))]
    means = np.array([x.mean() for x in np.array_split(stretch, BLOCKS)])
    return out + [means.mean() / np.sqrt(means.var(ddof=1) / BLOCKS)]


def passes(datasets: dict, reference: str, key: str) -> dict[tuple[str, str], list[str]]:
    """(model, other) -> the cells in which model is not better at ``key`` < 0.001."""
    out: dict[tuple[str, str], list[str]] = {}
    for ds, entry in datasets.items():
        for h, per_h in entry["horizons"].items():
            for m, v in per_h["methods"].items():
                others = dict(v.get("vs_models") or {})
                if v.get("vs_reference"):  # every model but the reference itself
                    others[reference] = v["vs_reference"]
                for other, tests in others.items():
                    fails = out.setdefault((m, other), [])
                    for k in METRICS:
                        t = tests.get(k)
                        if t is None:  # not tested: not passed
                            fails.append(f"{ds}/{h}/{k}")
                            continue
                        better = t["mean_diff"] < 0 if k == "nrmsd" else t["mean_diff"] > 0
                        if not (better and t[key] is not None and t[key] < 1e-3):
                            fails.append(f"{ds}/{h}/{k}")
    return out


def evaluate_protocol(name: str, doc: str):
    """Parse the bench's options (--models, --precision, --samples), evaluate the models on protocol
    v1's datasets and print the bench's header line; (protocol, {dataset: (EvalResult, seconds)})."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--models", default="flow,echopt:pretrained,pretrained")
    ap.add_argument("--precision", default="auto")
    ap.add_argument("--samples", type=int, default=PROTOCOL_V1.samples, help="windows per dataset (fewer: a quick look)")
    args = ap.parse_args()
    protocol = dataclasses.replace(PROTOCOL_V1, samples=args.samples)
    specs = method_specs(args.models.split(","), protocol.reference)
    folder, stores, results = cache_dir(protocol), {}, {}
    t0 = time.perf_counter()
    for ds in protocol.datasets:
        if ds.store.name not in stores:
            stores[ds.store.name] = ensure_store(ds.store, protocol, folder)[0]
        results[ds.name] = evaluate_dataset(stores[ds.store.name], ds, specs, protocol, "cpu", args.precision, None)
    print(f"# {name}  {platform.node()}  {time.strftime('%Y-%m-%d')}  {time.perf_counter() - t0:.0f} s  "
          f"protocol {protocol.version}, {protocol.samples} windows per dataset")
    return protocol, results


def main() -> None:
    protocol, results = evaluate_protocol("bench_serial", __doc__)
    res0 = next(iter(results.values()))[0]
    span = res0.n_in + max(protocol.horizons)
    cells = len(protocol.datasets) * len(protocol.horizons) * len(METRICS)
    counts: dict[str, dict] = {}
    for spans in (0, *SPANS):
        datasets = {}
        for ds in protocol.datasets:
            res, seconds = results[ds.name]
            if spans:
                robust_p(res, dataclasses.replace(WindowPlaces.of(res.window_ids, span), bandwidth=spans * span))
            datasets[ds.name] = dataset_entry(res, ds, protocol, seconds)
        correct_over_file(datasets, protocol)
        counts[spans] = passes(datasets, protocol.reference, "p_holm" if not spans else "p_hac_holm")
    pairs = list(counts[0])
    print(f"\nCells (of {cells}) in which the model is better at Holm p < 0.001:\n")
    print("| test | " + " | ".join(f"{m} vs {o}" for m, o in pairs) + " |")
    print("|---|" + "---|" * len(pairs))
    for spans, fails in counts.items():
        label = "paired t-test" if not spans else f"robust, {spans} span{'s' * (spans > 1)} ({spans * span} frames)"
        print(f"| {label} | " + " | ".join(str(cells - len(fails[p])) for p in pairs) + " |")
    for p in pairs:
        lost = sorted(set(counts[HAC_SPANS][p]) - set(counts[0][p]))
        gained = sorted(set(counts[0][p]) - set(counts[HAC_SPANS][p]))
        print(f"\n{p[0]} vs {p[1]}: no longer passing with the default robust test: {', '.join(lost) or 'none'}"
              + (f"; newly passing: {', '.join(gained)}" if gained else ""))
    names = res0.predictors
    a, b, h = names[-1], names[-2], max(protocol.horizons)
    print(f"\nt statistic of {a} - {b}'s CC at horizon {h}: paired / robust at "
          + ", ".join(str(k) for k in SPANS) + f" spans / batch means over {BLOCKS} blocks:\n")
    for ds, (res, _) in results.items():
        t = t_statistics(res, a, b, h, span)
        print(f"- {ds}: {t[0]:.1f} / " + ", ".join(f"{x:.1f}" for x in t[1:-1]) + f" / {t[-1]:.1f}")
    print("\nLag-one autocorrelation of CC differences, per horizon (" + ", ".join(results) + "):\n")
    for a, b in [(names[j], names[i]) for j in range(1, len(names)) for i in range(j)]:
        for h in protocol.horizons:
            print(f"- {a} - {b}, horizon {h}: "
                  + " / ".join(f"{lag_one(results[ds][0], a, b, h):+.2f}" for ds in results))


if __name__ == "__main__":
    main()
