"""One writer at a time (store/lock.py), with real processes: a second writer is refused in one
line, two same-name imports leave one run and one refusal, and a killed holder leaves no lock."""

import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from sonarset import open_store
from sonarset.store.lock import lock_path, writer_lock
from sonarset.store.validate import validate_store

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="flock is POSIX")


def _sonarset(*args, cwd) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "sonarset.cli", *map(str, args)], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "COLUMNS": "200", "NO_COLOR": "1"})


def _errors(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("error:")]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    where = tmp_path_factory.mktemp("rec")
    rng = np.random.default_rng(3)
    T, R, A = 12, 32, 16
    np.savez(where / "rec.npz", images=rng.random((T, R, A), dtype=np.float32),
             velocity=np.c_[rng.uniform(0, 0.3, T), rng.uniform(-0.5, 0.5, T)].astype(np.float32),
             time=np.arange(T) * 0.2, range=0.5 + (np.arange(R) + 0.5) * (4.5 / R),
             azimuth=-np.pi / 2 + (np.arange(A) + 0.5) * (np.pi / A))
    return where / "rec.npz"


def test_a_second_writer_is_refused_naming_the_holder(recording, tmp_path):
    store = tmp_path / "s.zarr"
    with writer_lock(store):
        for args in (["import", recording, store, "--name", "A"],
                     ["generate", store, "--runs", "1", "--test-runs", "0", "--minutes", "0.1", "--workers", "1"]):
            p = _sonarset(*args, cwd=tmp_path)
            out, err = p.communicate(timeout=120)
            assert p.returncode == 1, out + err
            assert _errors(err) == [f"error: {store}: another writer is at work on it (pid {os.getpid()} on "
                                    f"{json.loads(lock_path(store).read_text())['host']} since "
                                    f"{json.loads(lock_path(store).read_text())['since']}); a store takes one "
                                    "writer at a time"], err
    assert not store.exists()  # nothing was written while the lock was held
    p = _sonarset("import", recording, store, "--name", "A", cwd=tmp_path)  # released: the import goes in
    assert p.wait(timeout=120) == 0


def test_two_imports_of_one_name_leave_one_run_and_one_refusal(recording, tmp_path):
    for attempt in range(4):
        store = tmp_path / f"s{attempt}.zarr"
        if attempt % 2:  # into an existing store as well as a new one
            assert _sonarset("import", recording, store, "--name", "B", cwd=tmp_path).wait(timeout=120) == 0
        procs = [_sonarset("import", recording, store, "--name", "A", cwd=tmp_path) for _ in range(2)]
        results = [(p.wait(timeout=120), p.communicate()[1]) for p in procs]
        codes = sorted(code for code, _ in results)
        assert codes == [0, 1], results
        refusal = _errors(next(err for code, err in results if code == 1))
        assert len(refusal) == 1 and ("another writer" in refusal[0] or "already exists" in refusal[0]), refusal
        assert open_store(store).runs() == (["A", "B"] if attempt % 2 else ["A"])
        assert validate_store(store) == []


def test_a_killed_holder_leaves_no_lock(tmp_path):
    store = tmp_path / "s.zarr"
    code = ("import os, signal; from sonarset.store.lock import writer_lock\n"
            f"with writer_lock({str(store)!r}):\n    os.kill(os.getpid(), signal.SIGKILL)\n")
    assert subprocess.run([sys.executable, "-c", code]).returncode == -signal.SIGKILL
    assert lock_path(store).exists()  # the file stays, the kernel's lock went with the process
    with writer_lock(store):
        pass
