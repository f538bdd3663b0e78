"""Benchmark results as Markdown: one file's tables (``results_markdown``, what results.md holds and
README or BENCHMARKS paste), and several files side by side (``compare_results``), which must
answer the same protocol version."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from sonarset.errors import SonarSetError
from sonarset.report.numbers import format_p, horizon_name
from sonarset.scoring.stats import windows_to_pass
from sonarset.windows import N_IN

from sonarset.models.benchmark.machine import describe
from sonarset.models.eval.report import LOWER_IS_BETTER, md_cell

#: The per-dataset table's metrics: CC and NRMSD (the paper's) and echo F1.
TABLE_METRICS = (("cc", "CC"), ("nrmsd", "NRMSD"), ("echo_f1", "echo F1"))
CEILING_LABELS = {"ceiling": "noise ceiling", "observable": "observable ceiling"}
#: A cell differs from the reference where its Holm-corrected p is below this.
ALPHA = 0.05


def load_results(path: str | os.PathLike) -> dict:
    """A results file (results.json of ``sonarset benchmark``); SonarSetError in one line when it is
    not one."""
    try:
        doc = json.loads(Path(path).read_text())
    except OSError as exc:
        raise SonarSetError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise SonarSetError(f"{path}: not JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("protocol"), dict) or "datasets" not in doc:
        raise SonarSetError(f"{path}: not a benchmark results file (no protocol and datasets)")
    return doc


def window_context(doc: dict) -> int:
    """The input frames a results file's windows have room for: its models' ``n_in``, which decides
    the windows its seed draws (files before it was recorded: the paper's 3)."""
    return max(int(d.get("n_in", N_IN)) for d in doc["datasets"].values())


def _version(doc: dict) -> str:
    p = doc["protocol"]
    return f"{p.get('name')} {p.get('version')}"


def _number(x: float | None, spec: str = ".3f") -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, spec)


def _marked(entry: dict, metric: str) -> str:
    """The mean, with '*' where the comparison with the reference is significant after Holm."""
    value = _number(entry[metric]["mean"])
    c = (entry.get("vs_reference") or {}).get(metric)
    if c and c.get("p_holm") is not None and c["p_holm"] < ALPHA and value != "-":
        value += "*"
    return value


def dataset_table(results: dict, name: str) -> str:
    """Rows = methods (then the ceilings, in italics), columns = CC, NRMSD and echo F1 at every
    horizon, and the share of the CC gap between flow and the observable ceiling closed at the
    longest horizon."""
    d = results["datasets"][name]
    hs = sorted(d["horizons"], key=int)
    longest = hs[-1]
    head = ["method"] + [f"{label} {horizon_name(int(h))}" for _, label in TABLE_METRICS for h in hs] + \
           [f"{horizon_name(int(longest))} gap share"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    methods = d["horizons"][longest]["methods"]
    reference = results["statistics"]["reference"]
    for m in methods:
        cells = [_marked(d["horizons"][h]["methods"][m], k) for k, _ in TABLE_METRICS for h in hs]
        share = (methods[m].get("gap_share") or {}).get("cc")
        cells.append("ref" if m == reference else _number(share, ".2f"))
        lines.append(f"| {md_cell(m)} | " + " | ".join(cells) + " |")
    for c, label in CEILING_LABELS.items():
        if c in d["horizons"][longest]["ceilings"]:
            cells = [_number(d["horizons"][h]["ceilings"][c][k]["mean"]) for k, _ in TABLE_METRICS for h in hs]
            lines.append(f"| *{label}* | " + " | ".join(cells) + " | |")
    return "\n".join(lines)


def summary_table(results: dict) -> str:
    """Rows = methods, one column per dataset: CC at the longest horizon."""
    names = list(results["datasets"])
    longest = str(max(results["protocol"]["definition"]["horizons"]))
    lines = ["| method | " + " | ".join(names) + " |", "|---" * (1 + len(names)) + "|"]
    for m in results["datasets"][names[0]]["horizons"][longest]["methods"]:
        cells = [_marked(results["datasets"][n]["horizons"][longest]["methods"][m], "cc") for n in names]
        lines.append(f"| {md_cell(m)} | " + " | ".join(cells) + " |")
    for c, label in CEILING_LABELS.items():
        if all(c in results["datasets"][n]["horizons"][longest]["ceilings"] for n in names):
            cells = [_number(results["datasets"][n]["horizons"][longest]["ceilings"][c]["cc"]["mean"]) for n in names]
            lines.append(f"| *{label}* | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def cost_table(costs: dict) -> str:
    """What each learned method costs to train on one machine (bench/bench_zoo.py's JSON): parameters,
    GFLOP per training window, samples/s and the share of the same process's matmul roof, per
    precision and rollout length."""
    runs = [(t["precision"], t["k"]) for t in costs["models"][0]["training"]]
    head = ["kind", "M params", "GFLOP/window (1 / 3 steps)"] + [f"{p} k={k}: samples/s (roof share)" for p, k in runs]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for row in costs["models"]:
        g = row["gflop_per_sample"]
        cells = [f"{t['samples_per_s']:.1f} ({100 * t['roof_share']:.0f} %)" for t in row["training"]]
        lines.append(f"| {row['kind']} | {row['params'] / 1e6:.2f} | {g['1']:.2f} / {g[str(costs['k'])]:.2f} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def zoo_table(results: dict, costs: dict) -> str:
    """The learned methods side by side: what each costs to train (``costs``: bench/bench_zoo.py's
    JSON, measured on one machine) and the share of the flow-to-observable CC gap it closes at the
    longest horizon on every dataset of ``results``. A method's row is found by its card's kind
    (``card["model"]``, EchoPT where a card names none)."""
    names = list(results["datasets"])
    longest = str(max(results["protocol"]["definition"]["horizons"]))
    by_kind = {row["kind"]: row for row in costs["models"]}
    head = ["method", "M params", "GFLOP/window (1 / 3 steps)", "samples/s fp32 (k=3)", "samples/s bf16 (k=3)",
            *[f"gap share {n}" for n in names], "mean"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for m in results["models"]:
        row = by_kind.get((m.get("card") or {}).get("model", "echopt")) if m.get("card") else None
        rates = {t["precision"]: t["samples_per_s"] for t in (row or {}).get("training", []) if t["k"] == costs["k"]}
        shares = [(results["datasets"][n]["horizons"][longest]["methods"][m["method"]].get("gap_share") or {}).get("cc")
                  for n in names]
        known = [s for s in shares if s is not None and math.isfinite(s)]
        cost = [f"{row['params'] / 1e6:.2f}",
                f"{row['gflop_per_sample']['1']:.2f} / {row['gflop_per_sample'][str(costs['k'])]:.2f}",
                _number(rates.get("fp32"), ".1f"), _number(rates.get("bf16"), ".1f")] if row else ["-"] * 4
        lines.append(f"| {md_cell(m['method'])} | " + " | ".join(cost + [_number(s, ".2f") for s in shares]
                                                        + [_number(sum(known) / len(known) if known else None, ".2f")]) + " |")
    return "\n".join(lines)


def unresolved_cells(results: dict, alpha: float = ALPHA) -> dict[tuple[str, str], dict]:
    """Per (model, other) of a results file (each model against the reference and against every model
    before it), over every dataset, horizon and table metric: the cells in which ``model`` is
    better at Holm p < ``alpha`` (``resolved``, a count), better on the mean but not significantly
    (``open``: dataset, horizon, metric, the test, and the windows at which the same difference
    would pass the Bonferroni bound of its Holm family, alpha / its size, by the paired and by the
    serial-robust test: ``stats.windows_to_pass``; a sufficient count, as Holm may pass a cell with
    fewer), worse on the mean (``worse``) and untested or equal (``undefined``)."""
    st = results["statistics"]
    reference = st["reference"]
    out: dict[tuple[str, str], dict] = {}
    for ds, d in results["datasets"].items():
        for h, per_h in sorted(d["horizons"].items(), key=lambda kv: int(kv[0])):
            for model, entry in per_h["methods"].items():
                others = {reference: entry["vs_reference"]} if entry.get("vs_reference") else {}
                others.update(entry.get("vs_models") or {})
                for other, tests in others.items():
                    family = st["tests"] if other == reference else st.get("head_to_head_tests", st["tests"])
                    pair = out.setdefault((model, other), {"resolved": 0, "open": [], "worse": 0, "undefined": 0})
                    for k, _ in TABLE_METRICS:
                        t = tests.get(k) or {}
                        diff = t.get("mean_diff")
                        if diff is None or diff == 0 or not math.isfinite(diff):
                            pair["undefined"] += 1
                        elif (diff < 0) != LOWER_IS_BETTER[k]:  # worse on the mean
                            pair["worse"] += 1
                        elif t.get("p_holm") is not None and t["p_holm"] < alpha:
                            pair["resolved"] += 1
                        else:
                            need = [windows_to_pass(math.nan if t.get(key) is None else t[key], t["n"], alpha / family)
                                    for key in ("t_paired_p", "t_hac_p")]
                            pair["open"].append({"dataset": ds, "horizon": int(h), "metric": k, "test": t,
                                                 "windows_to_pass": need})
    return out


def unresolved_table(results: dict, alpha: float = ALPHA) -> str:
    """``unresolved_cells`` as Markdown: a line per pair of models, then a row per open cell."""
    labels = dict(TABLE_METRICS)
    lines, rows = [], []
    for (model, other), cells in unresolved_cells(results, alpha).items():
        lines.append(f"- {model} vs {other}: better at Holm p < {alpha:g} in {cells['resolved']} cells, better on the "
                     f"mean but not significantly in {len(cells['open'])}, worse on the mean in {cells['worse']}"
                     + (f", untested or equal in {cells['undefined']}" if cells["undefined"] else ""))
        for c in cells["open"]:
            t = c["test"]
            need = " | ".join("-" if not math.isfinite(x) else f"{x:,.0f} ({x / t['n']:.1f}x)"
                              for x in c["windows_to_pass"])
            rows.append(f"| {md_cell(model)} vs {md_cell(other)} | {c['dataset']} | {horizon_name(c['horizon'])} | "
                        f"{labels[c['metric']]} | "
                        f"{t['mean_diff']:+.4f} | {t['n']} | {format_p(t['p_holm'])} | {need} |")
    if rows:
        lines += ["", "| model vs other | dataset | horizon | metric | mean difference | windows | Holm p | "
                      "windows to pass: paired | serial-robust |", "|---" * 9 + "|", *rows]
    return "\n".join(lines)


def results_markdown(results: dict) -> str:
    """results.md: the summary, a table per dataset, the statistics' meaning and the timings."""
    p = results["protocol"]["definition"]
    longest = horizon_name(max(p["horizons"]))
    models = ", ".join(f"{m['method']} (`{m['spec']}`" + (f", {m['precision']}" if m.get("precision") else "") + ")"
                       for m in results["models"])
    stats = results["statistics"]
    parts = [
        f"# Benchmark {_version(results)}", "",
        f"Machine: {describe(results['machine'])}. Models: {models}.", "",
        f"Each dataset: {p['samples']} windows drawn once (seed {p['eval_seed']}) and shared by every method; "
        f"means over the windows where a metric is defined. CC and echo F1: higher is better; NRMSD: lower. "
        f"`*`: differs from {stats['reference']} (paired t-test, p < {ALPHA} after Holm's correction over the "
        f"{stats['tests']} tests of every model against {stats['reference']} on every dataset, horizon and metric of "
        "this file). "
        f"Gap share: the share of the gap between {stats['reference']} and the observable ceiling that the "
        "method closes in CC (1: all the context allows; 0: no better than flow).", "",
        f"## Summary: CC at {longest}", "", summary_table(results),
    ]
    for name, d in results["datasets"].items():
        parts += ["", f"## {name}", "", f"{d['about']}: runs {', '.join(d['runs'])}, {d['windows']} windows, "
                  f"{d['seconds']['evaluate']:.0f} s.", "", dataset_table(results, name)]
        parts += [f"\n> {note}" for note in d["notes"]]
    parts += ["", "## Cells not resolved", "",
              f"Where a model is better than another on the mean but not at Holm p < {ALPHA}: how many windows "
              "the same difference, with its spread, would need to pass the Bonferroni bound of its Holm family "
              "(sufficient: Holm may pass a cell with fewer; more runs of the same length, for the serial-robust "
              "test; a power estimate at the observed effect, itself uncertain, not a test: "
              "`sonarset.scoring.stats.windows_to_pass`). Many times the windows: a difference small against its "
              "spread; a few: a sample too small.", "", unresolved_table(results)]
    t = results["timings"]
    methods = list(t["per_method"])
    parts += ["", "## Timing (seconds)", "",
              "| dataset | evaluate | " + " | ".join(map(md_cell, methods)) + " |", "|---" * (2 + len(methods)) + "|"]
    for name, d in results["datasets"].items():
        parts.append(f"| {name} | {d['seconds']['evaluate']:.1f} | "
                     + " | ".join(_number(d["seconds"]["methods"].get(m), ".1f") for m in methods) + " |")
    parts += ["", f"Total {t['total']:.0f} s: simulating the stores {t['generate']:.0f} s (0 when cached), "
                  f"evaluating {t['evaluate']:.0f} s. Method times are the rollouts' (the ceilings' renders run "
                  "beside them)."]
    return "\n".join(parts) + "\n"


def compare_results(paths: list[str | os.PathLike]) -> str:
    """One table of several results files (from other machines, other models): per file and
    method, CC at the longest horizon on every dataset and the method's seconds. Files of another
    protocol version than the first's are refused."""
    if not paths:
        raise SonarSetError("no results files to compare")
    docs = [(str(p), load_results(p)) for p in paths]
    first, version = docs[0][0], _version(docs[0][1])
    context = window_context(docs[0][1])
    for path, doc in docs[1:]:
        if _version(doc) != version:
            raise SonarSetError(f"{path}: protocol {_version(doc)}, not {version} as {first}; results compare "
                                "only within one protocol version")
        if window_context(doc) != context:
            raise SonarSetError(f"{path}: windows with room for {window_context(doc)} input frames, not {context} "
                                f"as {first}'s; results compare only on the same windows")
    names = [d["name"] for d in docs[0][1]["protocol"]["definition"]["datasets"]]
    longest = str(max(docs[0][1]["protocol"]["definition"]["horizons"]))
    lines = [f"# {version}: CC at {horizon_name(int(longest))} (`*`: differs from flow, Holm p < {ALPHA} within "
             "its file); seconds: the method's forecasts over every dataset (a direct forecaster's, of "
             "the scored horizons alone since 2026-12-07)", "",
             "| results | method | " + " | ".join(names) + " | seconds |", "|---" * (3 + len(names)) + "|"]
    for path, doc in docs:
        for m in doc["datasets"][names[0]]["horizons"][longest]["methods"]:
            cells = [_marked(doc["datasets"][n]["horizons"][longest]["methods"][m], "cc") for n in names]
            lines.append(f"| {md_cell(str(path))} | {md_cell(m)} | " + " | ".join(cells) + f" | "
                         f"{_number(doc['timings']['per_method'].get(m), '.1f')} |")
    lines += ["", *[f"- {path}: {describe(doc['machine'])}" for path, doc in docs]]
    return "\n".join(lines) + "\n"
