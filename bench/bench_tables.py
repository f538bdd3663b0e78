"""The Markdown that README and BENCHMARKS paste from benchmark results files.

    python bench/bench_tables.py RESULTS.json             # results.md: summary and per-dataset tables
    python bench/bench_tables.py A.json B.json [...]      # one table of several files (same protocol version)
    python bench/bench_tables.py RESULTS.json --summary   # only the summary table (CC at AR-10 per dataset)
    python bench/bench_tables.py RESULTS.json --zoo BENCH_ZOO.json  # the model zoo's table
    python bench/bench_tables.py RESULTS.json --costs BENCH_ZOO.json  # what each method costs to train

The zoo table joins a benchmark results file (the scores) with bench/bench_zoo.py's JSON (the cost of
each method on this machine): parameters, GFLOP per training window, training samples/s in fp32 and
bf16, then the AR-10 CC gap share on every dataset and its mean.

RESULTS.json is what ``sonarset benchmark`` writes (``--out DIR``: DIR/results.json).
"""

from __future__ import annotations

import argparse
import json
import sys

from sonarset.errors import SonarSetError
from sonarset.models.benchmark import compare_results, load_results, results_markdown
from sonarset.models.benchmark.tables import cost_table, summary_table, zoo_table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="+", help="results.json files of sonarset benchmark")
    ap.add_argument("--summary", action="store_true", help="only the summary table")
    ap.add_argument("--zoo", default="", help="bench_zoo.py's JSON: print the model zoo's table")
    ap.add_argument("--costs", default="", help="bench_zoo.py's JSON: print its cost table")
    args = ap.parse_args()
    try:
        if args.costs:
            text = cost_table(json.loads(open(args.costs).read())) + "\n"
        elif args.zoo:
            text = zoo_table(load_results(args.results[0]), json.loads(open(args.zoo).read())) + "\n"
        elif args.summary:
            text = summary_table(load_results(args.results[0])) + "\n"
        elif len(args.results) == 1:
            text = results_markdown(load_results(args.results[0]))
        else:
            text = compare_results(args.results)
    except SonarSetError as exc:
        sys.exit(f"error: {exc}")
    print(text, end="")


if __name__ == "__main__":
    main()
