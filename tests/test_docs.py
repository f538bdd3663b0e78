"""The README's numbers about the shipped model are the card's: a model shipped without its table
re-measured (or a table edited by hand) fails here, not in a reader's hands."""

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CARD = ROOT / "models" / "pretrained" / "echopt-small.json"
HORIZONS = {"one-shot": "1", "AR-3": "3", "AR-5": "5", "AR-10": "10"}
#: | family | shipped | horizon | flow CC | CC vs flow | NRMSD vs flow | echo F1 vs flow | ...
ROW = re.compile(r"^\| (\w+) \| shipped \| ([\w-]+) \| ([\d.]+) \| ([^|]+) \| ([^|]+) \| ([^|]+) \|", re.M)


def mark(p_holm: float) -> str:
    """The README's significance mark of a Holm p (its table's legend)."""
    return "" if p_holm < 1e-3 else "°" if p_holm < 0.05 else " (n.s.)"


def cell(entry: dict) -> str:
    return f"{entry['diff']:+.3f}{mark(entry['p_holm'])}".replace("-0.000", "+0.000")


def shipped_rows(text: str) -> dict[tuple[str, str], tuple[str, ...]]:
    return {(fam, HORIZONS[h]): tuple(c.strip() for c in cells) for fam, h, *cells in ROW.findall(text)}


def test_the_row_pattern_reads_a_table_row():
    text = "| lab | shipped | AR-3 | 0.877 | +0.014 | -0.050° | +0.048 (n.s.) | 0.947 | 0.20 |\n"
    assert shipped_rows(text) == {("lab", "3"): ("0.877", "+0.014", "-0.050°", "+0.048 (n.s.)")}


def test_readme_families_table_is_the_shipped_cards():
    by_world = json.loads(CARD.read_text())["test"]["by_world"]
    rows = shipped_rows((ROOT / "README.md").read_text())
    expected = {(fam, h): (f"{m['cc']['flow']:.3f}", cell(m["cc"]), cell(m["nrmsd"]), cell(m["echo_f1"]))
                for fam, per_h in by_world.items() for h, m in per_h.items()}
    assert len(expected) >= 8  # the card holds the families' test numbers
    assert rows == expected


RESULTS = ROOT / "docs" / "results"


def test_readme_and_benchmarks_tables_are_the_results_files():
    """The benchmark tables that README and BENCHMARKS show are generated from the committed results
    files (bench/bench_tables.py): one home per number."""
    from sonarset.models.benchmark import load_results
    from sonarset.models.benchmark.tables import dataset_table, summary_table, zoo_table

    readme, benchmarks = (ROOT / "README.md").read_text(), (ROOT / "BENCHMARKS.md").read_text()
    shipped = load_results(RESULTS / "benchmark-v1.json")
    assert summary_table(shipped) in readme
    zoo = load_results(RESULTS / "zoo-v1.json")
    costs = json.loads((RESULTS / "bench_zoo.json").read_text())
    assert zoo_table(zoo, costs) in readme and summary_table(zoo) in readme
    for name in zoo["datasets"]:
        assert dataset_table(zoo, name) in benchmarks
    assert summary_table(shipped) in benchmarks
