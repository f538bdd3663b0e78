"""EchoPT's precision setting: detection of bf16 units, what ``auto`` picks, and what bf16 changes."""

import numpy as np
import pytest

from sonarset import SonarSetError, open_store
from sonarset.models.echopt import precision as prec
from sonarset.models.eval.evaluate import evaluate
from sonarset.models.registry import make_predictor
from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.sim import generate

X86_CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
flags\t\t: fpu vme avx2 avx512f avx512bw avx512_bf16 avx512_vnni
"""
ARM_CPUINFO = """processor\t: 0
Features\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics fphp asimdhp bf16 i8mm
"""
OLD_X86_CPUINFO = "flags\t\t: fpu vme sse sse2 avx avx2 fma\n"


def test_bf16_units_are_read_from_the_processors_flags():
    assert prec.bf16_flags_in(X86_CPUINFO) == ("avx512_bf16",)
    assert prec.bf16_flags_in(ARM_CPUINFO) == ("bf16",)
    assert prec.bf16_flags_in(OLD_X86_CPUINFO) == ()
    assert prec.bf16_flags_in("flags : amx_bf16 amx_tile avx512_bf16\n") == ("amx_bf16", "avx512_bf16")
    assert isinstance(prec.cpu_bf16_flags(), tuple)  # this machine's, whatever they are


def test_auto_picks_bf16_only_where_the_cpu_has_bf16_units(monkeypatch):
    monkeypatch.setattr(prec, "cpu_bf16_flags", lambda: ())
    assert prec.resolve_precision("auto", "cpu") == "fp32"
    assert "no bf16 units" in prec.describe_precision("auto", "cpu")
    monkeypatch.setattr(prec, "cpu_bf16_flags", lambda: ("avx512_bf16",))
    assert prec.resolve_precision("auto", "cpu") == "bf16"
    assert prec.describe_precision("auto", "cpu") == "bf16 (CPU flags avx512_bf16)"
    for explicit in ("fp32", "bf16"):  # an explicit choice is kept, units or not
        assert prec.resolve_precision(explicit, "cpu") == explicit
    with pytest.raises(SonarSetError, match="precision must be one of auto, fp32, bf16"):
        prec.resolve_precision("fp16", "cpu")


@pytest.fixture(scope="module")
def default_grid_run(tmp_path_factory):
    """A one-minute test run on the default grid: the shipped model's own kind of data."""
    path = tmp_path_factory.mktemp("precision") / "fresh.zarr"
    generate(path, runs=0, test_runs=1, minutes=1.0, seed=11, workers=1, grid=SensorGrid.default())
    return open_store(path)


def test_without_bf16_units_auto_runs_the_model_in_fp32(default_grid_run, monkeypatch):
    monkeypatch.setattr(prec, "cpu_bf16_flags", lambda: ())
    p = make_predictor("echopt:pretrained", default_grid_run.grid, RobotRig())
    assert p.precision == "fp32"
    res = evaluate(default_grid_run, ["flow", "echopt:pretrained"], horizons=(1, 3), samples=12)
    assert res.precision == {"echopt": "fp32"}
    assert np.isfinite(res.per_window["echopt"][3]["cc"]).all()


def test_bf16_keeps_the_shipped_models_scores_within_0_002(default_grid_run):
    """The shipped model in bf16 autocast against fp32 on the same windows of a fresh run: no mean
    CC or NRMSD moves by more than 0.002 at any horizon (BENCHMARKS.md: 1000 windows, AR-10)."""
    scores = {}
    for precision in ("fp32", "bf16"):
        res = evaluate(default_grid_run, ["echopt:pretrained"], horizons=(1, 3, 5), samples=40, precision=precision)
        assert res.precision == {"echopt": precision}
        scores[precision] = res.summary()["echopt"]
    for h, entry in scores["fp32"].items():
        for metric in ("cc", "nrmsd"):
            assert abs(entry[metric]["mean"] - scores["bf16"][h][metric]["mean"]) <= 0.002, (h, metric)


def test_the_predictor_gives_the_same_frames_in_one_batch_or_many(default_grid_run):
    """Batches are split into single-threaded chunks per core: the split must not change a frame."""
    from sonarset.windows import FrameBank, WindowBatcher, WindowIndex

    bank = FrameBank.from_store(default_grid_run, split="test", image_dtype=np.float32)
    index = WindowIndex.build(bank, 3, 1)
    batch = WindowBatcher.of(bank).gather(index, np.arange(20))
    p = make_predictor("echopt:pretrained", default_grid_run.grid, RobotRig(), precision="fp32")
    whole = p.predict(batch.frames, batch.commands[:, :4])
    p.predictor.batch_size = 3  # seven chunks over the worker threads (p: the registry's checked view)
    chunked = p.predict(batch.frames, batch.commands[:, :4])
    np.testing.assert_allclose(chunked, whole, atol=1e-5)
    assert whole.dtype == np.float32 and whole.min() >= 0 and whole.max() <= 1
