"""The JSON metadata of a recording: the sidecar beside it, read strictly and within bounds.

A sidecar is ``SRC.json`` beside a ``.npz``, or ``recording.json`` in a directory of ``.npy``
files. It is parsed as strict JSON (no NaN, no Infinity), at most a few levels deep and a few
megabytes long, since what reads it later (pydantic, the JSON encoder writing ``zarr.json``, every
reader) recurses and reads it whole.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from sonarset.ingest.files import regular_file_problem, short_reason

SIDECAR_NAME = "recording.json"
#: A metadata file is a few kilobytes; anything this large is not one (and would be read whole).
MAX_METADATA_BYTES = 16 * 2**20
#: Metadata nests a few levels (units, grid, rig, source); deeper documents are refused before
#: they reach code that recurses (pydantic, the JSON encoder writing zarr.json, every reader).
MAX_METADATA_DEPTH = 32


def sidecar_for(src: Path) -> Path:
    """Where the sidecar of the recording ``src`` is unless given: ``SRC.json`` or ``SRC/recording.json``."""
    return src / SIDECAR_NAME if src.is_dir() else src.with_suffix(".json")


def parse_metadata(text: str) -> dict:
    """A metadata JSON object: strict JSON (no NaN, no Infinity), at most MAX_METADATA_DEPTH deep."""
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
    stack = [(doc, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_METADATA_DEPTH:
            raise ValueError(f"nested too deeply (at most {MAX_METADATA_DEPTH} levels)")
        children = node.values() if isinstance(node, dict) else node
        stack += [(c, depth + 1) for c in children if isinstance(c, (dict, list))]
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
