"""`generate` killed at each distinct write phase resumes to the same bytes, with no leftovers.

A driver process runs the real CLI command with zarr's one file-write function wrapped: at write
number N it dies by SIGKILL, either mid-write ("torn": the temp file ``*.<id>.partial`` holds half
the bytes and was never renamed) or just after the write landed ("after"). The same command,
run again, must finish the store: arrays byte-identical to an uninterrupted run, no temp file
in or beside the store, and a store that validates.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import zarr.storage._local as zlocal
from typer.testing import CliRunner

from sonarset import open_store
from sonarset.cli.app import app
from sonarset.store.validate import validate_store

# Two runs of 66 frames (two image chunks each) on a small grid: every kind of write happens, and
# each kill costs about two seconds. (Grids of 12x8 or 16x12 bins trip the sonar model itself.)
ARGS = ["--runs", "1", "--test-runs", "1", "--minutes", "0.22", "--seed", "3", "--workers", "1",
        "--n-range", "20", "--n-azimuth", "10"]
KEYS = ("images", "velocity", "time", "pose", "snr_db", "slip")

DRIVER = r"""
# Imports once, then forks one child per kill (scipy alone takes seconds to import). Nothing here
# starts a thread before the forks: zarr's event loop starts in each child.
import json, os, signal, sys, threading, uuid
import zarr.storage._local as zlocal
from sonarset.cli.app import app
import sonarset.sim.generation

plan, argv = json.loads(sys.argv[1]), sys.argv[2:]
orig, lock, count = zlocal._put, threading.Lock(), [0]

def killer(kill_at, mode, log):
    def put(path, value, exclusive=False):
        with lock:
            count[0] += 1
            n = count[0]
        if n != kill_at:
            return orig(path, value, exclusive)
        with open(log, "w") as f:
            f.write(str(path))
        if mode == "torn":
            path.parent.mkdir(parents=True, exist_ok=True)
            data = bytes(value.as_buffer_like())
            with open(path.with_suffix(f".{uuid.uuid4().hex}.partial"), "wb") as f:
                f.write(data[: len(data) // 2])
        else:
            orig(path, value, exclusive)
        os.kill(os.getpid(), signal.SIGKILL)
    return put

status = {}
for out, kill_at, mode, log in plan:
    pid = os.fork()
    if pid == 0:
        zlocal._put = killer(kill_at, mode, log)
        sys.argv = ["sonarset", *[out if a == "OUT" else a for a in argv]]
        try:
            app()
        except SystemExit as exc:
            os._exit(exc.code if isinstance(exc.code, int) else 1)
        os._exit(0)
    _, st = os.waitpid(pid, 0)
    status[out] = -os.WTERMSIG(st) if os.WIFSIGNALED(st) else os.WEXITSTATUS(st)
print(json.dumps(status))
"""


def _relative(path: str, store: str) -> str:
    """The written file's path inside its store (the store being built aside, or in place)."""
    for marker in ("/store.zarr/", f"/{store}/"):
        if marker in path:
            return ("aside:" if marker == "/store.zarr/" else "") + path.split(marker, 1)[1]
    raise AssertionError(path)


def _phases(writes: list[str]) -> list[tuple[int, str, str]]:
    """(write number, phase name, mode) for each distinct moment of a generation."""
    rel = [_relative(w, "ref.zarr") for w in writes]
    where: dict[str, list[int]] = {}
    for i, r in enumerate(rel, start=1):
        where.setdefault(r, []).append(i)

    def first(r: str) -> int:
        return where[r][0]

    def last(r: str) -> int:
        return where[r][-1]

    done_000 = last("run_000/zarr.json")
    chosen = [
        (first("aside:zarr.json"), "store root created aside", "torn"),
        (last("aside:zarr.json"), "store root consolidated aside", "torn"),
        (last("aside:zarr.json"), "store built aside, not yet renamed", "after"),
        (first("run_000/zarr.json"), "run group created", "torn"),
        (first("zarr.json"), "root rewritten as a parent (temp file only)", "torn"),
        (first("run_000/images/zarr.json"), "images array created", "torn"),
        (first("run_000/azimuth/c/0"), "azimuth coordinates written", "after"),
        (first("run_000/images/c/0/0/0"), "first image chunk", "torn"),
        (first("run_000/images/c/1/0/0"), "second image chunk", "torn"),
        (first("run_000/velocity/c/0/0"), "vectors written at commit", "torn"),
        (done_000, "completion flag", "torn"),
        (done_000, "completion flag set", "after"),
        (min(i for i in where["zarr.json"] if i > done_000), "root consolidated after a run", "torn"),
        (len(rel), "final consolidation", "torn"),
        (len(rel), "final consolidation done", "after"),
    ]
    return chosen


def _arrays(location) -> dict:
    s = open_store(location)
    return {(n, k): s.run(n)[k][:] for n in s.runs() for k in KEYS}


def _leftovers(root: Path) -> list[str]:
    inside = [str(p.relative_to(root)) for p in root.rglob("*") if p.name.endswith(".partial")]
    beside = [p.name for p in root.parent.iterdir() if p.name.startswith(f".{root.name}.")]
    return inside + beside


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted generation, and the list of files it wrote, in order."""
    work = tmp_path_factory.mktemp("ref")
    writes: list[str] = []
    lock = threading.Lock()
    orig = zlocal._put

    def put(path, value, exclusive=False):
        with lock:
            writes.append(str(path))
        return orig(path, value, exclusive)

    zlocal._put = put
    try:
        res = CliRunner().invoke(app, ["generate", str(work / "ref.zarr"), *ARGS])
    finally:
        zlocal._put = orig
    assert res.exit_code == 0, res.output
    return _arrays(work / "ref.zarr"), writes


def _kill(tmp_path, cases: list[tuple[int, str]]) -> list[tuple[Path, Path, int]]:
    """Run the command once per (write number, mode), each killed there: (store, log, exit status)."""
    plan = [(str(tmp_path / f"k{k}" / "out.zarr"), n, mode, str(tmp_path / f"k{k}.log"))
            for k, (n, mode) in enumerate(cases)]
    for out, *_ in plan:
        Path(out).parent.mkdir()
    proc = subprocess.run([sys.executable, "-c", DRIVER, json.dumps(plan), "generate", "OUT", *ARGS],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    status = json.loads(proc.stdout.strip().splitlines()[-1])
    return [(Path(out), Path(log), status[out]) for out, _, _, log in plan]


def test_kill_at_every_write_phase_resumes_byte_identical(tmp_path, reference):
    ref, writes = reference
    phases = _phases(writes)
    assert len({name for _, name, _ in phases}) >= 10
    runner = CliRunner()
    killed_at = set()
    results = _kill(tmp_path, [(n, mode) for n, _, mode in phases])
    for (n, name, mode), (out, log, status) in zip(phases, results):
        assert status == -signal.SIGKILL, f"{name}: the command was not killed at write {n} (exit {status})"
        # zarr writes a node's metadata and its parents' concurrently, so write n may be a sibling
        # of the planned one; the phase is what was actually cut.
        killed_at.add((_relative(log.read_text(), "out.zarr"), mode))
        res = runner.invoke(app, ["generate", str(out), *ARGS])
        assert res.exit_code == 0, f"{name} ({mode}, write {n}): resume failed: {res.output}"
        assert _leftovers(out) == [], f"{name} ({mode}): leftovers after resume"
        got = _arrays(out)
        assert got.keys() == ref.keys(), name
        for key in ref:
            assert got[key].tobytes() == ref[key].tobytes(), f"{name} ({mode}): {key} differs"
        assert validate_store(out) == [], name
        # The root's consolidated snapshot lists both runs, complete.
        assert open_store(out, consolidated=True).runs() == ["run_000", "test_000"], name
    assert len(killed_at) >= 10, killed_at


def test_kill_leaves_incomplete_run_invisible(tmp_path, reference):
    """Between a run's first chunk and its completion flag, readers see only finished runs."""
    ref, writes = reference
    n = next(i for i, w in enumerate(writes, start=1) if w.endswith("test_000/images/c/0/0/0"))
    [(out, _, status)] = _kill(tmp_path, [(n, "after")])
    assert status == -signal.SIGKILL
    assert open_store(out).runs() == ["run_000"]
    np.testing.assert_array_equal(open_store(out).run("run_000").images[:], ref[("run_000", "images")])


def test_full_disk_is_one_line_and_resumable(tmp_path, reference, monkeypatch):
    import errno

    ref, writes = reference
    n = next(i for i, w in enumerate(writes, start=1) if w.endswith("test_000/images/c/1/0/0"))
    count = [0]
    orig = zlocal._put

    def put(path, value, exclusive=False):
        count[0] += 1
        if count[0] >= n:
            path.parent.mkdir(parents=True, exist_ok=True)
            raise OSError(errno.ENOSPC, "No space left on device")
        return orig(path, value, exclusive)

    out = tmp_path / "out.zarr"
    monkeypatch.setattr(zlocal, "_put", put)
    res = CliRunner().invoke(app, ["generate", str(out), *ARGS])
    monkeypatch.undo()
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert res.exit_code == 1 and len(lines) == 1, res.output
    assert "out.zarr" in lines[0] and "no space left on device" in lines[0] and "re-run" in lines[0]
    assert open_store(out).runs() == ["run_000"]
    res = CliRunner().invoke(app, ["generate", str(out), *ARGS])
    assert res.exit_code == 0, res.output
    got = _arrays(out)
    assert all(got[k].tobytes() == ref[k].tobytes() for k in ref) and got.keys() == ref.keys()
    assert _leftovers(out) == []


@pytest.mark.parametrize("damage", ["images array removed", "velocity chunk removed", "image chunk cut short"])
def test_a_rerun_repairs_a_run_flagged_complete_but_broken(tmp_path, reference, damage):
    """What a concurrent or interrupted writer can leave: a complete flag over a broken run. The
    same command re-simulates that run (deterministic: the same bytes), never says "complete"."""
    import shutil

    ref, _ = reference
    out = tmp_path / "s.zarr"
    assert CliRunner().invoke(app, ["generate", str(out), *ARGS]).exit_code == 0
    run = out / "test_000"
    if damage == "images array removed":
        shutil.rmtree(run / "images")
    elif damage == "velocity chunk removed":
        (run / "velocity" / "c" / "0" / "0").unlink()
    else:
        chunk = run / "images" / "c" / "1" / "0" / "0"
        chunk.write_bytes(chunk.read_bytes()[:100])
    assert validate_store(out)
    res = CliRunner().invoke(app, ["generate", str(out), *ARGS])
    assert res.exit_code == 0, res.output
    assert "wrote 1 run(s)" in res.output
    assert validate_store(out) == []
    got = open_store(out)
    for key in KEYS:
        np.testing.assert_array_equal(got.run("test_000")[key][:], ref[("test_000", key)])
