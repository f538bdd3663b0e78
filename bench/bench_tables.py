"""The Markdown that README and BENCHMARKS paste from benchmark results files.

    python bench/bench_tables.py RESULTS.json             # results.md: summary and per-dataset tables
    python bench/bench_tables.py A.json B.json [...]      # one table of several files (same protocol version)

RESULTS.json is what ``sonarset benchmark`` writes (``--out DIR``: DIR/results.json).
"""

from __future__ import annotations

import argparse
import sys

from sonarset.errors import SonarSetError
from sonarset.models.benchmark import compare_results, load_results, results_markdown


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="+", help="results.json files of sonarset benchmark")
    args = ap.parse_args()
    try:
        text = results_markdown(load_results(args.results[0])) if len(args.results) == 1 else compare_results(args.results)
    except SonarSetError as exc:
        sys.exit(f"error: {exc}")
    print(text, end="")


if __name__ == "__main__":
    main()
