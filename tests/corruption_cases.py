"""The corruption table of tests/test_corruption.py: the base store, the ways to damage it and what
each command must then do.

``KINDS`` lists every kind of damage (a :class:`Kind`: its name, the function that damages a copy of
the base store, and the expected outcome of each command); the helpers above it build those
functions. The tests that run them are in tests/test_corruption.py.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import zarr

from sonarset.format.arrays import FRAME_ARRAYS
from sonarset.format.attrs import SensorGrid

GRID = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                  azimuth_max_rad=math.pi / 2, n_azimuth=30)
RUNS = ("run_000", "test_000")  # one per split: train reads the first, eval and show the second
FRAME = 70  # in the second image chunk (c/1/0/0, frames 64..127): show draws this frame
COMMANDS = ("validate", "info", "eval", "train", "show")


def make_base_store(path: Path) -> Path:
    """The store every kind damages a copy of: one train and one test run of 150 frames on ``GRID``."""
    from sonarset.sim import generate

    generate(path, runs=1, test_runs=1, minutes=0.5, seed=3, workers=1, grid=GRID)
    return path




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


def _bit_flipped(b: bytes) -> bytes:
    # one bit of the payload: the chunk still decodes, so only its checksum (format 1.2) can tell
    data = bytearray(b)
    data[len(data) // 2] ^= 0x08
    return bytes(data)


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



def _fifo(rel: str) -> Callable[[Path], None]:
    """``rel`` replaced by a FIFO: a reader that opens it waits for a writer that never comes."""
    def apply(store: Path) -> None:
        (store / rel).unlink()
        os.mkfifo(store / rel)
    return apply


def _links(*pairs: tuple[str, str]) -> Callable[[Path], None]:
    """Symbolic links at ``rel`` pointing to ``target`` (``rel`` replaced where it exists)."""
    def apply(store: Path) -> None:
        for rel, target in pairs:
            (store / rel).unlink(missing_ok=True)
            (store / rel).symlink_to(target)
    return apply


def _nested(rel: str, depth: int) -> Callable[[Path], None]:
    """``rel``'s attributes gain a value nested ``depth`` lists deep."""
    def apply(store: Path) -> None:
        doc = json.loads((store / rel).read_text())
        text = json.dumps(doc)[:-1] + ', "deep": ' + "[" * depth + "]" * depth + "}"
        (store / rel).write_text(text)
    return apply


def _length(n: int) -> Callable[[Path], None]:
    """Run test_000 declares ``n`` frames, consistently: its ``n_frames`` and every time-indexed
    array's shape, over the chunks of the real 150 frames."""
    def apply(store: Path) -> None:
        _json(store, "test_000/zarr.json", lambda d: d["attributes"]["sonarset"].update(n_frames=n))
        for key in FRAME_ARRAYS:
            if (store / "test_000" / key / "zarr.json").exists():
                _json(store, f"test_000/{key}/zarr.json", lambda d: d.update(shape=[n, *d["shape"][1:]]))
    return apply

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
    Kind("image chunk one bit flipped", _chunk("images", "c/1/0/0", _bit_flipped),
         f"{IMG1} is corrupt or truncated: checksum mismatch", ok=("info",)),
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
        "validate": "time: not strictly increasing (first at frame 71)"}),
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
         says={"validate": "run is incomplete", "eval": "no complete runs in split 'test'", "show": "run is incomplete"}),
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
    # what a store directory may hold (store/local.py): folders and regular files, metadata within limits
    Kind("run zarr.json is a FIFO", _fifo("test_000/zarr.json"), "test_000/zarr.json: a FIFO"),
    Kind("array zarr.json is a FIFO", _fifo("test_000/images/zarr.json"), "test_000/images/zarr.json: a FIFO"),
    Kind("image chunk is a FIFO", _fifo("test_000/images/c/1/0/0"), "test_000/images/c/1/0/0: a FIFO"),
    Kind("run zarr.json links to /dev/zero", _links(("test_000/zarr.json", "/dev/zero")),
         "test_000/zarr.json: a symbolic link"),
    Kind("symlink loop inside a run", _links(("test_000/loopa", "loopb"), ("test_000/loopb", "loopa")),
         "test_000/loopa: a symbolic link"),
    Kind("chunk folder links back up", _links(("test_000/images/c/loop", "../../images")),
         "test_000/images/c/loop: a symbolic link"),
    Kind("root zarr.json nested 100,000 deep", _nested("zarr.json", 100_000), "zarr.json: JSON nested too deeply"),
    Kind("run zarr.json nested 200 deep", _nested("test_000/zarr.json", 200),
         "test_000/zarr.json: JSON nested deeper than 64 levels"),
    # a length edited consistently far beyond what is stored: refused from the counts, at once
    Kind("run length edited to a million frames", _length(10**6), "images: at least"),
    Kind("run length edited to 1e12 frames", _length(10**12), "images: at least"),
]
