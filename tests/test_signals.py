"""Signals to a command with worker processes: no worker outlives it, no traceback (sonarset.pool)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sonarset.testing import pool_workers, running

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table in /proc")


def _interruptible() -> None:
    # A shell starts a background job (``cmd &``) with SIGINT ignored, and the ignore is inherited:
    # run under one, the command would rightly keep ignoring Ctrl-C. The test is of a command a
    # user can interrupt.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def generating(tmp_path) -> tuple[subprocess.Popen, set[int]]:
    """``generate --workers 2`` in its own session, once both workers run; (process, workers)."""
    proc = subprocess.Popen([sys.executable, "-m", "sonarset.cli", "generate", str(tmp_path / "s.zarr"),
                             "--minutes", "25", "--runs", "3", "--workers", "2"],
                            stderr=subprocess.PIPE, text=True, start_new_session=True, preexec_fn=_interruptible)
    deadline = time.monotonic() + 60
    workers: set[int] = set()
    while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
        workers = pool_workers(proc.pid)
    assert len(workers) >= 2, "the pool never started"
    return proc, workers


@pytest.mark.parametrize("how, code, says", [
    ("SIGINT to the process group at start-up", 130, "error: interrupted"),
    ("SIGINT to the process group", 130, "error: interrupted"),
    ("SIGTERM to the parent", 143, "error: terminated"),
    ("SIGKILL to the parent", -signal.SIGKILL, None),
])
def test_no_worker_outlives_a_signalled_generate(tmp_path, how, code, says):
    proc, workers = generating(tmp_path)
    if "start-up" not in how:
        time.sleep(2)  # the workers are simulating now
    sig = getattr(signal, how.split()[0])
    if "group" in how:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    _, stderr = proc.communicate(timeout=30)
    deadline = time.monotonic() + 10
    while any(map(running, workers)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(map(running, workers)), f"{how}: workers still running"
    assert proc.returncode == code, stderr
    assert "Traceback" not in stderr, stderr
    if says is not None:
        assert says in stderr.splitlines(), stderr


HELD = """
import os, signal, sys, threading, time
import sonarset.pool as pool
go, sent = threading.Event(), threading.Event()
def send():  # started before the block, so this thread does not block SIGINT: the kernel picks it
    go.wait()
    os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    sent.set()
threading.Thread(target=send, daemon=True).start()
steps = 0
try:
    with pool.terminated_as_interrupt():
        with pool.signals_held():
            go.set()
            sent.wait()
            for steps in range(1, 200):  # bytecode, calls and sleeps: where a handler would run
                time.sleep(0.001)
        print("not raised", flush=True)
except KeyboardInterrupt as e:
    print("raised after the block" if steps == 199 else f"raised at step {steps}", type(e).__name__)
"""


@pytest.mark.parametrize("sig, raised", [("SIGINT", "KeyboardInterrupt"), ("SIGTERM", "Terminated")])
def test_a_signal_while_a_worker_starts_waits_until_it_has(sig, raised):
    """A signal received by another thread while a worker is being started runs its handler only
    once the worker is (sonarset.pool.signals_held): never half-way through multiprocessing's start-up."""
    out = subprocess.run([sys.executable, "-c", HELD, sig], capture_output=True, text=True, timeout=60,
                         preexec_fn=_interruptible)
    assert out.stdout.splitlines() == [f"raised after the block {raised}"], out.stdout + out.stderr


# ---- any command: one line and the signal's exit status, whatever zarr's I/O loop was doing ------

def _threads(pid: int) -> int:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("Threads:")))


def _store_of_runs(path: Path, n: int) -> Path:
    """A store of ``n`` copies of one 2-frame run: what costs per run, built in a second."""
    import shutil

    from sonarset.store.store import create_store
    from tests.conftest import TINY, make_run

    create_store(path, TINY).write_run("run_000", **make_run(2))
    for i in range(1, n):
        shutil.copytree(path / "run_000", path / f"run_{i:03d}")
    return path


def _signalled(args: list[str], sig: int, *, when, after_s: float = 0.0, group: bool = False,
               env: dict | None = None):
    """Run the CLI with ``args``, send ``sig`` ``after_s`` after ``when(pid)`` holds; (exit status,
    stderr, seconds from the signal to the exit)."""
    proc = subprocess.Popen([sys.executable, "-m", "sonarset.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, preexec_fn=_interruptible,
                            env={**os.environ, "NO_COLOR": "1", "COLUMNS": "200", **(env or {})})
    deadline = time.monotonic() + 60
    while not when(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(after_s)
    assert proc.poll() is None, f"ended before the signal: {proc.communicate()[1]}"
    (os.killpg if group else os.kill)(proc.pid, sig)
    sent = time.monotonic()
    _, stderr = proc.communicate(timeout=30)
    return proc.returncode, stderr, time.monotonic() - sent


@pytest.fixture(scope="module")
def many_runs(tmp_path_factory) -> Path:
    return _store_of_runs(tmp_path_factory.mktemp("many") / "s.zarr", 400)


@pytest.mark.parametrize("sig, group, code, line", [
    (signal.SIGINT, True, 130, "error: interrupted"),
    (signal.SIGTERM, False, 143, "error: terminated"),
])
def test_interrupted_while_zarr_lists_runs_says_one_line(many_runs, sig, group, code, line):
    """Interrupted while zarr's I/O threads open hundreds of run groups at once (they appear with
    the first listing): zarr's exit hook used to print thousands of asyncio tracebacks, then
    'RuntimeError: Cannot close a running event loop'."""
    rc, stderr, took = _signalled(["info", str(many_runs)], sig, group=group, when=lambda pid: _threads(pid) >= 4,
                                  after_s=0.3)
    assert (rc, stderr.splitlines()) == (code, [line]), stderr[-3000:]
    assert took < 5


def test_terminated_while_blocked_on_a_hanging_server(tmp_path):
    """The main thread waits in zarr's ``sync`` for a request that does not return: the signal
    still ends the process at once."""
    from sonarset.testing import serve_directory

    _store_of_runs(tmp_path / "s.zarr", 2)
    with serve_directory(str(tmp_path), "hang") as (url, handler):
        rc, stderr, took = _signalled(["validate", f"{url}/s.zarr"], signal.SIGTERM,
                                      when=lambda pid: handler.requests > 0, env={"SONARSET_REMOTE_TIMEOUT": "60"})
    assert (rc, stderr.splitlines()) == (143, ["error: terminated"]), stderr
    assert took < 5


SWALLOWS = """
import time
import sonarset.pool as pool
pool.EXIT_GRACE_S = 1.0
with pool.terminated_as_interrupt():
    try:
        print("ready", flush=True)
        time.sleep(30)
    except KeyboardInterrupt:  # swallowed, as an exception raised in a __del__ is
        print("swallowed", flush=True)
    time.sleep(30)
"""


@pytest.mark.parametrize("signals", [1, 2])
def test_a_swallowed_signal_still_ends_the_process(signals):
    """One signal: the process ends once the grace for its clean-up is over; a second ends it at once."""
    proc = subprocess.Popen([sys.executable, "-c", SWALLOWS], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=_interruptible)
    assert proc.stdout.readline() == "ready\n"
    os.kill(proc.pid, signal.SIGTERM)
    assert proc.stdout.readline() == "swallowed\n"
    sent = time.monotonic()
    if signals == 2:
        os.kill(proc.pid, signal.SIGTERM)
    _, stderr = proc.communicate(timeout=30)
    took = time.monotonic() - sent
    assert (proc.returncode, stderr.splitlines()) == (143, ["error: terminated"]), stderr
    assert took < (0.5 if signals == 2 else 3)
