"""The JSON metadata of a recording: the sidecar beside it, read strictly and within bounds, and
validated into its model (``RecordingMeta``, ``RawRecordingMeta``); for a raw recording, what the
sidecar declares: the microphone layout, the emitted sweep and the output grid.

A sidecar is ``SRC.json`` beside a ``.npz``, or ``recording.json`` in a directory of ``.npy``
files. It is parsed as strict JSON (no NaN, no Infinity), at most a few levels deep and a few
megabytes long, since what reads it later (pydantic, the JSON encoder writing ``zarr.json``, every
reader) recurses and reads it whole.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from sonarset.store.local import json_depth
from sonarset.format import plausibility as plaus
from sonarset.format.attrs import SensorGrid
from sonarset.format.problems import pydantic_problems
from sonarset.format.sidecars import RawRecordingMeta, RecordingMeta
from sonarset.format.units import grid_to_si
from sonarset.ingest.files import RawSource, regular_file_problem, short_reason
from sonarset.sensor.ertis import read_layout_csv, sweep

SIDECAR_NAME = "recording.json"
MAX_LAYOUT_M = 1.0  # microphones farther from the emitter than this: probably not metres
#: A metadata file is a few kilobytes; anything this large is not one (and would be read whole).
MAX_METADATA_BYTES = 16 * 2**20
#: Metadata nests a few levels (units, grid, rig, source); deeper documents are refused before
#: they reach code that recurses (pydantic, the JSON encoder writing zarr.json, every reader).
MAX_METADATA_DEPTH = 32


def sidecar_for(src: Path) -> Path:
    """Where the sidecar of the recording ``src`` is unless given: ``SRC.json`` or ``SRC/recording.json``."""
    return src / SIDECAR_NAME if src.is_dir() else src.with_suffix(".json")


def parse_metadata(text: str) -> dict:
    """A metadata JSON object: strict JSON (no NaN, no Infinity), at most MAX_METADATA_DEPTH deep and
    MAX_METADATA_BYTES long, wherever it comes from (a sidecar, or the ``metadata`` array of an .npz)."""
    if len(text) > MAX_METADATA_BYTES:  # characters: at least as many bytes
        raise ValueError(f"{len(text) / 2**20:.0f} MiB is more than metadata holds ({MAX_METADATA_BYTES // 2**20} MiB)")

    def constant(name: str):
        raise ValueError(f"{name} is not valid JSON")

    def number(token: str) -> float:
        value = float(token)
        if not math.isfinite(value):
            raise ValueError(f"number {token[:20]} is out of range")
        return value

    try:
        doc = json.loads(text, parse_constant=constant, parse_float=number)
    except RecursionError:
        raise ValueError(f"nested too deeply (at most {MAX_METADATA_DEPTH} levels)") from None
    if not isinstance(doc, dict):
        raise ValueError("top level must be a JSON object")
    if json_depth(doc) > MAX_METADATA_DEPTH:
        raise ValueError(f"nested too deeply (at most {MAX_METADATA_DEPTH} levels)")
    return doc


def read_sidecar(path: Path, problems: list[str]) -> dict | None:
    """The metadata object in the file ``path``; None, with a line added to ``problems``, when it
    is no regular file, too large, or not a strict JSON object."""
    irregular = regular_file_problem(path)
    if irregular:
        problems.append(f"{path.name}: {irregular}")
        return None
    try:
        if path.stat().st_size > MAX_METADATA_BYTES:
            raise ValueError(f"{path.stat().st_size} bytes, more than a metadata file holds "
                             f"({MAX_METADATA_BYTES // 2**20} MiB)")
        return parse_metadata(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        problems.append(f"{path.name}: invalid JSON ({short_reason(exc)})")
        return None


def recording_meta(src: Path, meta_path: str | os.PathLike | None, embedded: dict | None,
                   problems: list[str], implausible: list[str]) -> RecordingMeta | None:
    """The recording's metadata: the sidecar completing and overriding the file's own; None when
    it is invalid (``problems`` says why)."""
    meta_doc: dict | None = None
    sidecar = Path(meta_path) if meta_path is not None else sidecar_for(src)
    if sidecar.exists() or sidecar.is_symlink():
        meta_doc = read_sidecar(sidecar, problems)
    elif meta_path is not None:
        problems.append(f"{sidecar}: metadata file not found")
    if meta_doc is not None and embedded:
        # A key both set differently is reported, naming both, rather than silently decided.
        implausible += map(str, plaus.metadata_conflicts(meta_doc, embedded, sidecar.name, src.name))
        meta_doc = plaus.merge_metadata(embedded, meta_doc)
    if meta_doc is None:
        meta_doc = embedded or {}
    try:
        return RecordingMeta.model_validate(meta_doc)
    except ValidationError as exc:
        problems += map(str, pydantic_problems(exc, "metadata."))
    except RecursionError:
        problems.append(f"metadata: nested too deeply (at most {MAX_METADATA_DEPTH} levels)")
    return None


def raw_meta(sidecar: Path, problems: list[str]) -> RawRecordingMeta | None:
    """The sidecar's settings (sample rate, sweep, microphones...); None when missing or invalid."""
    if not sidecar.is_file():
        problems.append(f"{sidecar.name}: metadata file not found (the sidecar with sample rate, sweep, microphones)")
        return None
    doc = read_sidecar(sidecar, problems)
    if doc is None:
        return None
    try:
        return RawRecordingMeta.model_validate(doc)
    except ValidationError as exc:
        problems += map(str, pydantic_problems(exc, f"{sidecar.name}: "))
        return None


def microphone_layout(meta: RawRecordingMeta, sidecar: Path, problems: list[str]) -> np.ndarray | None:
    """The microphone positions (M, 3), metres, the sidecar declares: 'ertis32', a layout CSV beside it,
    or a list; None, with a line in ``problems``, when they cannot be beamformed."""
    spec = meta.microphones
    if isinstance(spec, str):
        if spec == "ertis32":
            return read_layout_csv()
        path = (sidecar.parent / spec) if not Path(spec).is_absolute() else Path(spec)
        try:
            pos = read_layout_csv(path)
        except FileNotFoundError:
            problems.append(f"{path.name}: microphone layout file not found")
            return None
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            problems.append(f"{path.name}: not a microphone layout CSV ({short_reason(exc)})")
            return None
        where = path.name
    else:
        where = "metadata.microphones"
        rows = spec
        if any(len(r) not in (2, 3) for r in rows):
            problems.append(f"{where}: each position must be [x, y] or [x, y, z] in metres")
            return None
        pos = np.array([list(r) + [0.0] * (3 - len(r)) for r in rows], float)
    if len(pos) < 3:
        problems.append(f"{where}: {len(pos)} microphone(s); beamforming needs at least 3")
        return None
    if not np.all(np.isfinite(pos)):
        problems.append(f"{where}: positions contain NaN or infinite values")
        return None
    far = float(np.abs(pos).max())
    if far > MAX_LAYOUT_M:
        problems.append(f"{where}: microphones up to {far:g} from the emitter; positions must be metres "
                        "(millimetres?)")
        return None
    if len(np.unique(np.round(pos[:, :2], 9), axis=0)) < len(pos):
        problems.append(f"{where}: two microphones share a horizontal position")
        return None
    return pos


def emitted_sweep(meta: RawRecordingMeta, reader: RawSource, problems: list[str]) -> np.ndarray | None:
    """The emitted sweep at the recording's rate: the sidecar's (parameters or samples) or the input's
    ``sweep`` array, exactly one of them; None, with a line in ``problems``, when unusable."""
    fs = meta.sample_rate_hz
    has_array = "sweep" in reader.members
    if has_array and meta.sweep is not None:
        problems.append("the sweep is given twice (sidecar 'sweep' and a 'sweep' array): keep one")
        return None
    if not has_array and meta.sweep is None:
        problems.append("no emitted sweep: give sidecar 'sweep' (parameters or samples) or a 'sweep' array")
        return None
    if has_array:
        m = reader.members["sweep"]
        if len(m.shape) != 1 or m.dtype.kind not in "fiu":
            problems.append(f"sweep: expected a 1-D real array, got shape {m.shape} of {m.dtype}")
            return None
        s = reader.read("sweep").astype(float)
        where = "sweep"
    elif meta.sweep.samples is not None:
        s, where = np.array(meta.sweep.samples, float), "metadata.sweep.samples"
    else:
        sw = meta.sweep
        top = max(sw.f_start_hz, sw.f_end_hz)
        if top >= 0.45 * fs:
            problems.append(f"metadata.sample_rate_hz: {fs:g} Hz cannot carry the sweep's {top:g} Hz "
                            f"(needs more than {top / 0.45:.0f} Hz)")
            return None
        s, where = sweep(fs, sw.f_start_hz, sw.f_end_hz, sw.duration_s, sw.window), "metadata.sweep"
    if len(s) < 8:
        problems.append(f"{where}: {len(s)} samples at {fs:g} Hz is too short for a sweep")
        return None
    if not np.all(np.isfinite(s)) or not np.any(s):
        problems.append(f"{where}: samples must be finite and not all zero")
        return None
    return s


def raw_grid(meta: RawRecordingMeta, grid: SensorGrid | None, problems: list[str]) -> SensorGrid | None:
    """The output grid: ``grid`` (an existing store's), which the sidecar's must match, else the
    sidecar's, else the default; None, with a line in ``problems``, when they disagree."""
    declared = None
    if meta.grid is not None:
        try:
            declared = grid_to_si(meta.grid, meta.units)
        except ValidationError as exc:
            problems += map(str, pydantic_problems(exc, "metadata.grid."))
            return None
    if grid is not None and declared is not None and not grid.matches(declared, rtol=1e-4):
        problems.append(f"metadata.grid {declared.describe()} differs from the store's {grid.describe()}")
        return None
    return grid or declared or SensorGrid.default()
