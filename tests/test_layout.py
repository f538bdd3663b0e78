"""The layout's rules that no single test of behaviour would catch: the library names values and
parameters, never the command line's flags (cli/ adds them: cli/common.py), and no module grows
past what a reader takes in at once."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ("sonarset", "models")
#: A command-line flag in running text: two dashes, a lower-case word, not inside a longer token.
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]+")
MAX_LINES = 400


def _modules(*dirs: str) -> list[Path]:
    return sorted(p for d in dirs for p in (ROOT / d).rglob("*.py"))


def flags_named(source: str) -> list[tuple[int, str]]:
    """(line, flag) for every flag in a string constant of ``source``: messages, docstrings and the
    literal parts of f-strings."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            found += [(node.lineno, flag) for flag in FLAG.findall(node.value)]
    return found


def test_the_scan_finds_flags_in_messages_docstrings_and_f_strings():
    source = '"""Use ``--processing``."""\nraise E(f"--minutes {m} must be > 0")\nx = "a--b, 1 -- 2, -3, --X"\n'
    assert flags_named(source) == [(1, "--processing"), (2, "--minutes")]


def test_no_library_string_names_a_cli_flag():
    """Library messages and docstrings say ``parameter`` names and values ("minutes must be > 0");
    the command line shows a parameter as its flag (SonarSetError's ``parameter``)."""
    hits = [f"{p.relative_to(ROOT)}:{line}: {flag}" for p in _modules(*LIBRARY)
            for line, flag in flags_named(p.read_text())]
    assert not hits, "library strings that name CLI flags:\n" + "\n".join(hits)


def test_no_module_over_400_lines():
    long = {str(p.relative_to(ROOT)): n for p in _modules(*LIBRARY, "cli")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def readme_imports() -> list[tuple[str, list[str]]]:
    """(module, names) of every ``from sonarset... import ...`` line in the README's Python blocks."""
    text = (ROOT / "README.md").read_text()
    found = []
    for block in re.findall(r"```python\n(.*?)```", text, flags=re.S):
        for node in ast.walk(ast.parse(block)):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("sonarset"):
                found.append((node.module, [a.name for a in node.names]))
    return found


def test_the_readme_imports_what_exists():
    """A user copies the README's snippets: every name they import is where the README says."""
    import importlib

    found = readme_imports()
    assert len(found) >= 5  # the scan sees the README's snippets
    missing = [f"{mod}.{name}" for mod, names in found for name in names
               if not hasattr(importlib.import_module(mod), name)]
    assert not missing, f"README imports names that do not exist: {missing}"
