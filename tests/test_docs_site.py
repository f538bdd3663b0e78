"""The documentation holds together: every relative link and every repository path written in
backticks names something that exists, the site's generated pages say what the code says, and
``mkdocs build --strict`` passes (where mkdocs is installed: ``pip install -e ".[docs]"``)."""

from __future__ import annotations

import glob
import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: folders that hold no documentation of ours (build output, caches, a virtual environment)
SKIP = {".git", "build", "dist", "site", ".venv", "venv", "node_modules", ".pytest_cache", ".hypothesis", "__pycache__"}
#: a backticked token is a repository path when it starts with one of these folders...
TOP_FOLDERS = ("sonarset", "models", "cli", "spec", "tests", "bench", "docs", "recipes", "examples")
#: ...or is one of these root files
ROOT_FILES = ("README.md", "BENCHMARKS.md", "CHANGELOG.md", "CONTRIBUTING.md", "CITATION.cff", "LICENSE",
              "pyproject.toml", "mkdocs.yml")
FENCE = re.compile(r"^\s*(```|~~~)")
LINK = re.compile(r"\[[^\]\n]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
CODE = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")
#: paths in other repositories that a page names beside their repository, in the same form as ours
ELSEWHERE = {
    "examples/energyscapeExample.m",  # docs/physics.md: the Cosys-Lab Acoustic-Imaging-Toolbox's
}
#: an upper-case word in a path is a placeholder (`bench/NAME.py`, `recipes/zoo/KIND-small.toml`)...
PLACEHOLDER = re.compile(r"(?<![A-Za-z])[A-Z][A-Z_]+(?![a-z])")
#: ...unless it is one of our upper-case file names
UPPER_NAMES = {"README", "FORMAT", "BENCHMARKS", "CHANGELOG", "CONTRIBUTING", "LICENSE", "CITATION"}
#: characters around a path in running code: quotes, brackets, trailing punctuation
STRIP = "\"'()[]{},;:."


def markdown_files() -> list[Path]:
    # a virtual environment inside the checkout, whatever its name, holds other projects' documents
    envs = {cfg.parent.name for cfg in ROOT.glob("*/pyvenv.cfg")}
    return sorted(p for p in ROOT.rglob("*.md") if p.relative_to(ROOT).parts[0] not in envs
                  and not any(part in SKIP or part.endswith(".egg-info") for part in p.relative_to(ROOT).parts))


def prose_lines(text: str):
    """(line number, line) of every line outside fenced code blocks."""
    fenced = False
    for n, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            yield n, line


def repo_path(token: str) -> str | None:
    """The repository path a backticked token names, or None when it names none.

    ``sonarset/windows.py``, ``models/echopt/train.py:120``, ``tests/test_x.py::test_y``,
    ``recipes/zoo/``, ``recipes/echopt-small/01-*.toml`` (a glob) and ``README.md`` are paths;
    ``my.zarr``, ``runs/a/model.safetensors``, ``sonarset.windows`` and ``--out DIR`` are not.
    """
    token = token.strip(STRIP).split("::")[0]
    token = re.sub(r":\d+(-\d+)?$", "", token)
    if token in ROOT_FILES:
        return token
    head = token.split("/")[0]
    if "/" not in token or head not in TOP_FOLDERS:
        return None
    if re.search(r"[<>$]|\.\.\.|\{", token) or set(PLACEHOLDER.findall(token)) - UPPER_NAMES:
        return None  # a placeholder, not a path
    return None if token in ELSEWHERE else token


def exists(path: str) -> bool:
    return bool(glob.glob(str(ROOT / path))) if any(c in path for c in "*?[") else (ROOT / path).exists()


def broken_references(path: Path) -> list[str]:
    """'file:line: what' for every relative link and backticked repository path that names nothing."""
    rel = path.relative_to(ROOT).as_posix()
    found = []
    for n, line in prose_lines(path.read_text()):
        for target in LINK.findall(line):
            if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:|^#|^/", target):
                continue  # a URL, an anchor on the page, an absolute path
            file = target.split("#")[0]
            if file and not (path.parent / file).exists():
                found.append(f"{rel}:{n}: link to {target}")
        for span in CODE.findall(line):
            for token in span.split():
                p = repo_path(token)
                if p and not exists(p):
                    found.append(f"{rel}:{n}: `{p}` does not exist")
    return found


def test_the_path_heuristic():
    assert repo_path("sonarset/windows.py") == "sonarset/windows.py"
    assert repo_path("models/echopt/train.py:120") == "models/echopt/train.py"
    assert repo_path("tests/test_cli.py::test_info") == "tests/test_cli.py"
    assert repo_path("(bench/bench_zoo.py),") == "bench/bench_zoo.py"
    assert repo_path("README.md") == "README.md"
    assert repo_path("spec/FORMAT.md") == "spec/FORMAT.md"
    for not_a_path in ("bench/NAME.py", "recipes/zoo/KIND-small.toml", "recipes/echopt-small/NN-name.toml",
                       "my.zarr", "runs/a/model.safetensors", "sonarset.windows", "--out", "DIR/results.json",
                       "docs/results/<name>.json", "echopt:runs/a", "sonarset", "examples/energyscapeExample.m"):
        assert repo_path(not_a_path) is None, not_a_path
    assert exists("recipes/echopt-small/0*.toml") and not exists("recipes/nope/*.toml")


def test_the_scan_finds_broken_links_and_paths(tmp_path, monkeypatch):
    doc = ROOT / "docs" / "_scan_probe.md"  # never written: the scan reads the text given below
    text = "[ok](../README.md) [bad](nope.md) `sonarset/nope.py` `my.zarr`\n```\n`sonarset/in_a_fence.py`\n```\n"
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: text)
    assert broken_references(doc) == ["docs/_scan_probe.md:1: link to nope.md",
                                      "docs/_scan_probe.md:1: `sonarset/nope.py` does not exist"]


def test_every_link_and_repository_path_in_the_markdown_exists():
    files = markdown_files()
    named = {p.relative_to(ROOT).as_posix() for p in files}
    assert {"README.md", "docs/index.md", "recipes/README.md", "spec/FORMAT.md"} <= named
    broken = [b for p in files for b in broken_references(p)]
    assert not broken, "links and paths that name nothing:\n" + "\n".join(broken)


def _hooks():
    spec = importlib.util.spec_from_file_location("sonarset_docs_hooks", ROOT / "docs" / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_cli_reference_has_every_command():
    import typer.main

    from sonarset.cli.app import app

    text = _hooks().cli_markdown()
    root = typer.main.get_command(app)
    names = list(root.commands)
    assert "train" in names and "experiment" in names
    for name in names:
        assert f"## `sonarset {name}`" in text
    for sub in ("slip", "control"):
        assert f"### `sonarset experiment {sub}`" in text
    assert "| `--max-steps` |" in text and "| `--compile`, `--no-compile` |" in text


def test_the_results_pages_are_the_results_files():
    import json

    from sonarset.models.benchmark import load_results
    from sonarset.models.benchmark.tables import summary_table, zoo_table

    hooks = _hooks()
    shipped = load_results(ROOT / "docs/results/benchmark-v1.json")
    assert summary_table(shipped) in hooks.generated("results", ["docs/results/benchmark-v1.json"])
    zoo = load_results(ROOT / "docs/results/zoo-v1.json")
    costs = json.loads((ROOT / "docs/results/bench_zoo.json").read_text())
    assert hooks.generated("zoo", ["docs/results/zoo-v1.json", "docs/results/bench_zoo.json"]) == zoo_table(zoo, costs)
    for page in ("results/benchmark.md", "results/zoo.md"):
        assert "<!-- sonarset:" in (ROOT / "docs" / page).read_text()


def test_mkdocs_build_strict(tmp_path):
    for module in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python"):
        try:
            found = importlib.util.find_spec(module)
        except ModuleNotFoundError:
            found = None
        if found is None:
            pytest.skip(f"{module} is not installed (pip install -e \".[docs]\")")
    # as on a fresh clone: the API's layout (docs/hooks.py) does not exist before the build
    shutil.rmtree(ROOT / "build" / "docs-api", ignore_errors=True)
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                       cwd=ROOT, capture_output=True, text=True, timeout=600,
                       env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-5000:]
    for page in ("index.html", "reference/cli/index.html", "reference/api/index.html", "results/zoo/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    assert "sonarset.open_store" in (tmp_path / "site" / "reference/api/index.html").read_text()
    shutil.rmtree(tmp_path / "site")
