"""How much of protocol v1's verdicts rests on targets that hold no echo?

    python bench/bench_empty_targets.py --models flow,echopt:pretrained,pretrained

A target "holds no echo" when it has no local maximum at or above the echo level (0.3; the
windows where echo recall is undefined), whoever predicts it: a turn away from every wall, an open
stretch of the orchard. Two of protocol v1's metrics treat such targets in ways that decide cells:

- NRMSD divides by the target's norm, ||p - m|| / ||m||, there near the post-processed noise
  floor's, so predicted energy can read as an NRMSD of 10 or more;
- echo F1 is undefined where neither image holds an echo, and the paired test drops the window:
  a model that correctly forecasts no echo, against one that draws a false echo (F1 0), loses
  that evidence.

This evaluates the models on protocol v1's datasets (the benchmark's stores, windows and Holm
families) and prints, per dataset and horizon, how many targets hold no echo, what share of the
variance of each NRMSD difference those windows carry, and each NRMSD comparison's Holm p as
protocol v1 scores it and with those windows set aside; then for echo F1, how many windows one
model forecasts correctly empty while the other draws an echo, each way, and each comparison's
Holm p as protocol v1 scores it and with a correct "no echo" scored 1 (each with its mean
difference before -> after). The other tests keep their raw p; Holm is recomputed over protocol
v1's families. Last, the cells (dataset x horizon x CC, NRMSD, echo F1) each model wins at Holm
p < 0.001, each way. A sensitivity analysis, not a protocol: protocol v1 stands.
"""

from __future__ import annotations


import numpy as np

from bench_serial import METRICS, evaluate_protocol, passes  # the same cells, counted the same way
from sonarset.models.benchmark.protocol import PROTOCOL_V1
from sonarset.models.benchmark.run import correct_over_file, dataset_entry
from sonarset.scoring.stats import WindowPlaces, compare


def empty_targets(res, h: int) -> np.ndarray:
    """The windows whose horizon-h target holds no echo: its brightest pixel, a local maximum,
    is below the echo level (where echo recall is undefined), whatever is predicted."""
    return res.target_peak[:, h - 1] < res.echo_matching.level


def rescore(res, places: WindowPlaces, metric: str) -> None:
    """Each ``metric`` comparison of ``res`` again: NRMSD over the windows whose target holds an
    echo; echo F1 with a correct "no echo" (neither image holds one) scored 1."""
    for i, c in enumerate(res.comparisons):
        if c.metric != metric:
            continue
        empty = empty_targets(res, c.horizon)
        if metric == "nrmsd":
            a, b = (np.where(empty, np.nan, res.per_window[m][c.horizon]["nrmsd"]) for m in (c.a, c.b))
        else:  # a finite forecast's F1 is undefined only where neither image holds an echo
            a, b = (np.where(empty & ~np.isfinite(res.per_window[m][c.horizon]["echo_f1"])
                             & np.isfinite(res.step_peak[m][:, c.horizon - 1]), 1.0,
                             res.per_window[m][c.horizon]["echo_f1"]) for m in (c.a, c.b))
        res.comparisons[i] = compare(a, b, metric=metric, horizon=c.horizon, names=(c.a, c.b), windows=places,
                                     seed=PROTOCOL_V1.eval_seed)


def silence(res, a: str, b: str, h: int) -> tuple[int, int]:
    """The windows a forecasts correctly empty while b draws an echo, and the other way round."""
    fa, fb = (res.per_window[m][h]["echo_f1"] for m in (a, b))
    quiet_a, quiet_b = (~np.isfinite(f) & np.isfinite(res.step_peak[m][:, h - 1]) for f, m in ((fa, a), (fb, b)))
    return int((quiet_a & (fb == 0)).sum()), int((quiet_b & (fa == 0)).sum())


def comparison(res, a: str, b: str, h: int):
    """The NRMSD comparison of a and b at horizon h, either way round."""
    return next(c for c in res.comparisons if c.metric == "nrmsd" and c.horizon == h and {c.a, c.b} == {a, b})


def variance_share(res, c) -> float:
    """The share of the variance of c's NRMSD differences carried by the windows with an empty target."""
    d = res.per_window[c.a][c.horizon]["nrmsd"] - res.per_window[c.b][c.horizon]["nrmsd"]
    empty, ok = empty_targets(res, c.horizon), np.isfinite(d)
    dev = (d - d[ok].mean()) ** 2
    return float(dev[ok & empty].sum() / dev[ok].sum())


def main() -> None:
    protocol, results = evaluate_protocol("bench_empty_targets", __doc__)
    print()
    scored = {}
    steps = {"protocol v1": None, "NRMSD without no-echo targets": "nrmsd",
             "and echo F1 scoring a correct no-echo 1": "echo_f1"}
    for label, metric in steps.items():  # each step keeps the ones before it
        datasets = {}
        for ds in protocol.datasets:
            res, seconds = results[ds.name]
            if metric:
                rescore(res, WindowPlaces.of(res.window_ids, res.n_in + max(protocol.horizons)), metric)
            datasets[ds.name] = dataset_entry(res, ds, protocol, seconds)
        correct_over_file(datasets, protocol)
        scored[label] = datasets
    res0 = next(iter(results.values()))[0]
    pairs = [(res0.predictors[j], res0.predictors[i]) for j in range(1, len(res0.predictors)) for i in range(j)]
    v1, nrmsd, f1 = scored.values()
    def table(metric: str, scored_after: dict, cell) -> None:
        print("| dataset | horizon | " + ("no-echo targets | " if metric == "nrmsd" else "")
              + " | ".join(f"{a} - {b}" for a, b in pairs) + " |")
        print("|---|---|" + "---|" * (len(pairs) + (metric == "nrmsd")))
        for ds in protocol.datasets:
            res = results[ds.name][0]
            for h in protocol.horizons:
                row = [f"{int(empty_targets(res, h).sum())}"] if metric == "nrmsd" else []
                for a, b in pairs:
                    before, after = (test_of(x[ds.name], a, b, h, protocol.reference, metric) for x in (v1, scored_after))
                    row.append(cell(res, a, b, h) + f"{before['mean_diff']:+.3f} -> {after['mean_diff']:+.3f}, "
                               f"{before['p_holm']:.2g} -> {after['p_holm']:.2g}")
                print(f"| {ds.name} | {h} | " + " | ".join(row) + " |")

    print("NRMSD: windows whose target holds no echo; per pair (later - earlier), the share of the difference's "
          "variance on those windows, the mean difference and the Holm p with every window -> with those set aside\n")
    table("nrmsd", nrmsd, lambda res, a, b, h: f"{variance_share(res, comparison(res, a, b, h)):.0%}, ")
    print("\nEcho F1: per pair, the windows the later model forecasts correctly empty while the earlier draws an "
          "echo / the other way round, the mean difference and the Holm p as protocol v1 scores it -> with a "
          "correct no-echo scored 1\n")
    table("echo_f1", f1, lambda res, a, b, h: "{}/{}, ".format(*silence(res, a, b, h)))
    cells = len(protocol.datasets) * len(protocol.horizons) * len(METRICS)
    print(f"\nCells (of {cells}) in which the model is better at Holm p < 0.001:\n")
    counted = {k: passes(v, protocol.reference, "p_holm") for k, v in scored.items()}
    print("| scored | " + " | ".join(f"{m} vs {o}" for m, o in counted["protocol v1"]) + " |")
    print("|---|" + "---|" * len(counted["protocol v1"]))
    for label, fails in counted.items():
        print(f"| {label} | " + " | ".join(str(cells - len(f)) for f in fails.values()) + " |")
    last = list(counted)[-1]
    for pair, fails in counted[last].items():
        print(f"\n{pair[0]} vs {pair[1]}, not passing ({last}): {', '.join(fails) or 'none'}")

def test_of(entry: dict, a: str, b: str, h: int, reference: str, metric: str) -> dict:
    """The ``metric`` test of a against b at horizon h in a results file's dataset entry."""
    methods = entry["horizons"][str(h) if str(h) in entry["horizons"] else h]["methods"]
    if b == reference:
        return methods[a]["vs_reference"][metric]
    return methods[a]["vs_models"][b][metric]


if __name__ == "__main__":
    main()
