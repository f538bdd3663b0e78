"""The documents' numbers are the files': the README's one results table and BENCHMARKS' tables are
generated from the committed results files and the shipped model's card, so a model shipped without
its tables re-measured (or a table edited by hand) fails here, not in a reader's hands. And the
documents name only files that exist."""

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CARD = ROOT / "models" / "pretrained" / "echopt-small.json"
RESULTS = ROOT / "docs" / "results"
HORIZONS = {"one-shot": "1", "AR-3": "3", "AR-5": "5", "AR-10": "10"}
#: | family | shipped | horizon | flow CC | CC vs flow | NRMSD vs flow | echo F1 vs flow | ...
ROW = re.compile(r"^\| (\w+) \| shipped \| ([\w-]+) \| ([\d.]+) \| ([^|]+) \| ([^|]+) \| ([^|]+) \|", re.MULTILINE)
#: The documents whose backticked repository paths must exist.
DOCS = ("README.md", "BENCHMARKS.md", "CONTRIBUTING.md", "CHANGELOG.md", "docs/results/lineage.md")
#: A backticked token is taken for a repository path when it starts with one of these folders.
TOP = ("sonarset/", "models/", "cli/", "bench/", "tests/", "spec/", "docs/", "recipes/", "examples/", ".ci/")


def mark(p_holm: float) -> str:
    """The families table's significance mark of a Holm p (its legend)."""
    return "" if p_holm < 1e-3 else "°" if p_holm < 0.05 else " (n.s.)"


def cell(entry: dict) -> str:
    return f"{entry['diff']:+.3f}{mark(entry['p_holm'])}".replace("-0.000", "+0.000")


def shipped_rows(text: str) -> dict[tuple[str, str], tuple[str, ...]]:
    return {(fam, HORIZONS[h]): tuple(c.strip() for c in cells) for fam, h, *cells in ROW.findall(text)}


def read(name: str) -> str:
    return (ROOT / name).read_text()


def test_the_row_pattern_reads_a_table_row():
    text = "| lab | shipped | AR-3 | 0.877 | +0.014 | -0.050° | +0.048 (n.s.) | 0.947 | 0.20 |\n"
    assert shipped_rows(text) == {("lab", "3"): ("0.877", "+0.014", "-0.050°", "+0.048 (n.s.)")}


def test_benchmarks_families_table_is_the_shipped_cards():
    by_world = json.loads(CARD.read_text())["test"]["by_world"]
    rows = shipped_rows(read("BENCHMARKS.md"))
    expected = {(fam, h): (f"{m['cc']['flow']:.3f}", cell(m["cc"]), cell(m["nrmsd"]), cell(m["echo_f1"]))
                for fam, per_h in by_world.items() for h, m in per_h.items()}
    assert len(expected) >= 8  # the card holds the families' test numbers
    assert rows == expected


def test_readme_shows_one_results_table_the_benchmarks_summary():
    """The README's front page has one table: protocol v1's summary, as the results file says."""
    from sonarset.models.benchmark import load_results
    from sonarset.models.benchmark.tables import summary_table

    readme = read("README.md")
    assert summary_table(load_results(RESULTS / "benchmark-v1.json")) in readme
    assert len(re.findall(r"^\|---", readme, flags=re.MULTILINE)) == 1
    assert len(readme.splitlines()) <= 300


def test_benchmarks_tables_are_the_results_files():
    """Every benchmark table BENCHMARKS shows is generated from the committed results files
    (bench/bench_tables.py): one home per number."""
    from sonarset.models.benchmark import load_results
    from sonarset.models.benchmark.tables import (
        cost_table,
        dataset_table,
        summary_table,
        zoo_table,
    )

    benchmarks = read("BENCHMARKS.md")
    shipped = load_results(RESULTS / "benchmark-v1.json")
    zoo = load_results(RESULTS / "zoo-v1.json")
    costs = json.loads((RESULTS / "bench_zoo.json").read_text())
    assert summary_table(shipped) in benchmarks
    assert summary_table(zoo) in benchmarks
    assert zoo_table(zoo, costs) in benchmarks
    assert cost_table(costs) in benchmarks
    for results in (shipped, zoo):
        for name in results["datasets"]:
            assert dataset_table(results, name) in benchmarks


def cited_paths(text: str) -> set[str]:
    """The repository paths a document names in backticks (``bench/bench_zoo.py``, ``spec/schema/``,
    ``DESIGN.md``), each word of a command, a ``path: name`` reference cut to the path."""
    found = set()
    for token in re.findall(r"`([^`\n]+)`", text):
        for word in token.split():
            word = word.split(":")[0].rstrip(".,;)")
            if ((word.startswith(TOP) or re.fullmatch(r"[A-Z]+\.(md|cff)", word))
                    and not any(c in word for c in "*<>{}$|") and not word.endswith("NNN")):
                found.add(word)
    return found


def exists(path: str) -> bool:
    """The path exists, or a placeholder in capitals (``recipes/zoo/KIND-small.toml``) stands for
    files that do."""
    return (ROOT / path).exists() or any(ROOT.glob(re.sub(r"\b[A-Z]{3,}\b", "*", path)))


def test_the_documents_cite_files_that_exist():
    missing = {f"{doc}: {p}" for doc in DOCS if (ROOT / doc).exists()
               for p in cited_paths(read(doc)) if not exists(p)}
    assert not missing, "documents cite paths that do not exist:\n" + "\n".join(sorted(missing))
