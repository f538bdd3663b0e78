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
