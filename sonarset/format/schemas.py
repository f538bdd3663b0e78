"""The JSON Schemas of the format's documents, generated from their pydantic models (``spec/schema/``)."""

from __future__ import annotations

import json
from typing import Any

from pydantic import BaseModel

from sonarset.format.attrs import FORMAT_VERSION, RunAttrs, StoreAttrs
from sonarset.format.sidecars import RawRecordingMeta, RecordingMeta


SCHEMAS: dict[str, type[BaseModel]] = {
    "store": StoreAttrs,
    "run": RunAttrs,
    "recording": RecordingMeta,
    "raw-recording": RawRecordingMeta,
}


def json_schema(kind: str) -> dict[str, Any]:
    """The JSON Schema of one document kind: 'store', 'run' or 'recording'."""
    if kind not in SCHEMAS:
        raise ValueError(f"unknown schema kind {kind!r}; choose from {', '.join(SCHEMAS)}")
    schema = SCHEMAS[kind].model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = f"https://sonarset.dev/schema/{FORMAT_VERSION}/{kind}.schema.json"
    return schema


def json_schema_text(kind: str) -> str:
    return json.dumps(json_schema(kind), indent=2, sort_keys=True) + "\n"
