import numpy as np
import pytest

from sonarset import SonarSetError
from sonarset.windows import FrameBank, WindowBatcher, WindowIndex, gather, iter_batches, load_windows
from tests.conftest import TINY


def coded_bank(sizes=(20, 15, 9)):
    # frame value = 1000 * run + frame index; velocity v = the same code: alignment is visible
    runs = []
    for j, T in enumerate(sizes):
        code = 1000 * j + np.arange(T, dtype=np.float32)
        runs.append((np.broadcast_to(code[:, None, None], (T, *TINY.shape)).copy(), np.c_[code, -code]))
    return FrameBank.from_arrays(runs, TINY)


@pytest.mark.parametrize("H", [1, 3, 5, 10])
def test_window_alignment_and_counts(H):
    bank = coded_bank()
    idx = WindowIndex.build(bank, 3, H)
    assert len(idx) == sum(max(0, T - 3 - H + 1) for T in (20, 15, 9))
    b = gather(bank, idx)
    f, c, t = b.frames[:, :, 0, 0], b.commands[:, :, 0], b.targets[:, :, 0, 0]
    i = f[:, 0]
    np.testing.assert_array_equal(f, i[:, None] + np.arange(3))  # frames i..i+2
    np.testing.assert_array_equal(c, i[:, None] + np.arange(3 + H))  # commands i..i+2+H
    np.testing.assert_array_equal(t, i[:, None] + 3 + np.arange(H))  # targets i+3..i+2+H
    # never across runs: every window's values share one run code
    codes = np.concatenate([f, t], axis=1) // 1000
    assert np.all(codes == codes[:, :1])


def test_locate():
    idx = WindowIndex.build(coded_bank(), 3, 1)
    assert idx.locate(0) == (0, 0) and idx.locate(17) == (1, 0) and idx.locate(len(idx) - 1) == (2, 5)


def test_validation_split_is_seeded_disjoint_and_purged():
    idx = WindowIndex.build(coded_bank((400, 300)), 3, 1)
    tr, va = idx.split(50, seed=3)
    tr2, va2 = idx.split(50, seed=3)
    assert np.array_equal(va.starts, va2.starts) and np.array_equal(tr.starts, tr2.starts)
    assert not np.array_equal(va.starts, idx.split(50, seed=4)[1].starts)
    assert len(va) == 50 and not set(tr.starts) & set(va.starts)
    val_frames = {int(s) + k for s in va.starts for k in range(4)}
    assert all(not ({int(s) + k for k in range(4)} & val_frames) for s in tr.starts)
    tr_np, _ = idx.split(50, seed=3, purge=False)
    assert len(tr_np) == len(idx) - 50 > len(tr)


def test_iter_batches_cover_each_window_once_and_are_seeded():
    bank = coded_bank()
    idx = WindowIndex.build(bank, 3, 2)
    seen = np.concatenate([b.starts for b in iter_batches(bank, idx, 7, seed=1)])
    assert sorted(seen) == sorted(idx.starts)
    again = np.concatenate([b.starts for b in iter_batches(bank, idx, 7, seed=1)])
    assert np.array_equal(seen, again)
    other = np.concatenate([b.starts for b in iter_batches(bank, idx, 7, seed=1, epoch=1)])
    assert not np.array_equal(seen, other)
    assert all(len(b) == 7 for b in iter_batches(bank, idx, 7, drop_last=True))


def test_load_windows_from_store(store):
    bank, idx = load_windows(store, "train", horizon=3)
    assert bank.run_names == ["run_000", "run_001"] and bank.n_frames == 55
    assert len(idx) == (30 - 5) + (25 - 5)
    np.testing.assert_array_equal(bank.images[30:55], store.run("run_001").images[:])
    with pytest.raises(SonarSetError, match="no complete runs in split 'val'"):
        load_windows(store, "val")


def test_torch_dataset_and_loader(store):
    torch = pytest.importorskip("torch")
    from sonarset.torchdata import SonarWindowDataset, make_loader

    bank, idx = load_windows(store, "train", horizon=2)
    ds = SonarWindowDataset(bank, idx)
    one = ds[4]
    assert one["frames"].shape == (3, 8, 6) and one["commands"].shape == (5, 2) and one["targets"].shape == (2, 8, 6)
    ref = gather(bank, idx, np.array([4]))
    assert torch.equal(one["targets"], torch.from_numpy(ref.targets[0]))
    batches = list(make_loader(ds, 8, seed=0))
    assert sum(b["frames"].shape[0] for b in batches) == len(ds)
    assert batches[0]["frames"].dtype == torch.float32
    with pytest.raises(IndexError):
        ds[len(ds)]
    for bad in (1.7, np.float32(2.0), True, [0.5, 1.0], "3"):  # never a quiet round-down or a bool as 1
        with pytest.raises(TypeError, match="integers"):
            ds[bad]
    assert ds[[]]["frames"].shape[0] == 0 and torch.equal(ds[np.int32(4)]["targets"], one["targets"])


def test_batcher_takes_the_first_k_targets_of_longer_windows():
    bank = coded_bank()
    idx = WindowIndex.build(bank, 3, 4)
    b = WindowBatcher.of(bank).gather(idx, np.arange(5), horizon=2)
    i = b.frames[:, 0, 0, 0]
    assert b.frames.shape[1] == 3 and b.commands.shape[1] == 5 and b.targets.shape[1] == 2
    np.testing.assert_array_equal(b.targets[:, :, 0, 0], i[:, None] + 3 + np.arange(2))
    np.testing.assert_array_equal(b.commands[:, :, 0], i[:, None] + np.arange(5))
    with pytest.raises(SonarSetError, match="hold 1 to 4 targets"):
        WindowBatcher.of(bank).gather(idx, np.arange(5), horizon=5)


def test_torch_batcher_gives_the_numpy_batch_as_tensors(store):
    torch = pytest.importorskip("torch")
    from sonarset.torchdata import torch_batcher

    bank = FrameBank.from_store(store, split="train", image_dtype="float16")
    idx = WindowIndex.build(bank, 3, 3)
    which = np.array([7, 0, 21])
    ref = gather(bank, idx, which, image_dtype=np.float32)
    got = torch_batcher(bank).gather(idx, which, horizon=2)
    assert got.frames.dtype == torch.float32 and got.commands.dtype == torch.float32
    np.testing.assert_array_equal(got.frames.numpy(), ref.frames)
    np.testing.assert_array_equal(got.targets.numpy(), ref.targets[:, :2])
    np.testing.assert_array_equal(got.commands.numpy(), ref.commands[:, :5])
    np.testing.assert_array_equal(got.starts, idx.starts[which])


@pytest.mark.parametrize("H", [1, 3])
def test_no_window_spans_a_recorded_gap(H):
    """Frames that follow a recorded gap (lost pings, the run attribute ``gaps``) bound windows as a
    run's edges do: a window starts at the frame after a gap at the earliest, and never holds the
    frames on both sides of one."""
    import dataclasses

    bank = dataclasses.replace(coded_bank(), gaps=np.array([5, 6, 19, 20 + 7, 35 + 4]))
    idx = WindowIndex.build(bank, 3, H)
    span = 3 + H
    expected = [i for lo, hi in ((0, 20), (20, 35), (35, 44)) for i in range(lo, hi - span + 1)
                if not any(i < g < i + span for g in bank.gaps)]
    assert idx.starts.tolist() == expected and 6 in expected and 5 not in expected
    plain = WindowIndex.build(coded_bank(), 3, H)
    assert set(idx.starts) < set(plain.starts)
    # the same windows as for the runs cut at their gaps, the pieces too short for one left out
    b = gather(bank, idx)
    rows = np.concatenate([b.frames[:, :, 0, 0], b.targets[:, :, 0, 0]], axis=1)
    assert np.all(np.diff(rows, axis=1) == 1)


def test_run_gaps_reads_the_attribute_and_refuses_a_malformed_one():
    from types import SimpleNamespace

    from sonarset.format.attrs import RunAttrs
    from sonarset.windows import RUN_GAPS, run_gaps

    def run(gaps):
        extra = {} if gaps is None else {RUN_GAPS: gaps}
        return SimpleNamespace(name="r", n_frames=10, attrs=RunAttrs(complete=True, n_frames=10, **extra))

    assert run_gaps(run(None)).tolist() == [] and run_gaps(run([])).tolist() == []
    assert run_gaps(run([[7, 1], [3, 2]])).tolist() == [3, 7]
    for bad in ([[0, 1]], [[10, 1]], [[3, 0]], [[3.5, 1]], [3], "x", [[3, None]]):
        with pytest.raises(SonarSetError, match="run 'r': attribute 'gaps'"):
            run_gaps(run(bad))


def test_the_frame_rate_check_leaves_out_the_spacings_across_recorded_gaps():
    """A 10 Hz drive that lost every other ping: its median spacing is 0.2 s; with the gaps recorded,
    the spacings of consecutive frames are what the declared rate is checked against."""
    from sonarset.format.arrays import frame_interval_problems, recorded_gap_frames

    steps = np.where(np.arange(40) % 3 == 0, 0.1, 0.2)
    time = np.concatenate([[0.0], np.cumsum(steps)])
    assert frame_interval_problems(time, 10.0)  # unrecorded: looks like a 5 Hz recording
    lost = [[k + 1, 1] for k in np.flatnonzero(steps > 0.15)]
    assert frame_interval_problems(time, 10.0, recorded_gap_frames(lost)) == []
    assert len(recorded_gap_frames("nonsense")) == 0
