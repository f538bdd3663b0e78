"""The corruption suite (issue 14): every way a store can break, against every command that reads it.

Each kind damages a copy of one small generated store. For each kind, ``validate``, ``info``,
``eval``, ``train`` and ``show`` must end either with correct output (exit 0) or with clear
one-line errors and a non-zero exit: never a traceback, never an "internal error", never a
number computed from bad data. The expected outcome of every (kind, command) pair is written
down, so a command that starts accepting a broken store fails here as surely as one that crashes.

The kinds of damage and their expected outcomes are in tests/corruption_cases.py.

    python -m pytest -q tests/test_corruption.py -s     # also prints the kinds x commands table
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from sonarset.cli.app import app
from tests.corruption_cases import GRID  # noqa: F401 - bench/bench_readcheck.py imports it from here
from tests.corruption_cases import COMMANDS, FRAME, KINDS, Kind, make_base_store

runner = CliRunner()


# ---- running the commands ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def base_store(tmp_path_factory) -> Path:
    return make_base_store(tmp_path_factory.mktemp("corruption") / "base.zarr")


def _args(command: str, store: Path, work: Path) -> list[str]:
    s = str(store)
    return {
        "validate": ["validate", s],
        "info": ["info", s],
        "eval": ["eval", s, "--models", "persistence,naive,flow", "--samples", "20", "--horizons", "1,3",
                 "--out", str(work / "eval"), "--no-figures"],
        "train": ["train", s, "--preset", "tiny", "--out", str(work / "train"), "--max-steps", "1", "--n-val", "10",
                  "--batch-size", "8", "--device", "cpu", "--test-samples", "0"],
        "show": ["show", s, "--run", "test_000", "--frame", str(FRAME), "--out", str(work / "show.png")],
    }[command]


@dataclass
class Outcome:
    exit_code: int
    output: str
    crashed: str | None  # the exception that escaped the command, if any

    @property
    def error_lines(self) -> list[str]:
        return [line for line in self.output.splitlines()
                if re.match(r"^(error|invalid|implausible|internal error):", line)]


def run_command(command: str, store: Path, work: Path) -> Outcome:
    return invoke(_args(command, store, work))


def invoke(args: list[str]) -> Outcome:
    r = runner.invoke(app, args)
    crashed = None
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        crashed = f"{type(r.exception).__name__}: {r.exception}"
    return Outcome(r.exit_code, r.output, crashed)


def judge(kind: Kind, command: str, o: Outcome) -> str | None:
    """None when the command behaved as the kind expects, else what went wrong."""
    if o.crashed is not None or "Traceback" in o.output or "internal error" in o.output:
        return f"crashed: {o.crashed or o.output.strip().splitlines()[-1]}"
    expected = kind.says.get(command, kind.where)
    if command in kind.ok:
        if o.exit_code != 0:
            return f"expected success, got exit {o.exit_code}: {' | '.join(o.error_lines) or o.output[-300:]}"
        if command in kind.says and expected not in o.output:
            return f"output lacks {expected!r}"
        return None
    if o.exit_code == 0:
        return "accepted a broken store (exit 0)"
    lines = o.error_lines
    if not lines:
        return f"exit {o.exit_code} without an error line: {o.output[-300:]!r}"
    if command != "validate" and len(lines) != 1:
        return f"{len(lines)} error lines, expected one: {lines}"
    if command == "validate" and len(lines) > 8:
        return f"{len(lines)} findings for one corruption: {lines}"
    if not any(expected in line for line in lines):
        return f"error does not say {expected!r}: {lines}"
    if command == "eval" and "| method |" in o.output:
        return "printed a results table as well as an error"
    return None


RESULTS: dict[str, dict[str, str]] = {}


def check_kind(kind: Kind, base: Path, work: Path) -> dict[str, tuple[str, str | None]]:
    """Corrupt a copy of ``base`` as ``kind`` says and run every command on it:
    command -> (what happened, None or what went wrong)."""
    store = work / "store.zarr"
    shutil.copytree(base, store)
    kind.apply(store)
    out = {}
    for command in COMMANDS:
        (work / command).mkdir()
        o = run_command(command, store, work / command)
        status = "ok" if o.exit_code == 0 else f"refused ({o.exit_code})"
        out[command] = (status, judge(kind, command, o))
    return out


def test_suite_is_large_enough():
    assert len(KINDS) >= 30 and len({k.name for k in KINDS}) == len(KINDS)


def test_intact_store_passes_every_command(base_store, tmp_path):
    intact = Kind("intact", lambda s: None, "", ok=COMMANDS, says={"eval": "| flow |"})
    got = check_kind(intact, base_store, tmp_path)
    assert all(problem is None for _, problem in got.values()), got


@pytest.mark.parametrize("kind", KINDS, ids=[k.name for k in KINDS])
def test_corruption(kind: Kind, base_store, tmp_path):
    got = check_kind(kind, base_store, tmp_path)
    RESULTS[kind.name] = {c: status if problem is None else f"BAD: {problem}" for c, (status, problem) in got.items()}
    bad = {c: problem for c, (_, problem) in got.items() if problem is not None}
    assert not bad, f"{kind.name}: {bad}"


def read_everything(location: Path) -> str | None:
    """The error a reader raises reading the whole store as the tools do (opened with the checks
    ``eval`` and ``train`` make, every run group by name, every array of each run through the
    checked read, the rig); None when everything reads."""
    from sonarset.errors import SonarSetError
    from sonarset.format.arrays import ARRAYS
    from sonarset.store.store import open_store

    try:
        store = open_store(location, check=True)
        _ = store.rig  # the rig is part of reading everything: a corrupt rig attribute raises here
        for name in store.runs(include_incomplete=True):
            run = store.run(name)
            for key, spec in ARRAYS.items():
                if spec.required or run.has(key):
                    run.read(key)
            run.load()
    except SonarSetError as exc:
        return str(exc)
    return None


@pytest.mark.parametrize("kind", KINDS, ids=[k.name for k in KINDS])
def test_validate_and_the_readers_agree(kind: Kind, base_store, tmp_path):
    """One rule, one verdict: ``validate`` reports a problem that readers refuse exactly when a
    reader refuses the store, and the reader's error names a node that ``validate`` names."""
    from sonarset.store.validate import validate_store

    store = tmp_path / "store.zarr"
    shutil.copytree(base_store, store)
    kind.apply(store)
    problems = validate_store(store)
    refusing = [p for p in problems if p.refused_by_readers]
    refused = read_everything(store)
    assert bool(refusing) == (refused is not None), (refused, [str(p) for p in problems])
    if refused is not None:
        assert any(refused.startswith(f"{p.where}:") for p in refusing), (refused, [str(p) for p in refusing])


@pytest.mark.parametrize("name", ["run zarr.json is `true`", "images data_type float17"])
def test_validate_consolidate_names_the_broken_node(name, base_store, tmp_path):
    """Re-consolidating parses every node: a broken one is named, in one line."""
    kind = next(k for k in KINDS if k.name == name)
    store = tmp_path / "store.zarr"
    shutil.copytree(base_store, store)
    kind.apply(store)
    o = invoke(["validate", str(store), "--consolidate"])
    assert o.crashed is None and o.exit_code == 1, o
    assert len(o.error_lines) == 1 and "test_000" in o.error_lines[0] and "cannot consolidate" in o.error_lines[0]


def _leaf_paths(doc, prefix=()) -> list[tuple]:
    out = [prefix] if prefix else []
    if isinstance(doc, dict) and prefix[:1] != ("consolidated_metadata",):
        for k, v in doc.items():
            out += _leaf_paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:3]):
            out += _leaf_paths(v, prefix + (i,))
    return out


def test_metadata_fuzz_never_crashes(base_store, tmp_path):
    """Any field of a run's or the root's zarr.json replaced by a value of another type: every
    command ends with a clean line or correct output. (A sweep of all 217 fields found two
    crashes, fixed; this keeps a seeded sample of 24.)"""
    import random

    files = ["zarr.json", "test_000/zarr.json", "test_000/images/zarr.json", "test_000/velocity/zarr.json",
             "test_000/time/zarr.json"]
    cases = [(f, p) for f in files for p in _leaf_paths(json.loads((base_store / f).read_text()))]
    rng = random.Random(14)
    failures = []
    for i, (f, path) in enumerate(rng.sample(cases, 24)):
        store = tmp_path / f"c{i}" / "s.zarr"
        shutil.copytree(base_store, store)
        doc = json.loads((store / f).read_text())
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value = rng.choice([None, True, "x", -1, [], {}, 1e308, "NaN"])
        (store / f).write_text(json.dumps(doc))
        for args in (["validate"], ["info"], ["eval", "--samples", "5", "--horizons", "1", "--no-figures",
                                               "--out", str(store.parent / "ev")]):
            o = invoke([args[0], str(store), *args[1:]])
            if o.crashed or "Traceback" in o.output or (o.exit_code != 0 and not o.error_lines):
                failures.append((f, path, value, args[0], o.crashed or o.output[-200:]))
    assert not failures, failures


def test_validate_answers_an_absurd_length_at_once(base_store, tmp_path):
    """A run whose shape and ``n_frames`` say 1e8 frames over 150 stored: the format checks refuse
    it from the chunk counts, and the plausibility pass must not then read the 1e8 declared
    commands (it took 86 s and 3.3 GB; 1e9 frames never answered). Run as a user would, with
    memory capped at 2 GiB so that a regression fails instead of swapping."""
    import subprocess
    import sys

    from tests.corruption_cases import _length

    store = tmp_path / "store.zarr"
    shutil.copytree(base_store, store)
    _length(10**8)(store)

    # A small interpreter runs the command with the cap and reports its child's peak RSS: measured
    # from here, the child's peak would count this large test process's pages (Linux keeps the
    # high-water mark of the address space a forked child starts from across its exec).
    runner = ("import json, resource, subprocess, sys, time\n"
              "cap = lambda: resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))\n"
              "t0 = time.monotonic()\n"
              "try:\n"
              "    p = subprocess.run([sys.executable, '-m', 'sonarset.cli', 'validate', sys.argv[1]], preexec_fn=cap,\n"
              "                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=60)\n"
              "    code, err = p.returncode, p.stderr\n"
              "except subprocess.TimeoutExpired as e:\n"
              "    code, err = None, e.stderr or ''\n"
              "print(json.dumps([code, err, time.monotonic() - t0,\n"
              "                  resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024]))\n")
    out = subprocess.run([sys.executable, "-c", runner, str(store)], capture_output=True, text=True,
                         env={**os.environ, "NO_COLOR": "1", "COLUMNS": "300"}, timeout=120)
    exit_code, stderr, seconds, peak_mb = json.loads(out.stdout)
    lines = (stderr or "").splitlines()
    assert exit_code == 1 and all(line.startswith("invalid:") for line in lines), lines
    assert any("test_000/velocity: at least" in line for line in lines), lines
    assert seconds < 20 and peak_mb < 500, (seconds, peak_mb)


def test_remote_store_checks_each_chunk_as_it_is_read(base_store, tmp_path):
    """Over a URL the open check cannot fetch every chunk; the read that needs one checks it."""
    from sonarset.errors import FormatError
    from sonarset.store.store import open_store
    from sonarset.testing import serve_directory
    from sonarset.store.validate import validate_store
    from sonarset.windows import FrameBank

    shutil.copytree(base_store, tmp_path / "s.zarr")
    chunk = tmp_path / "s.zarr" / "test_000" / "velocity" / "c" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:600])  # stored uncompressed: zarr would decode garbage
    with serve_directory(str(tmp_path)) as (url, _):
        store = open_store(f"{url}/s.zarr", check=True)
        assert len(FrameBank.from_store(store, split="train").run_names) == 1  # the intact run loads
        with pytest.raises(FormatError, match=r"s.zarr/test_000/velocity: chunk c/0/0 is corrupt or truncated: "
                                              r"its blosc header declares 1216 bytes, 1220 with its checksum; "
                                              r"the chunk has 600; checksum mismatch"):
            FrameBank.from_store(store, split="test")
        problems = [str(p) for p in validate_store(f"{url}/s.zarr")]
    assert any("test_000/velocity: chunk c/0/0 is corrupt or truncated" in p for p in problems), problems


def test_eval_takes_dt_from_the_time_stamps(tmp_path, monkeypatch):
    """The baselines step by the median spacing of the time stamps, not by the declared rate."""
    from sonarset.models import registry
    from sonarset.models.eval.evaluate import evaluate
    from sonarset.store.store import create_store
    from tests.conftest import TINY, make_run

    s = create_store(tmp_path / "s.zarr", TINY)  # declares 5 Hz; the stamps are 4 % slower
    s.write_run("test_000", **{**make_run(12), "time": np.arange(12) * 0.208}, split="test")
    seen = []
    real = registry.make_predictor

    def spy(spec, grid, rig, **kw):
        seen.append(rig.frame_interval_s)
        return real(spec, grid, rig, **kw)

    monkeypatch.setattr(registry, "make_predictor", spy)
    res = evaluate(s, ["naive", "flow"], horizons=(1,), samples=5)
    assert seen == [pytest.approx(0.208)] * 2
    assert "naive and flow use the time stamps' 0.208 s frames" in res.notes[0]


def test_eval_counts_windows_whose_cc_is_undefined(tmp_path):
    from sonarset.models.eval.report import results_table
    from sonarset.models.eval.evaluate import evaluate
    from sonarset.store.store import create_store
    from tests.conftest import TINY, make_run

    run = make_run(20)
    run["images"][8:] = 0.5  # targets of windows 5..16 are constant
    s = create_store(tmp_path / "s.zarr", TINY)
    s.write_run("test_000", **run, split="test")
    res = evaluate(s, ["persistence", "naive"], horizons=(1,), samples=100)
    assert len(res.window_ids) == 17
    assert ("note: CC is undefined where the target frame or the prediction is constant: 12 of 17 windows at "
            "one-shot; those windows are left out of its means, stds and tests") in res.notes
    summary = res.summary()
    assert summary["naive"]["1"]["n"] == 5 and summary["naive"]["1"]["nrmsd"]["mean"] is not None
    run["images"][:] = 0.5
    s.write_run("test_000", **run, split="test", overwrite=True)
    res = evaluate(s, ["naive"], horizons=(1,), samples=100)
    assert res.summary()["naive"]["1"]["cc"] == {"mean": None, "std": None}
    assert "| naive | undefined |" in results_table(res, with_paper=False)


def table(results: dict[str, dict[str, str]]) -> str:
    lines = ["| corruption | " + " | ".join(COMMANDS) + " |", "|---" * (1 + len(COMMANDS)) + "|"]
    for name, row in results.items():
        lines.append(f"| {name} | " + " | ".join(row.get(c, "-") for c in COMMANDS) + " |")
    return "\n".join(lines)


def test_zz_print_table():
    """Print the kinds x commands table (run with -s to see it)."""
    if RESULTS:
        print("\n" + table(RESULTS))
    assert all(not v.startswith("BAD") for row in RESULTS.values() for v in row.values())


if __name__ == "__main__":  # pragma: no cover - python -m tests.test_corruption prints the table
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        base = make_base_store(Path(tmp) / "base.zarr")
        res = {}
        for i, kind in enumerate(KINDS):
            work = Path(tmp) / f"k{i}"
            got = check_kind(kind, base, work)
            res[kind.name] = {c: s if p is None else f"BAD: {p}" for c, (s, p) in got.items()}
        print(table(res))
        os._exit(0 if all(not v.startswith("BAD") for row in res.values() for v in row.values()) else 1)
