"""Scale-out: Dask generation, stores behind URLs (memory://, a loopback HTTP server), DDP training."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from sonarset.format.attrs import SensorGrid
from sonarset.sim import generate
from sonarset.store.store import open_store
from sonarset.testing import serve_directory
from sonarset.store.validate import validate_store
from sonarset.windows import FrameBank, WindowIndex, gather

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)
KW = dict(runs=2, test_runs=1, minutes=0.3, seed=11, grid=GRID)

distributed = pytest.importorskip("distributed")


def arrays(store):
    return {(n, k): np.asarray(store.run(n)[k][:]) for n in store.runs() for k in ("images", "velocity", "time", "pose")}


def assert_identical(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].tobytes() == b[k].tobytes(), k


@pytest.fixture(scope="module")
def local_ref(tmp_path_factory):
    path = tmp_path_factory.mktemp("ref") / "ref.zarr"
    generate(path, workers=1, **KW)
    return open_store(path)


@pytest.mark.slow
def test_dask_local_cluster_generation_equals_local_generation(local_ref, tmp_path):
    out = tmp_path / "dask.zarr"
    written = generate(out, workers=2, scheduler="local", **KW)
    assert sorted(written) == ["run_000", "run_001", "test_000"]
    assert_identical(arrays(local_ref), arrays(open_store(out)))
    assert validate_store(out) == []
    # resume: complete runs are kept, the missing one is redone by the cluster
    s = open_store(out, "r+")
    s.delete_run("run_001")
    s.consolidate()
    assert generate(out, workers=2, scheduler="local", **KW) == ["run_001"]
    assert_identical(arrays(local_ref), arrays(open_store(out)))


def test_dask_writes_a_memory_url_store_that_validates_and_reads_back(local_ref):
    from distributed import Client, LocalCluster

    url = "memory://scaling/dask.zarr"
    # memory:// lives in one process: the cluster's workers are threads of this one
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        generate(url, workers=2, scheduler=client, **KW)
    assert validate_store(url) == []
    s = open_store(url)
    assert type(s.group.store).__name__ == "ChunkCache"
    assert_identical(arrays(local_ref), arrays(s))


def test_unreachable_scheduler_is_a_clear_error(tmp_path, monkeypatch):
    from sonarset.errors import SonarSetError
    from sonarset.sim import distributed as sim_distributed

    monkeypatch.setattr(sim_distributed, "CONNECT_TIMEOUT", "2s")
    with pytest.raises(SonarSetError, match="cannot reach the Dask scheduler"):
        generate(tmp_path / "x.zarr", workers=1, scheduler="tcp://127.0.0.1:9", **KW)


@pytest.fixture
def http_root(local_ref):
    """The reference store served read-only over HTTP on loopback: (URL, request counter)."""
    with serve_directory(os.path.dirname(local_ref.location)) as (base, handler):
        yield f"{base}/{os.path.basename(local_ref.location)}", handler


def test_store_over_http_validates_reads_identically_and_caches_chunks(local_ref, http_root):
    from typer.testing import CliRunner

    from sonarset.cli.app import app

    http_root, served = http_root
    assert validate_store(http_root) == []
    remote = open_store(http_root)
    assert_identical(arrays(local_ref), arrays(remote))
    r = CliRunner().invoke(app, ["info", http_root, "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["runs"][0]["name"] == "run_000"
    # window by window through the lazy path: each chunk crosses the network once
    run = open_store(http_root).run("run_000")
    served.requests = 0
    for k in range(0, run.n_frames - 4):
        run.images[k:k + 4]
    assert 0 < served.requests <= 4  # chunks of 64 frames: 90 frames are 2 chunks (+ metadata)
    # and the in-memory bank built from the URL equals the local one
    idx = WindowIndex.build(FrameBank.from_store(local_ref), 3, 1)
    f_local = gather(FrameBank.from_store(local_ref), idx, np.arange(10))
    f_remote = gather(FrameBank.from_store(open_store(http_root)), idx, np.arange(10))
    for field in ("frames", "commands", "targets"):
        np.testing.assert_array_equal(getattr(f_local, field), getattr(f_remote, field))


@pytest.mark.slow
def test_two_process_gloo_ddp_matches_single_process_training(local_ref, tmp_path):
    from sonarset.models.echopt.checkpoint import load_checkpoint

    store = local_ref.location
    args = ["train", store, "--preset", "tiny", "--max-steps", "3", "--eval-every", "3", "--n-val", "8",
            "--batch-size", "8", "--device", "cpu", "--test-samples", "0", "--lr", "1e-3"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    ddp = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                          "-m", "sonarset.cli", *args, "--out", str(tmp_path / "ddp")],
                         capture_output=True, text=True, env=env, timeout=300)
    assert ddp.returncode == 0, ddp.stderr[-3000:]
    one = subprocess.run([sys.executable, "-m", "sonarset.cli", *args, "--out", str(tmp_path / "one")],
                         capture_output=True, text=True, env=env, timeout=300)
    assert one.returncode == 0, one.stderr[-3000:]
    m_ddp, card = load_checkpoint(tmp_path / "ddp", GRID)
    m_one, _ = load_checkpoint(tmp_path / "one", GRID)
    assert card["processes"] == 2 and card["steps"] == 3
    for (k, a), b in zip(m_ddp.state_dict().items(), m_one.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=k)
    log = [json.loads(line) for line in (tmp_path / "ddp" / "metrics.jsonl").read_text().splitlines()]
    ref = [json.loads(line) for line in (tmp_path / "one" / "metrics.jsonl").read_text().splitlines()]
    assert len(log) == len(ref) == 1
    assert log[0]["val_loss"] == pytest.approx(ref[0]["val_loss"], rel=1e-4)


def test_chunk_cache_evicts_the_least_recently_used_values_within_its_budget():
    import asyncio

    from zarr.core.buffer import cpu, default_buffer_prototype
    from zarr.storage import MemoryStore

    from sonarset.store.cache import ChunkCache

    proto = default_buffer_prototype()

    async def scenario():
        mem = MemoryStore()
        for key, size in (("a", 100), ("b", 100), ("c", 100), ("big", 300)):
            await mem.set(key, cpu.Buffer.from_bytes(bytes([len(key)]) * size))
        cache = ChunkCache(mem, max_bytes=250)
        got = [await cache.get(k, proto) for k in ("a", "b", "a", "c")]  # "a" used again: "b" goes
        assert [len(v) for v in got] == [100] * 4 and cache._size == 200 and list(cache._lru) == [
            ("a", "None"), ("c", "None")]
        assert (cache.hits, cache.misses) == (1, 3)
        await cache.get("a", proto)
        await cache.get("b", proto)  # evicted: fetched again, and now "c" is the oldest
        assert (cache.hits, cache.misses) == (2, 4) and [k for k, _ in cache._lru] == ["a", "b"]
        big = await cache.get("big", proto)  # larger than the whole budget: served, never kept
        assert len(big) == 300 and cache._size == 200 and await cache.get("missing", proto) is None

    asyncio.run(scenario())
