"""Every code block of the getting-started page and the guides runs, in order, in a fresh directory.

A page's ``bash``/``sh`` blocks run in bash (``set -euo pipefail``), its ``python`` blocks in one
namespace per page (so a later block sees an earlier one's names), all in the page's own temporary
directory. A block of plain ``sonarset ...`` lines (no pipes, redirections or other programs) runs
its commands in this process through typer's CliRunner, as tests/test_cli.py does, which spares a
second of start-up per command. Two HTML comments on the line before a block change that:

- ``<!-- file: NAME -->``: the block is written to the file NAME (a recipe, a sidecar, a module);
- ``<!-- no-test: REASON -->``: the block is not run (an install, a robot, a desktop viewer).

To keep the suite short, SHRINK below rewrites some sizes on each page, in plain sight: what runs
is the page's command with fewer minutes, steps and samples, never another command.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from sonarset.cli.app import app

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
BLOCK = re.compile(r"(?:^<!-- (file|no-test): ?([^>]*?) -->\n)?^```(\w*)\n(.*?)^```", re.M | re.S)
RUN = {"bash", "sh", "python"}

#: page -> [(text on the page, what the test runs instead)]; every pair must match something.
SHRINK: dict[str, list[tuple[str, str]]] = {
    "getting-started.md": [
        ("--runs 2 --test-runs 1 --minutes 2", "--runs 1 --test-runs 1 --minutes 0.2"),
        ("--samples 200", "--samples 10"),
        ("n_val=50", "n_val=8"),
        ("batch_size=16", "batch_size=4"),
    ],
    "guides/own-recordings.md": [
        ("--minutes 0.2", "--minutes 0.1"),
        ("frames=slice(0, 8)", "frames=slice(0, 4)"),
        ("--samples 20", "--samples 5"),
    ],
    "guides/training.md": [
        # ten-step windows: a run of 0.2 minutes would hold only validation windows
        ("--runs 2 --test-runs 1 --minutes 2", "--runs 1 --test-runs 1 --minutes 0.4"),
        ("batch_size = 16", "batch_size = 4"),
        ("max_steps = 1000", "max_steps = 2"),
        ("eval_every = 100", "eval_every = 1"),
        ("n_val = 256", "n_val = 4"),
        ("test_samples = 1000", "test_samples = 0"),
    ],
    "guides/own-predictor.md": [
        ("--minutes 2", "--minutes 0.2"),
        ("samples=200", "samples=10"),
        ("--samples 200", "--samples 10"),
        # installed into a folder on PYTHONPATH (see _env), so the environment is left as it was
        ("pip install -e examples/sonarset-plugin-example",
         f"{sys.executable} -m pip install -q --no-deps --no-build-isolation --no-index --target plugins "
         f"{ROOT / 'examples' / 'sonarset-plugin-example'}"),
        ("--models flow,example-decay,example-decay:0.25", "--models flow,example-decay,example-decay:0.25 --samples 10"),
        ("steps = 300", "steps = 3"),
    ],
    "guides/benchmark.md": [
        ("sonarset benchmark flow pretrained --out bench-v1", "sonarset benchmark flow --quick --out bench-v1"),
        ('run_benchmark(["echopt:pretrained"], "bench-echopt")', 'run_benchmark(["naive"], "bench-echopt", quick=True)'),
        ("here/results.json gpu-box/results.json", "bench-v1/results.json bench-echopt/results.json"),
    ],
    "guides/experiments.md": [("--runs 50", "--runs 1 --max-time 4 --workers 1")],
    "guides/viewing.md": [("--minutes 1", "--minutes 0.2")],
    "guides/onnx.md": [],
}
PAGES = sorted(SHRINK)


def blocks(text: str) -> list[tuple[str, str, str, str]]:
    """(marker, marker argument, language, code) of every fenced block, in order."""
    return [(m.group(1) or "", m.group(2) or "", m.group(3), m.group(4)) for m in BLOCK.finditer(text)]


def shrunk(page: str) -> str:
    text = (DOCS / page).read_text()
    for old, new in SHRINK[page]:
        assert old in text, f"{page}: the substitution's text {old!r} is not on the page any more"
        text = text.replace(old, new)
    return text


def sonarset_commands(code: str) -> list[list[str]] | None:
    """The argument lists of a block made only of ``sonarset`` commands, or None (run it in bash)."""
    commands = []
    for line in code.replace("\\\n", " ").splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            words = shlex.split(line, comments=True)
        except ValueError:  # a quote that spans lines: bash's business
            return None
        if words[:1] != ["sonarset"] or any(re.search(r"[|&;<>$`]", w) for w in words):
            return None
        commands.append(words[1:])
    return commands or None


def _env(tmp: Path) -> dict[str, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1", SONARSET_CACHE=str(tmp / "cache"), MPLBACKEND="Agg")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tmp / "plugins"), str(tmp), env.get("PYTHONPATH", "")]))
    return env


def test_blocks_are_found_with_their_markers():
    text = ("x\n<!-- no-test: a robot -->\n```bash\nros2 bag\n```\n"
            "<!-- file: a.toml -->\n```toml\nk = 1\n```\n```python\nprint(1)\n```\n")
    assert blocks(text) == [("no-test", "a robot", "bash", "ros2 bag\n"), ("file", "a.toml", "toml", "k = 1\n"),
                            ("", "", "python", "print(1)\n")]


def test_plain_sonarset_blocks_run_in_process_and_the_rest_in_bash():
    assert sonarset_commands("sonarset info a.zarr   # comment\n\nsonarset eval a.zarr \\\n  --models flow\n") == [
        ["info", "a.zarr"], ["eval", "a.zarr", "--models", "flow"]]
    for code in ("sonarset info a | head\n", "cd x && sonarset info a\n", "pip install x\nsonarset models\n",
                 "sonarset info $STORE\n", "python -c 'import x\nprint(x)'\n", "python -c 'print(1)' > x\n"):
        assert sonarset_commands(code) is None, code


def test_every_page_with_code_is_tested():
    """A new guide with runnable blocks gets a SHRINK entry (an empty list if it needs none)."""
    pages = [p.relative_to(DOCS).as_posix() for p in [DOCS / "getting-started.md", *sorted((DOCS / "guides").glob("*.md"))]]
    untested = [p for p in pages if p not in SHRINK and any(lang in RUN and marker != "no-test"
                                                            for marker, _, lang, _ in blocks((DOCS / p).read_text()))]
    assert not untested


@pytest.mark.parametrize("page", PAGES)
def test_the_page_runs(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    env = _env(tmp_path)
    for key in ("OMP_NUM_THREADS", "SONARSET_CACHE", "MPLBACKEND"):
        monkeypatch.setenv(key, env[key])
    namespace: dict = {"__name__": "__guide__"}
    ran = 0
    for i, (marker, arg, lang, code) in enumerate(blocks(shrunk(page))):
        where = f"{page}, block {i + 1} ({lang or 'text'})"
        t0 = time.perf_counter()
        if marker == "no-test":
            assert arg.strip(), f"{where}: say why it is not run"
            continue
        if marker == "file":
            (tmp_path / arg.strip()).parent.mkdir(parents=True, exist_ok=True)  # a bag directory's sidecar
            (tmp_path / arg.strip()).write_text(code)
            continue
        if lang in ("bash", "sh") and (commands := sonarset_commands(code)):
            for args in commands:
                r = CliRunner().invoke(app, args)
                assert r.exit_code == 0, f"{where}: sonarset {shlex.join(args)} failed:\n{r.output[-3000:]}\n{r.exception!r}"
            ran += 1
        elif lang in ("bash", "sh"):
            r = subprocess.run(["bash", "-euo", "pipefail", "-c", code], cwd=tmp_path, env=env,
                               capture_output=True, text=True, timeout=300)
            assert r.returncode == 0, f"{where} failed:\n{code}\n--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-3000:]}"
            ran += 1
        elif lang == "python":
            exec(compile(code, where, "exec"), namespace)
            ran += 1
        print(f"{where}: {time.perf_counter() - t0:.1f} s")
    assert ran, f"{page}: no block ran"
