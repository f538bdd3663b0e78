"""The corruption suite (issue 14): every way a store can break, against every command that reads it.

Each kind damages a copy of one small generated store. For each kind, ``validate``, ``info``,
``eval``, ``train`` and ``show`` must end either with correct output (exit 0) or with clear
one-line errors and a non-zero exit: never a traceback, never an "internal error", never a
number computed from bad data. The expected outcome of every (kind, command) pair is written
down, so a command that starts accepting a broken store fails here as surely as one that crashes.

    python -m pytest -q tests/test_corruption.py -s     # also prints the kinds x commands table
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import zarr
from typer.testing import CliRunner

from sonarset.cli.app import app
from sonarset.schema import SensorGrid

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)
RUNS = ("run_000", "test_000")  # one per split: train reads the first, eval and show the second
FRAME = 70  # in the second image chunk (c/1/0/0, frames 64..127): show draws this frame
COMMANDS = ("validate", "info", "eval", "train", "show")
OK = "ok"

runner = CliRunner()


# ---- corruptions ---------------------------------------------------------------------------------

def _json(store: Path, rel: str, change: Callable[[dict], object]) -> None:
    path = store / rel
    doc = json.loads(path.read_text())
    new = change(doc)
    path.write_text(new if isinstance(new, str) else json.dumps(doc if new is None else new))


def _meta(rel: str, **fields) -> Callable[[Path], None]:
    return lambda s: _json(s, rel, lambda d: d.update(fields))


def _each_run(fn: Callable[[Path, str], None]) -> Callable[[Path], None]:
    def apply(store: Path) -> None:
        for run in RUNS:
            fn(store, run)
    return apply


def _values(key: str, change: Callable[[np.ndarray], None]) -> Callable[[Path], None]:
    """Rewrite array ``key`` of every run through zarr: well-formed chunks holding bad values."""
    def apply(store: Path, run: str) -> None:
        arr = zarr.open_array(store / run / key, mode="r+")
        values = arr[:]
        change(values)
        arr[:] = values
    return _each_run(apply)


def _chunk(key: str, chunk: str, change: Callable[[bytes], bytes | None]) -> Callable[[Path], None]:
    """Damage one stored chunk file of every run (None: delete it)."""
    def apply(store: Path, run: str) -> None:
        path = store / run / key / chunk
        new = change(path.read_bytes())
        path.unlink()
        if new is not None:
            path.write_bytes(new)
    return _each_run(apply)


def _set(index, value):
    def change(a: np.ndarray) -> None:
        a[index] = value
    return change


def _swap_times(t: np.ndarray) -> None:
    t[FRAME], t[FRAME + 1] = t[FRAME + 1], t[FRAME]


def _scale(factor: float):
    def change(a: np.ndarray) -> None:
        a *= factor
    return change


def _garbage(b: bytes) -> bytes:
    return np.random.default_rng(1).integers(0, 256, len(b), dtype=np.uint8).tobytes()


def _scrambled_payload(b: bytes) -> bytes:
    # the 16-byte blosc header stays intact, so only the decoder (or the values) can tell
    return b[:16] + _garbage(b[16:])


def _all_image_chunks_deleted(store: Path) -> None:
    for run in RUNS:
        shutil.rmtree(store / run / "images" / "c")


def _chunk_is_directory(store: Path) -> None:
    for run in RUNS:
        path = store / run / "images" / "c" / "1" / "0" / "0"
        path.unlink()
        path.mkdir()


def _consolidated_lacks_run(store: Path) -> None:
    def change(doc: dict) -> None:
        meta = doc["consolidated_metadata"]["metadata"]
        for key in [k for k in meta if k == "test_000" or k.startswith("test_000/")]:
            del meta[key]
    _json(store, "zarr.json", change)


def _run_attrs(**fields):
    return lambda s: _json(s, "test_000/zarr.json", lambda d: d["attributes"]["sonarset"].update(fields))


def _root_attrs(change: Callable[[dict], None]):
    def apply(store: Path) -> None:
        def edit(doc: dict) -> None:
            change(doc["attributes"]["sonarset"])
        _json(store, "zarr.json", edit)
    return apply


def _drop(key: str):
    def change(d: dict) -> None:
        del d[key]
    return change


def _extra_array(store: Path) -> None:
    g = zarr.open_group(store / "test_000", mode="r+", use_consolidated=False)
    g.create_array("notes", shape=(3,), dtype="float32", fill_value=0.0)[:] = [1, 2, 3]
    zarr.consolidate_metadata(str(store))  # a writer that adds arrays re-consolidates


def _junk_directory(store: Path) -> None:
    (store / "not_a_node" / "x").mkdir(parents=True)
    (store / "not_a_node" / "x" / "readme.txt").write_text("not zarr")


@dataclass
class Kind:
    name: str
    apply: Callable[[Path], None]
    #: what every refusing command's error must contain (the run, array and chunk where known)
    where: str
    #: the commands that must succeed (all others must refuse)
    ok: tuple[str, ...] = ()
    #: command -> text its output must contain (success) or its error must contain (refusal),
    #: where it differs from ``where``
    says: dict[str, str] = field(default_factory=dict)


IMG1 = "images: chunk c/1/0/0"
KINDS = [
    Kind("image chunk deleted", _chunk("images", "c/1/0/0", lambda b: None), f"{IMG1} is missing",
         says={"validate": "images: 1 chunk(s) missing from storage (deleted?), first: c/1/0/0"}),
    Kind("every image chunk deleted", _all_image_chunks_deleted, "images: chunk c/0/0/0 is missing",
         says={"validate": "images: 3 chunk(s) missing"}),
    Kind("image chunk truncated", _chunk("images", "c/1/0/0", lambda b: b[:len(b) // 2]),
         f"{IMG1} is corrupt or truncated: its blosc header declares"),
    Kind("image chunk empty", _chunk("images", "c/1/0/0", lambda b: b""), f"{IMG1} is corrupt or truncated: 0 bytes"),
    Kind("image chunk garbage", _chunk("images", "c/1/0/0", _garbage), f"{IMG1} is corrupt"),
    Kind("image chunk payload scrambled", _chunk("images", "c/1/0/0", _scrambled_payload), "images", ok=("info",),
         says={"validate": "chunk c/1/0/0 is corrupt or truncated", "eval": "c/1/0/0", "train": "c/1/0/0",
               "show": "c/1/0/0"}),
    Kind("image chunk is a directory", _chunk_is_directory, f"{IMG1} is a directory"),
    Kind("velocity chunk truncated in place (stored uncompressed)",
         _chunk("velocity", "c/0/0", lambda b: b[:len(b) // 2]),
         "velocity: chunk c/0/0 is corrupt or truncated: its blosc header declares"),
    Kind("velocity chunk deleted", _chunk("velocity", "c/0/0", lambda b: None), "velocity: chunk c/0/0 is missing",
         says={"validate": "velocity: 1 chunk(s) missing"}),
    Kind("time chunk truncated", _chunk("time", "c/0", lambda b: b[:-40]), "time: chunk c/0 is corrupt or truncated"),
    Kind("time chunk deleted", _chunk("time", "c/0", lambda b: None), "time: chunk c/0 is missing",
         says={"validate": "time: 1 chunk(s) missing"}),
    Kind("range chunk truncated (no compressor)", _chunk("range", "c/0", lambda b: b[:200]),
         "range: chunk c/0 is corrupt or truncated: 200 bytes"),
    Kind("pose chunk garbage", _chunk("pose", "c/0/0", _garbage), "pose: chunk c/0/0 is corrupt"),
    Kind("NaN image", _values("images", _set(FRAME, np.nan)), f"images: NaN or infinite values (first at frame {FRAME})",
         ok=("info",)),
    Kind("infinite image", _values("images", _set((FRAME, 3, 3), np.inf)), "images: NaN or infinite values", ok=("info",)),
    Kind("image above 1", _values("images", _set((FRAME, 3, 3), 1.5)), "images: values outside [0, 1]", ok=("info",)),
    Kind("negative image", _values("images", _set((FRAME, 3, 3), -0.25)), "images: values outside [0, 1]", ok=("info",)),
    Kind("NaN velocity", _values("velocity", _set((FRAME, 0), np.nan)), "velocity: NaN or infinite values",
         ok=("info",)),
    Kind("infinite velocity", _values("velocity", _set((FRAME, 1), -np.inf)), "velocity: NaN or infinite values",
         ok=("info",)),
    Kind("velocity of 1e30 (finite, impossible)", _values("velocity", _set((FRAME, 0), 1e30)),
         "velocity: linear speed up to 1e+30 m/s exceeds", ok=("info",)),
    Kind("NaN time", _values("time", _set(FRAME, np.nan)), "time: NaN or infinite values (first at frame 70)"),
    Kind("time not increasing", _values("time", _swap_times), "time", says={
        "validate": "time is not strictly increasing (first at frame 71)"}),
    Kind("10 Hz time stamps in a 5 Hz store", _values("time", _scale(0.5)), "time stamps are 0.1 s apart (median)"),
    Kind("time in milliseconds declared as seconds", _values("time", _scale(1000.0)), "milliseconds declared as seconds"),
    Kind("NaN pose (optional array)", _values("pose", _set((FRAME, 0), np.nan)), "pose: NaN or infinite values",
         ok=("info", "eval", "train")),
    Kind("all images zero (constant)", _values("images", _set(slice(None), 0.0)), "", ok=COMMANDS,
         says={"eval": "CC is undefined where the target frame or the prediction is constant: 20 of 20 windows"}),
    Kind("all images 0.5 (constant)", _values("images", _set(slice(None), 0.5)), "", ok=COMMANDS,
         says={"eval": "CC is undefined where the target frame or the prediction is constant: 20 of 20 windows"}),
    Kind("run zarr.json not JSON", lambda s: (s / "test_000" / "zarr.json").write_text("{not json"),
         "test_000: unreadable zarr metadata"),
    Kind("run zarr.json is `true`", lambda s: (s / "test_000" / "zarr.json").write_text("true"),
         "test_000: unreadable zarr metadata"),
    Kind("run zarr.json without node_type", lambda s: _json(s, "test_000/zarr.json", _drop("node_type")),
         "test_000: unreadable zarr metadata"),
    Kind("images data_type float17", _meta("test_000/images/zarr.json", data_type="float17"),
         "test_000/images: unreadable zarr metadata"),
    Kind("images negative shape", _meta("test_000/images/zarr.json", shape=[-150, 50, 30]),
         "test_000/images: unreadable zarr metadata"),
    Kind("images 2-D", _meta("test_000/images/zarr.json", shape=[150, 50], dimension_names=["time", "range"],
                             chunk_grid={"name": "regular", "configuration": {"chunk_shape": [64, 50]}}),
         "test_000/images: dimension_names ['time', 'range'] must be"),
    Kind("images dtype int16", _meta("test_000/images/zarr.json", data_type="int16", fill_value=0),
         "test_000/images: dtype int16 not allowed"),
    Kind("velocity int16 with NaN fill", _meta("test_000/velocity/zarr.json", data_type="int16"),
         "test_000/velocity: unreadable zarr metadata"),
    Kind("velocity of 100 rows in 150 frames", _meta("test_000/velocity/zarr.json", shape=[100, 2]),
         "test_000/velocity: shape (100, 2) does not match (150, 2)"),
    Kind("velocity of 200 rows in 150 frames", _meta("test_000/velocity/zarr.json", shape=[200, 2]),
         "test_000/velocity: shape (200, 2) does not match (150, 2)"),
    Kind("images without dimension_names", _meta("test_000/images/zarr.json", dimension_names=None),
         "test_000/images: dimension_names None must be"),
    Kind("images array deleted", lambda s: shutil.rmtree(s / "test_000" / "images"), "test_000: ",
         says={"validate": "missing required array 'images'"}),
    Kind("run flagged complete with 200 frames of 150", _run_attrs(n_frames=200),
         "test_000/images: shape (150, 50, 30) does not match (200, 50, 30)"),
    Kind("run attributes missing", lambda s: _json(s, "test_000/zarr.json", lambda d: d.update(attributes={})),
         "test_000: ", says={"validate": "missing run attribute 'sonarset'"}),
    Kind("run split upper-case", _run_attrs(split="TEST"), "split must be lower-case"),
    Kind("run incomplete", _run_attrs(complete=False), "test_000", ok=("info", "train"),
         says={"validate": "incomplete run", "eval": "no complete runs in split 'test'", "show": "run is incomplete"}),
    Kind("range coordinates off the grid", _values("range", _scale(1.1)), "range: coordinates do not match the store grid"),
    Kind("root zarr.json not JSON", lambda s: (s / "zarr.json").write_text("{"), "zarr.json",
         says={"validate": "unreadable JSON"}),
    Kind("root grid attribute missing", _root_attrs(_drop("grid")), "grid: Field required"),
    Kind("rig frame interval disagrees with the frame rate",
         _root_attrs(lambda a: a["rig"].update(frame_interval_s=0.1)),
         "frame_interval_s 0.1 s disagrees with frame_rate_hz 5"),
    Kind("consolidated metadata lacks a run", _consolidated_lacks_run, "consolidated metadata is stale",
         ok=("info", "eval", "train", "show")),
    Kind("unknown extra array in a run", _extra_array, "", ok=COMMANDS),
    Kind("junk directory in the root", _junk_directory, "", ok=COMMANDS),
]


# ---- running the commands ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def base_store(tmp_path_factory) -> Path:
    from sonarset.sim import generate

    path = tmp_path_factory.mktemp("corruption") / "base.zarr"
    generate(path, runs=1, test_runs=1, minutes=0.5, seed=3, workers=1, grid=GRID)
    return path


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


def test_remote_store_checks_each_chunk_as_it_is_read(base_store, tmp_path):
    """Over a URL the open check cannot fetch every chunk; the read that needs one checks it."""
    from sonarset.errors import FormatError
    from sonarset.store import open_store
    from sonarset.testing import serve_directory
    from sonarset.validate import validate_store
    from sonarset.windows import FrameBank

    shutil.copytree(base_store, tmp_path / "s.zarr")
    chunk = tmp_path / "s.zarr" / "test_000" / "velocity" / "c" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:600])  # stored uncompressed: zarr would decode garbage
    with serve_directory(str(tmp_path)) as (url, _):
        store = open_store(f"{url}/s.zarr", check=True)
        assert len(FrameBank.from_store(store, split="train").run_names) == 1  # the intact run loads
        with pytest.raises(FormatError, match=r"s.zarr/test_000/velocity: chunk c/0/0 is corrupt or truncated: "
                                              r"its blosc header declares 1216 bytes, the chunk has 600"):
            FrameBank.from_store(store, split="test")
        problems = [str(p) for p in validate_store(f"{url}/s.zarr")]
    assert any("test_000/velocity: chunk c/0/0 is corrupt or truncated" in p for p in problems), problems


def test_eval_takes_dt_from_the_time_stamps(tmp_path, monkeypatch):
    """The baselines step by the median spacing of the time stamps, not by the declared rate."""
    from sonarset.models import registry
    from sonarset.models.evaluate import evaluate
    from sonarset.store import create_store
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
    from sonarset.models.eval_report import results_table
    from sonarset.models.evaluate import evaluate
    from sonarset.store import create_store
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


if __name__ == "__main__":  # pragma: no cover - python tests/test_corruption.py prints the table
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        from sonarset.sim import generate

        base = Path(tmp) / "base.zarr"
        generate(base, runs=1, test_runs=1, minutes=0.5, seed=3, workers=1, grid=GRID)
        res = {}
        for i, kind in enumerate(KINDS):
            work = Path(tmp) / f"k{i}"
            got = check_kind(kind, base, work)
            res[kind.name] = {c: s if p is None else f"BAD: {p}" for c, (s, p) in got.items()}
        print(table(res))
        os._exit(0 if all(not v.startswith("BAD") for row in res.values() for v in row.values()) else 1)
