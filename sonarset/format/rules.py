"""The format's rules on a store's metadata, each written once (spec/FORMAT.md §3-§5).

Pure functions over parsed documents and values, no I/O: each returns the Problems it finds, with
an empty ``where`` that the store walker (``sonarset.store.root``) fills with the node. The readers
raise the first problem (``raise_first``); ``validate`` lists them all. The rules on arrays are in
``sonarset.format.arrays``, those on names and versions beside their models in ``format.attrs``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import ValidationError

from sonarset.format.attrs import NAMESPACE, RunAttrs, StoreAttrs, version_problems
from sonarset.format.plausibility import command_problems
from sonarset.format.problems import Problem, pydantic_problems

#: Where the SonarSet attributes sit in a node's ``zarr.json``: how problems name their fields.
ATTRS_PREFIX = f"attributes.{NAMESPACE}."
#: How far ``rig.frame_interval_s`` x ``frame_rate_hz`` may stray from 1 (relative).
RIG_RATE_TOLERANCE = 1e-6


def root_document_problems(doc: Any) -> list[Problem]:
    """A root ``zarr.json`` (parsed) must be Zarr v3 group metadata."""
    if not isinstance(doc, dict) or doc.get("zarr_format") != 3:
        return [Problem("zarr.json", "not Zarr v3 metadata (zarr_format must be 3)")]
    if doc.get("node_type") != "group":
        return [Problem("", "root is a zarr array; a SonarSet store is a group")]
    return []


def parse_store_attrs(raw: Any) -> tuple[StoreAttrs | None, list[Problem]]:
    """The root's ``attributes.sonarset``: the model, or None and why not."""
    if not isinstance(raw, dict):
        return None, [Problem("", f"missing root attribute {NAMESPACE!r}: not a SonarSet store")]
    found = version_problems(raw.get("format_version"))
    if found:
        return None, found
    try:
        return StoreAttrs.model_validate(raw), []
    except ValidationError as exc:
        return None, pydantic_problems(exc, ATTRS_PREFIX)


def store_attrs_problems(attrs: StoreAttrs) -> list[Problem]:
    """What the schema alone cannot say about valid root attributes: the rig's frame interval is
    the frame rate's inverse (format 1.1)."""
    rig, rate = attrs.rig, attrs.frame_rate_hz
    if rig is None or math.isclose(rig.frame_interval_s * rate, 1.0, rel_tol=RIG_RATE_TOLERANCE):
        return []
    return [Problem("", f"{ATTRS_PREFIX}rig.frame_interval_s {rig.frame_interval_s:g} s disagrees with "
                        f"frame_rate_hz {rate:g} (1/{rate:g} = {1 / rate:g} s)")]


def parse_run_attrs(raw: Any) -> tuple[RunAttrs | None, list[Problem]]:
    """A run group's ``attributes.sonarset``: the model, or None and why not."""
    if not isinstance(raw, dict):
        return None, [Problem("", f"missing run attribute {NAMESPACE!r}")]
    try:
        return RunAttrs.model_validate(raw), []
    except ValidationError as exc:
        return None, pydantic_problems(exc, ATTRS_PREFIX)


def run_state_problems(attrs: RunAttrs) -> list[Problem]:
    """A run is read only once its writer finished (spec/FORMAT.md §5)."""
    if attrs.complete:
        return []
    return [Problem("", "run is incomplete: its writer did not finish (re-run it or delete the group)")]


def command_limit_problems(velocity: np.ndarray) -> list[Problem]:
    """Commands no ground robot could follow, whatever its rig: a run holding them is unreadable.
    (Commands beyond the store's own rig are only implausible: ``plausibility.command_problems``.)"""
    return command_problems(velocity, None)
