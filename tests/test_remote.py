"""Remote stores that misbehave: every request is bounded in time, transient failures are retried,
and what still fails is one line naming the URL (sonarset.store.remote)."""

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sonarset.errors import RemoteError, SonarSetError
from sonarset.store.remote import RemoteLimits
from sonarset.store.store import open_store
from sonarset.store.validate import validate_store
from sonarset.testing import serve_directory

FAST = {"SONARSET_REMOTE_TIMEOUT": "1", "SONARSET_REMOTE_RETRIES": "2"}


@pytest.fixture
def fast_limits(monkeypatch):
    for k, v in FAST.items():
        monkeypatch.setenv(k, v)


@pytest.fixture
def retry_limits(monkeypatch):
    """FAST's retries with a timeout no loaded CI machine reaches: tests of failures that answer at
    once (HTTP 500, a cut body) must not fail on a slow healthy request instead (a 1 s timeout did,
    on a fresh-clone CI run, at the validate after the chunk reads)."""
    monkeypatch.setenv("SONARSET_REMOTE_TIMEOUT", "30")
    monkeypatch.setenv("SONARSET_REMOTE_RETRIES", FAST["SONARSET_REMOTE_RETRIES"])


@contextlib.contextmanager
def served(store, fault=None, times=-1):
    """(URL, handler) of ``store`` served over HTTP with ``fault``."""
    root, name = os.path.split(store.location)
    with serve_directory(root, fault, times) as (base, handler):
        yield f"{base}/{name}", handler


@pytest.mark.parametrize("fault", ["hang", "trickle"])
def test_a_server_that_never_finishes_answering_is_one_line_within_the_timeout(store, fast_limits, fault):
    with served(store, fault) as (url, _):
        t0 = time.perf_counter()
        with pytest.raises(RemoteError, match=rf"^{url}/zarr.json: no complete answer within 1 s .*SONARSET_REMOTE_TIMEOUT"):
            open_store(url)
        assert time.perf_counter() - t0 < 5
        with pytest.raises(RemoteError):  # validate cannot say anything about the store either
            validate_store(url)


@pytest.mark.parametrize("fault, cause", [("server_error", "HTTP 500"), ("short_body", "the answer was cut short")])
def test_persistent_server_failures_are_retried_then_reported_with_the_chunk_url(store, retry_limits, fault, cause):
    with served(store, fault) as (url, handler):
        remote = open_store(url)
        with pytest.raises(RemoteError, match=rf"^{url}/run_000/\w+/c/[0-9/]+: {cause}.*tried 3 times"):
            remote.run("run_000")["images"][:]
        with pytest.raises(RemoteError, match=cause):
            validate_store(url)  # not a finding about the store


@pytest.mark.parametrize("fault", ["server_error", "short_body"])
def test_a_transient_failure_is_retried_and_the_data_read_whole(store, retry_limits, fault):
    with served(store, fault, times=2) as (url, handler):
        images = np.asarray(open_store(url).run("run_000")["images"][:])
    np.testing.assert_array_equal(images, store.run("run_000")["images"][:])
    assert handler.faults_left == 0


def test_limits_come_from_the_environment_and_bad_values_are_refused(monkeypatch):
    monkeypatch.setenv("SONARSET_REMOTE_TIMEOUT", "2.5")
    monkeypatch.setenv("SONARSET_REMOTE_RETRIES", "0")
    assert RemoteLimits.from_environment() == RemoteLimits(timeout_s=2.5, retries=0)
    for value in ("soon", "0", "-1", "inf", "nan"):
        monkeypatch.setenv("SONARSET_REMOTE_TIMEOUT", value)
        with pytest.raises(SonarSetError, match="SONARSET_REMOTE_TIMEOUT"):
            RemoteLimits.from_environment()


def test_cli_on_a_hanging_server_exits_1_with_one_line(store):
    with served(store, "hang") as (url, _):
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "sonarset.cli", "info", url], capture_output=True, text=True,
                           env={**os.environ, **FAST}, timeout=60)
        elapsed = time.perf_counter() - t0
    assert r.returncode == 1, r.stderr
    assert r.stderr.strip().splitlines() == [f"error: {url}/zarr.json: no complete answer within 1 s "
                                             "(the limit is SONARSET_REMOTE_TIMEOUT)"]
    assert elapsed < 20


def test_an_absurd_length_behind_a_url_is_refused_from_a_few_requests(store):
    """A consistent edit to 1e12 frames, consolidated so URL readers trust it: every reader refuses
    it after a bisection (about 40 existence checks per array), in validate's quick pass too."""
    import zarr

    from tests.corruption_cases import _length

    _length(10**12)(Path(store.location))
    zarr.consolidate_metadata(store.location)
    with served(store) as (url, handler):
        t0 = time.perf_counter()
        with pytest.raises(SonarSetError, match=r"test_000/\w+: \d+ chunk\(s\) declared, but storage ends at chunk c/3"):
            open_store(url, check=True)
        for check_data in (False, True):
            found = [str(p) for p in validate_store(url, check_data=check_data)]
            assert any("storage ends at chunk c/3" in p for p in found), found
        assert time.perf_counter() - t0 < 20 and handler.requests < 2000
