"""Arrow schemas built from ``data_specs/schema_v*.yaml`` (the single source of the record layout)."""
from __future__ import annotations

import json
from functools import lru_cache
from typing import Any

import pyarrow as pa

from data_specs import load_schema_spec

from .errors import UslError

SCHEMA_VERSION = 1
KNOWN_VERSIONS = (1,)
METADATA_KEY = b"usl"

_SCALARS = {
    "string": pa.string(),
    "binary": pa.binary(),
    "int32": pa.int32(),
    "int64": pa.int64(),
    "float32": pa.float32(),
    "float64": pa.float64(),
}


def _arrow_type(spec: Any) -> pa.DataType:
    if isinstance(spec, str):
        return _SCALARS[spec]
    if "list" in spec:
        item = _arrow_type(spec["list"])
        return pa.list_(item, spec["size"]) if "size" in spec else pa.list_(item)
    if "struct" in spec:
        return pa.struct([_arrow_field(f) for f in spec["struct"]])
    raise ValueError(f"unknown type spec {spec!r} in the record schema")


def _arrow_field(spec: dict[str, Any]) -> pa.Field:
    return pa.field(spec["name"], _arrow_type(spec["type"]), nullable=bool(spec.get("nullable", False)))


@lru_cache(maxsize=None)
def table_schema(table: str, version: int = SCHEMA_VERSION) -> pa.Schema:
    """Arrow schema of ``frames`` or ``objects`` without dataset metadata."""
    spec = load_schema_spec(version)["tables"][table]
    return pa.schema([_arrow_field(f) for f in spec["fields"]])


def with_metadata(schema: pa.Schema, metadata: dict[str, Any]) -> pa.Schema:
    """Attach the dataset metadata (name, schema version, categories, layout) under key ``usl``."""
    return schema.with_metadata({METADATA_KEY: json.dumps(metadata, sort_keys=True).encode()})


def read_metadata(schema: pa.Schema, path: str) -> dict[str, Any]:
    """Dataset metadata of a shard; refuses unknown schema versions with a clear message."""
    raw = (schema.metadata or {}).get(METADATA_KEY)
    if raw is None:
        raise UslError(f"{path}: not a usl record shard (no '{METADATA_KEY.decode()}' schema metadata)")
    meta = json.loads(raw)
    check_version(meta.get("schema_version"), path)
    return meta


def check_version(version: Any, path: str) -> None:
    if version not in KNOWN_VERSIONS:
        raise UslError(
            f"{path}: record schema version {version!r} is not known to this usl "
            f"(known: {', '.join(map(str, KNOWN_VERSIONS))}); upgrade usl or rebuild the dataset"
        )
