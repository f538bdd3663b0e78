"""Streaming windows (sonarset.stream, StreamingWindowDataset, train/eval --stream): every window
once per epoch, the same batches run to run, exact resume, DDP shards, URLs, and eval's numbers."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from sonarset import open_store
from sonarset.format.attrs import SensorGrid
from sonarset.sim import generate
from sonarset.stream import ShardPlan, WindowStream, batches_per_rank, make_slabs, window_bank
from sonarset.testing import serve_directory
from sonarset.torchdata import StreamingLoader, StreamingWindowDataset
from sonarset.windows import FrameBank, RunLayout, WindowBatcher, WindowIndex

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("stream") / "s.zarr"
    generate(path, runs=3, test_runs=1, minutes=0.5, seed=4, workers=1, grid=GRID)
    return open_store(path)


def _dataset(store, **kw):
    base = dict(n_in=3, horizon=2, batch_size=16, seed=5, shuffle_buffer=40, slab_frames=64)
    return StreamingWindowDataset.from_store(store.location, "train", **{**base, **kw})


def _epoch(store, workers=0, state=None, stop=None, **kw):
    """The starts of each batch of one epoch (stopping after ``stop`` batches), and the state then."""
    loader = StreamingLoader(_dataset(store, **kw), num_workers=workers)
    if state is not None:
        loader.load_state_dict(state)
    out = []
    for b in loader:
        out.append(b["starts"].numpy())
        if stop is not None and len(out) == stop:
            break
    return out, loader.state_dict()


def test_layout_numbers_windows_as_the_bank_does(store):
    bank = FrameBank.from_store(store, split="train")
    layout = RunLayout.of(store, split="train")
    assert layout.run_names == bank.run_names and np.array_equal(layout.run_offsets, bank.run_offsets)
    assert layout.frame_interval_s == pytest.approx(bank.frame_interval_s)
    assert np.array_equal(layout.index(3, 5).starts, WindowIndex.build(bank, 3, 5).starts)


@pytest.mark.parametrize("workers", [0, 2])
def test_every_window_once_per_epoch_with_the_in_memory_contents(store, workers):
    bank = FrameBank.from_store(store, split="train")
    index = WindowIndex.build(bank, 3, 2)
    batches, state = _epoch(store, workers)
    starts = np.concatenate(batches)
    assert len(starts) == len(index) and np.array_equal(np.sort(starts), index.starts)
    assert state == {"epoch": 1, "consumed": {}}  # a finished epoch moves on
    # a batch holds exactly what the in-memory batcher gathers for the same windows
    loader = StreamingLoader(_dataset(store), num_workers=0)
    b = next(iter(loader))
    ref = WindowBatcher.of(bank).gather(index, np.searchsorted(index.starts, b["starts"].numpy()))
    for key in ("frames", "commands", "targets"):
        np.testing.assert_array_equal(b[key].numpy(), getattr(ref, key).astype(np.float32))


def test_same_batches_run_to_run_and_new_order_each_epoch(store):
    a, _ = _epoch(store, 2)
    b, _ = _epoch(store, 2)
    assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    ds = _dataset(store)
    ds.set_epoch(1)
    loader = StreamingLoader(ds)
    c = [x["starts"].numpy() for x in loader]
    assert not np.array_equal(np.concatenate(c), np.concatenate(_epoch(store, 0)[0]))


@pytest.mark.parametrize("workers", [0, 2])
def test_resume_mid_epoch_continues_exactly(store, workers):
    whole, _ = _epoch(store, workers)
    head, state = _epoch(store, workers, stop=5)
    assert sum(state["consumed"].values()) == 5
    tail, _ = _epoch(store, workers, state=json.loads(json.dumps(state)))  # a state survives JSON
    assert len(head) + len(tail) == len(whole)
    assert all(np.array_equal(x, y) for x, y in zip(head + tail, whole))


def test_shards_are_disjoint_equal_and_bounded_in_memory(store):
    layout = RunLayout.of(store, split="train")
    index = layout.index(3, 2)
    slabs = make_slabs(layout, index.starts, 5, slab_frames=64)
    plans = [ShardPlan.make(slabs, 0, 1, s, 3, shuffle_buffer=40) for s in range(3)]
    sizes = [len(p) for p in plans]
    assert max(sizes) - min(sizes) <= 1 and sum(sizes) == len(index)
    assert len(np.unique(np.concatenate([p.starts for p in plans]))) == len(index)
    # the windows of one shard are mixed, not read slab after slab in order
    assert not np.array_equal(plans[0].starts, np.sort(plans[0].starts))
    # held slabs stay within the shuffle buffer's open slabs plus the read-ahead
    stream = WindowStream(store, layout, slabs, 3, 2, 8, plans[0])
    held, alive, most = [], set(), [0]
    orig = stream._read

    class Slab(np.ndarray):  # a slab that says when the stream lets it go
        def __del__(self):
            alive.discard(id(self))

    def counting(piece):
        held.append(piece)
        block = orig(piece).view(Slab)
        alive.add(id(block))
        most[0] = max(most[0], len(alive))
        return block
    stream._read = counting
    assert sum(len(b) for b in stream) == sizes[0]
    n_open = math.ceil(40 / (sizes[0] / len(plans[0].pieces)))
    assert len(set(held)) == len(plans[0].pieces)  # each slab read once
    # slabs held at once: the open ones, those read ahead, and one opened within a batch
    assert most[0] <= n_open + stream.prefetch + 2, (most[0], n_open)
    assert batches_per_rank(len(index), 2, 2, 16) == min(
        sum(s // 16 for s in [(k + 1) * len(index) // 4 - k * len(index) // 4 for k in r]) for r in ((0, 1), (2, 3)))


def test_streams_from_an_http_url_as_from_disk(store):
    local, _ = _epoch(store, 0)
    root = os.path.dirname(store.location)
    with serve_directory(root) as (base, served):
        url = f"{base}/{os.path.basename(store.location)}"
        remote, _ = _epoch(open_store(url), 0)
    assert len(local) == len(remote) and all(np.array_equal(a, b) for a, b in zip(local, remote))


def test_window_bank_reads_only_the_windows_and_gives_the_same_numbers(store):
    from sonarset.models.eval.evaluate import evaluate

    layout = RunLayout.of(store, split="train")
    index = layout.index(3, 4).sample(20, seed=1)
    held = window_bank(store, layout, index)
    whole = FrameBank.from_store(store, split="train")
    assert held.images.nbytes < whole.images.nbytes / 2
    a, b = WindowBatcher.of(held).gather(index), WindowBatcher.of(whole).gather(index)
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.targets, b.targets)
    with pytest.raises(IndexError, match="outside the windows"):
        held.images[np.setdiff1d(np.arange(whole.n_frames), index.rows())[:1]]
    last = int(index.rows().max())
    if last == whole.n_frames - 1:
        np.testing.assert_array_equal(held.images[-1], whole.images[-1])  # negative rows count from the end
    for bad in (np.ones(whole.n_frames, dtype=bool), 1.5, slice(0, 2)):
        with pytest.raises(TypeError, match="integer rows"):
            held.images[bad]
    kw = dict(horizons=(1, 3), samples=40, split="train", ceiling=True)
    streamed, loaded = evaluate(store, ["flow", "naive"], stream=True, **kw), evaluate(store, ["flow", "naive"], **kw)
    assert streamed.window_ids == loaded.window_ids
    for m in loaded.per_window:
        for h in (1, 3):
            for k, v in loaded.per_window[m][h].items():
                np.testing.assert_array_equal(streamed.per_window[m][h][k], v, err_msg=f"{m} {h} {k}")


def test_train_stream_resumes_to_the_uninterrupted_result(store, tmp_path):
    from sonarset.errors import SonarSetError
    from sonarset.models.echopt.checkpoint import load_checkpoint
    from sonarset.models.echopt.train import train
    from sonarset.models.echopt.train_config import TrainConfig

    def cfg(**kw):
        base = dict(preset="tiny", epochs=3, batch_size=16, lr=1e-3, n_val=20, eval_every=3, device="cpu",
                    test_samples=0, command="test", stream=True, shuffle_buffer=40, max_steps=9, curriculum="0:1,5:2")
        return TrainConfig(**{**base, **kw})

    full = train(store, tmp_path / "full", cfg())
    part = train(store, tmp_path / "part", cfg(max_minutes=1e-9))
    assert part.steps == 1
    resumed = train(store, tmp_path / "part", cfg(), resume=True)
    assert resumed.steps == 9
    at = [(r["step"], r["val_loss"]) for r in full.history if r["step"] % 3 == 0]
    assert at == [(r["step"], r["val_loss"]) for r in resumed.history if r["step"] % 3 == 0]  # bit for bit
    wa, card = load_checkpoint(tmp_path / "full", GRID)
    wb, _ = load_checkpoint(tmp_path / "part", GRID)
    for a, b in zip(wa.state_dict().values(), wb.state_dict().values()):
        assert torch.equal(a, b)
    assert card["training"]["config"]["stream"] is True
    with pytest.raises(SonarSetError, match="resume with shuffle_buffer"):
        train(store, tmp_path / "full", cfg(shuffle_buffer=80), resume=True)
    # in memory, how a stream would be read does not matter
    train(store, tmp_path / "mem", cfg(stream=False, max_minutes=1e-9))
    assert train(store, tmp_path / "mem", cfg(stream=False, shuffle_buffer=80), resume=True).steps == 9


def test_a_rank_outside_the_world_is_refused(store):
    from sonarset.errors import SonarSetError

    with pytest.raises(SonarSetError, match="rank 1 is not one of a world of 1"):
        _dataset(store, rank=1)
    assert _dataset(store, rank=1, world_size=2).shard_batches(0) == [math.ceil(
        (len(RunLayout.of(store, split="train").index(3, 2)) - len(RunLayout.of(store, split="train").index(3, 2)) // 2)
        / 16)]


def test_train_and_eval_stream_on_the_command_line(store, tmp_path):
    from typer.testing import CliRunner

    from sonarset.cli.app import app

    r = CliRunner().invoke(app, ["train", store.location, "--preset", "tiny", "--out", str(tmp_path / "m"),
                                 "--max-steps", "4", "--batch-size", "8", "--n-val", "16", "--stream",
                                 "--shuffle-buffer", "32", "--workers", "2", "--test-samples", "0", "--device", "cpu"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["eval", store.location, "--models", f"flow,echopt:{tmp_path / 'm'}", "--samples", "30",
                                 "--stream", "--no-figures", "--out", str(tmp_path / "e")])
    assert r.exit_code == 0, r.output
    assert "30 windows" in r.output
    r = CliRunner().invoke(app, ["train", store.location, "--preset", "tiny", "--out", str(tmp_path / "n"),
                                 "--stream", "--batch-size", "100000", "--n-val", "16", "--test-samples", "0"])
    assert r.exit_code == 1 and "fewer than one batch" in r.output


DDP_SCRIPT = """
import json, sys
import torch.distributed as dist
from sonarset.torchdata import StreamingLoader, StreamingWindowDataset

if __name__ == "__main__":  # spawned DataLoader workers import this file again
    dist.init_process_group("gloo")
    ds = StreamingWindowDataset.from_store(sys.argv[1], "train", n_in=3, horizon=2, batch_size=8, seed=5,
                                           shuffle_buffer=40, slab_frames=64)
    starts = [int(s) for b in StreamingLoader(ds, num_workers=int(sys.argv[3])) for s in b["starts"]]
    json.dump(starts, open(f"{sys.argv[2]}/rank{dist.get_rank()}.json", "w"))
    dist.destroy_process_group()
"""


@pytest.mark.parametrize("workers", [0, 2])
def test_ddp_ranks_stream_disjoint_windows_each_once(store, tmp_path, workers):
    script = tmp_path / "ddp.py"
    script.write_text(DDP_SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    p = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                        str(script), store.location, str(tmp_path), str(workers)],
                       capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    r0, r1 = (json.loads((tmp_path / f"rank{r}.json").read_text()) for r in (0, 1))
    every = RunLayout.of(store, split="train").index(3, 2).starts
    assert not set(r0) & set(r1) and abs(len(r0) - len(r1)) <= 2
    assert sorted(r0 + r1) == every.tolist()


def test_window_bank_reads_a_few_chunks_at_a_time_and_holds_them_packed(store, monkeypatch):
    import sonarset.stream as stream
    from sonarset.store.run import Run

    layout = RunLayout.of(store, split="train")
    index = layout.index(3, 4).sample(60, seed=2)
    reads, read = [], Run.read

    def spy(self, key, start=0, stop=None, out=None):
        if key == "images":
            reads.append(stop - start)
        return read(self, key, start, stop, out)
    monkeypatch.setattr(stream, "READ_FRAMES", 64)
    monkeypatch.setattr(Run, "read", spy)
    packed = window_bank(store, layout, index, np.float32)
    chunk = store.run(layout.run_names[0]).array("images").chunks[0]
    assert reads and max(reads) <= max(64, chunk)  # not one read per stretch of close windows
    dense = window_bank(store, layout, index, np.float32, packed=False)
    assert packed.images.nbytes < dense.images.nbytes / 2  # mostly black frames compress
    a, b = WindowBatcher.of(packed).gather(index), WindowBatcher.of(dense).gather(index)
    assert a.frames.dtype == np.float32
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.targets, b.targets)


def test_streamed_validation_and_test_read_only_their_windows_with_the_in_memory_numbers(store, tmp_path,
                                                                                         monkeypatch):
    from sonarset.models.echopt.cards import add_test_metrics
    from sonarset.models.echopt.checkpoint import load_checkpoint
    from sonarset.models.echopt.distributed import Dist
    from sonarset.models.echopt.losses import validation_loss
    from sonarset.models.echopt.train import train
    from sonarset.models.echopt.train_config import TrainConfig
    from sonarset.models.echopt.train_data import MemoryWindows, StreamedWindows

    cfg = TrainConfig(preset="tiny", batch_size=16, n_val=40, eval_every=2, max_steps=2, device="cpu",
                      precision="fp32", curriculum="2", command="test", stream=True, shuffle_buffer=40,
                      test_samples=20)

    def whole_split(*args, **kwargs):
        raise AssertionError("a streamed run read every frame of a split")
    with monkeypatch.context() as m:
        m.setattr(FrameBank, "from_store", classmethod(whole_split))
        res = train(store, tmp_path / "m", cfg)
        streamed_test = add_test_metrics(tmp_path / "m", store, cfg)
    # the one validation (step 2) kept its weights: the in-memory windows give that model the same loss
    model, _ = load_checkpoint(tmp_path / "m", GRID)
    loaded = MemoryWindows.make(store, cfg, model.cfg.n_in, 2, Dist(), "cpu")
    streamed = StreamedWindows.make(store, cfg, model.cfg.n_in, 2, Dist(), "cpu")
    assert np.array_equal(loaded.val_idx.starts, streamed.val_idx.starts)
    # held compressed: under half the bytes of their frames as stored (float16)
    frames = np.unique(streamed.val_idx.rows()).size
    assert streamed.val_batcher.images.nbytes < frames * GRID.n_range * GRID.n_azimuth * 2 / 2
    losses = [validation_loss(model, w.val_batcher, w.val_idx, 2, batch_size=2 * cfg.batch_size, precision="fp32",
                              terms={"mse": 1.0})
              for w in (loaded, streamed)]
    assert losses[0] == losses[1] == res.history[-1]["val_loss"]
    cfg.stream = False
    assert add_test_metrics(tmp_path / "m", store, cfg)["results"] == streamed_test["results"]
